"""Non-linear least squares over Sim(3) poses (C-Sec. B.2), GTSAM-style.

* :mod:`~como3r.optim.values` — ``PoseValues``: the poses and which are pinned;
* :mod:`~como3r.optim.factors` — ``RelativePoseFactors``: dense relative-pose factor
  batches that linearize into 7x7 edge blocks, and their quadratic models;
* :mod:`~como3r.optim.match_factors` — its two residuals, ``RayRangeFactors`` (C-Eq. 6)
  and ``CalibratedFactors`` (C-Eq. 17);
* :mod:`~como3r.optim.system` — ``EdgeBlocks`` and their assembly into the block normal
  equations (``BlockSystem``);
* :mod:`~como3r.optim.linear` — the damped solve of C-Eq. 25 (dense,
  sparse, or :mod:`~como3r.optim.pcg` conjugate gradients with a block-Jacobi or the
  :mod:`~como3r.optim.band` two-level preconditioner, the default on large graphs;
  Tikhonov escalation);
* :mod:`~como3r.optim.optimizer` — ``levenberg_marquardt_irls`` (tracking, C-Eq. 2) and
  ``gauss_newton_irls`` (local solve and global BA, C-Eq. 5).
"""

from como3r.optim.factors import Factor, RelativePoseFactors
from como3r.optim.linear import LinearSolution, SolveStatus, solve
from como3r.optim.match_factors import CalibratedFactors, RayRangeFactors
from como3r.optim.optimizer import SolveReport, gauss_newton_irls, levenberg_marquardt_irls
from como3r.optim.system import BlockSystem, EdgeBlocks, assemble
from como3r.optim.values import PoseValues

__all__ = [
    "BlockSystem",
    "CalibratedFactors",
    "EdgeBlocks",
    "Factor",
    "LinearSolution",
    "PoseValues",
    "RayRangeFactors",
    "RelativePoseFactors",
    "SolveReport",
    "SolveStatus",
    "assemble",
    "gauss_newton_irls",
    "levenberg_marquardt_irls",
    "solve",
]
