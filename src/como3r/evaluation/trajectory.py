"""Trajectory accuracy through evo: ATE and RPE per agent, and a merged ATE for the team.

The protocol is the papers' (C-Sec. B.5): each agent's estimate is associated with its own
ground truth by timestamp, aligned with one closed-form Sim(3) (Umeyama, evo's
``align(..., correct_scale=True)``), and the Absolute Trajectory Error is the RMSE of the
camera-centre differences after alignment. Everything numeric is delegated to evo so the
numbers equal what ``evo_ape tum GT EST -as`` prints.

The merged ATE aligns the associated poses of ALL agents with ONE Sim(3). Per-agent ATE
hides gauge errors between agents (each agent gets its own alignment); the merged ATE does
not, so it measures whether the team built one consistent map. Association is always per
agent against that agent's own ground truth: agents' timestamps overlap, so sorting all
poses by time and associating once would pair one agent's estimate with another's truth.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from evo import EvoException
from evo.core import metrics, sync
from evo.core.trajectory import PosePath3D, PoseTrajectory3D

from como3r.errors import InputError
from como3r.io.tum import Trajectory

logger = logging.getLogger(__name__)

#: evo's default association window [s] (``evo_ape --t_max_diff``).
MAX_TIME_DIFF = 0.01
#: Fewest associated poses a Sim(3) alignment and an RMSE are computed from.
MIN_ASSOCIATED = 3
#: Second over first principal spread below which positions count as collinear.
COLLINEAR_RATIO = 1e-6
#: RPE step: consecutive associated frames.
RPE_DELTA_FRAMES = 1


@dataclass(frozen=True)
class Sim3Alignment:
    """The similarity that maps estimated positions onto ground truth: ``p_gt ~ s R p_est + t``.

    Attributes:
        rotation: ``(3, 3)`` rotation R.
        translation: ``(3,)`` translation t [m, ground-truth frame].
        scale: scale s (ground-truth metres per estimated unit).
    """

    rotation: np.ndarray
    translation: np.ndarray
    scale: float

    def apply(self, positions: np.ndarray) -> np.ndarray:
        """Map ``(N, 3)`` estimated positions into the ground-truth frame."""
        return self.scale * positions @ self.rotation.T + self.translation

    @classmethod
    def from_json(cls, document: dict[str, object]) -> Sim3Alignment:
        """The alignment :meth:`to_json` wrote (``ate.json``)."""
        return cls(
            np.asarray(document["rotation"], dtype=np.float64),
            np.asarray(document["translation"], dtype=np.float64),
            float(document["scale"]),
        )  # type: ignore[arg-type]

    def to_json(self) -> dict[str, object]:
        return {
            "scale": self.scale,
            "rotation": self.rotation.tolist(),
            "translation": self.translation.tolist(),
        }


@dataclass(frozen=True)
class ErrorStats:
    """Statistics of one error array as evo reports them (units of the metric)."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float

    @classmethod
    def of(cls, metric: metrics.PE) -> ErrorStats:
        stats = metric.get_all_statistics()
        return cls(**{name: float(stats[name]) for name in cls.__dataclass_fields__})

    def to_json(self) -> dict[str, float]:
        return {name: getattr(self, name) for name in self.__dataclass_fields__}


@dataclass(frozen=True)
class AssociatedPair:
    """An agent's estimate and ground truth reduced to the poses matched by timestamp.

    Attributes:
        est: evo trajectory of the associated estimated poses (not aligned).
        gt: evo trajectory of the matching ground-truth poses, same length as ``est``.
        est_name: where the estimate came from (a file name), for messages.
        gt_name: where the ground truth came from.
        est_total: number of estimated poses before association.
    """

    est: PoseTrajectory3D
    gt: PoseTrajectory3D
    est_name: str
    gt_name: str
    est_total: int

    def __len__(self) -> int:
        return int(self.est.num_poses)


@dataclass(frozen=True)
class AgentErrors:
    """ATE and RPE of one agent after its own Sim(3) alignment.

    Attributes:
        frames: number of associated poses the errors are computed over.
        ate: absolute translation error statistics [m].
        rpe_trans: relative translation error between consecutive frames [m].
        rpe_rot_deg: relative rotation angle error between consecutive frames [deg].
        alignment: the Sim(3) that aligned the estimate to ground truth.
    """

    frames: int
    ate: ErrorStats
    rpe_trans: ErrorStats
    rpe_rot_deg: ErrorStats
    alignment: Sim3Alignment


@dataclass(frozen=True)
class MergedErrors:
    """ATE of several agents under ONE shared Sim(3) alignment.

    Attributes:
        agents: the agent indices whose associated poses were stacked.
        frames: total number of associated poses.
        ate: absolute translation error statistics over all stacked poses [m].
        alignment: the single Sim(3) that aligned all of them.
    """

    agents: tuple[int, ...]
    frames: int
    ate: ErrorStats
    alignment: Sim3Alignment


def to_evo(trajectory: Trajectory, name: str = "") -> PoseTrajectory3D:
    """An evo trajectory of a como3r :class:`Trajectory` (the Sim(3) scale column is ignored;
    TUM poses carry scale 1)."""
    poses = trajectory.T_WC.detach().to("cpu").double().numpy()
    quat_wxyz = poses[:, [6, 3, 4, 5]]
    return PoseTrajectory3D(
        positions_xyz=poses[:, :3].copy(),
        orientations_quat_wxyz=quat_wxyz,
        timestamps=trajectory.timestamps.copy(),
        name=name,
    )


def associate(
    est: Trajectory,
    gt: Trajectory,
    est_name: str,
    gt_name: str,
    max_diff: float = MAX_TIME_DIFF,
) -> AssociatedPair:
    """Match estimated and ground-truth poses by nearest timestamp (evo's association).

    Raises:
        InputError: fewer than :data:`MIN_ASSOCIATED` poses match; names both files.
    """
    gt_evo, est_evo = to_evo(gt, gt_name), to_evo(est, est_name)
    try:
        gt_sync, est_sync = sync.associate_trajectories(gt_evo, est_evo, max_diff=max_diff)
        matched = est_sync.num_poses
    except sync.SyncException:
        matched = 0
    if matched < MIN_ASSOCIATED:
        raise InputError(
            f"{est_name}: only {matched} pose(s) match a ground-truth timestamp in {gt_name} "
            f"within {max_diff} s (need {MIN_ASSOCIATED})"
        )
    if matched < len(est):
        logger.info("%s: %d of %d poses associated with %s", est_name, matched, len(est), gt_name)
    return AssociatedPair(est_sync, gt_sync, est_name, gt_name, len(est))


def is_collinear(positions: np.ndarray) -> bool:
    """Whether ``(N, 3)`` positions lie on one line (or one point) up to file rounding."""
    spread = np.linalg.svd(positions - positions.mean(axis=0), compute_uv=False)
    return bool(spread[0] == 0.0 or spread[1] < COLLINEAR_RATIO * spread[0])


def align_sim3(est: PosePath3D, gt: PosePath3D, what: str) -> tuple[PosePath3D, Sim3Alignment]:
    """A Sim(3)-aligned copy of ``est`` (Umeyama through evo, C-Sec. B.5) and the alignment.

    Raises:
        InputError: the positions are degenerate (all equal or collinear); ``what`` names them.
    """
    # evo only rejects exactly rank-deficient covariances; a line written to a TUM file with
    # 9 decimals passes that test and yields an arbitrary rotation about the line.
    for name, path in (("estimated", est), ("ground-truth", gt)):
        if is_collinear(path.positions_xyz):
            raise InputError(
                f"{what}: degenerate Sim(3) alignment, the {name} positions are "
                f"constant or collinear"
            )
    aligned = copy.deepcopy(est)
    try:
        rotation, translation, scale = aligned.align(gt, correct_scale=True)
    except EvoException as exc:
        raise InputError(
            f"{what}: cannot Sim(3)-align the estimate to ground truth ({exc})"
        ) from None
    alignment = Sim3Alignment(np.asarray(rotation), np.asarray(translation), float(scale))
    if not (np.isfinite(alignment.scale) and alignment.scale > 0.0):
        raise InputError(f"{what}: degenerate Sim(3) alignment (scale {alignment.scale})")
    return aligned, alignment


def _ape(gt: PosePath3D, est_aligned: PosePath3D) -> ErrorStats:
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((gt, est_aligned))
    return ErrorStats.of(ape)


def _rpe(gt: PosePath3D, est_aligned: PosePath3D, relation: metrics.PoseRelation) -> ErrorStats:
    rpe = metrics.RPE(relation, delta=RPE_DELTA_FRAMES, delta_unit=metrics.Unit.frames)
    rpe.process_data((gt, est_aligned))
    return ErrorStats.of(rpe)


def agent_errors(pair: AssociatedPair) -> AgentErrors:
    """ATE and RPE (delta 1 frame) of one agent after its own Sim(3) alignment.

    Raises:
        InputError: degenerate alignment (names the estimate and ground-truth files).
    """
    what = f"{pair.est_name} vs {pair.gt_name}"
    est_aligned, alignment = align_sim3(pair.est, pair.gt, what)
    return AgentErrors(
        frames=len(pair),
        ate=_ape(pair.gt, est_aligned),
        rpe_trans=_rpe(pair.gt, est_aligned, metrics.PoseRelation.translation_part),
        rpe_rot_deg=_rpe(pair.gt, est_aligned, metrics.PoseRelation.rotation_angle_deg),
        alignment=alignment,
    )


def _stack(paths: Sequence[PosePath3D]) -> PosePath3D:
    return PosePath3D(poses_se3=[pose for path in paths for pose in path.poses_se3])


def merged_errors(pairs: Sequence[AssociatedPair], agents: Sequence[int]) -> MergedErrors:
    """ATE of the given agents' associated poses under ONE Sim(3) alignment.

    Each pair was associated with its own ground truth; here the pairs are only stacked, so
    overlapping timestamps of different agents never mix.

    Args:
        pairs: associated pairs of every agent, indexed by agent.
        agents: which agents to stack.

    Raises:
        InputError: degenerate alignment.
    """
    chosen = [pairs[a] for a in agents]
    est, gt = _stack([p.est for p in chosen]), _stack([p.gt for p in chosen])
    what = "merged " + ", ".join(p.est_name for p in chosen)
    est_aligned, alignment = align_sim3(est, gt, what)
    return MergedErrors(tuple(agents), int(est.num_poses), _ape(gt, est_aligned), alignment)


def validate_components(components: Sequence[Sequence[int]], num_agents: int) -> None:
    """Check that ``components`` are disjoint groups of agent indices in ``[0, num_agents)``.

    Raises:
        InputError: an index out of range or listed twice.
    """
    seen: set[int] = set()
    for component in components:
        for agent in component:
            if not 0 <= agent < num_agents:
                raise InputError(
                    f"components: agent {agent} is out of range for {num_agents} agents"
                )
            if agent in seen:
                raise InputError(f"components: agent {agent} is in more than one component")
            seen.add(agent)


def merged_errors_by_component(
    pairs: Sequence[AssociatedPair], components: Sequence[Sequence[int]] | None = None
) -> list[MergedErrors]:
    """Merged ATE of every gauge component with more than one agent.

    Args:
        pairs: associated pairs of every agent, indexed by agent.
        components: groups of agents that share one gauge (one world frame). ``None`` means
            all agents share one: the result is then a single entry over all agents (for
            one agent it equals that agent's ATE).
    """
    if components is None:
        return [merged_errors(pairs, range(len(pairs)))]
    validate_components(components, len(pairs))
    return [merged_errors(pairs, sorted(c)) for c in components if len(c) > 1]
