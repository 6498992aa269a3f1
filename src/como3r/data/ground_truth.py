"""The simulated prior's ground truth read from the agent folders of a run.

Only :class:`como3r.prior.simulated.SimulatedPrior` holds one of these: the runtime builds
it with the run's agent inputs and hands it to the prior, so depth maps, surface maps,
ground-truth poses and the true intrinsics never travel with a frame through the system.
The runtime asks :func:`encodable` which frames the prior can encode (a frame without a
ground-truth pose is skipped, :func:`skipped_warning` counts them once).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from como3r.data.agent_input import AgentInput
from como3r.data.preprocess import frame_ground_truth
from como3r.errors import PriorError
from como3r.prior.ground_truth import GroundTruth


class AgentFolderTruth:
    """A :class:`~como3r.prior.ground_truth.GroundTruthSource` over agent inputs.

    Args:
        agents: agent id -> its input (the ids the views carry).
        long_side: the run's ``input.long_side`` (the views' resolution).
    """

    def __init__(self, agents: Mapping[int, AgentInput], long_side: int) -> None:
        self.agents = dict(agents)
        self.long_side = long_side

    def truth(self, agent: int, index: int) -> GroundTruth:
        """Frame ``index`` of ``agent``'s folder, resized as its view was (depth, surface,
        the folder's calib.txt as K, the ground-truth pose)."""
        source = self.agents.get(agent)
        if source is None:
            raise PriorError(f"simulated prior: no input folder for agent {agent}")
        return frame_ground_truth(source.load_frame(index), self.long_side, source.calib)


def encodable(source: AgentInput) -> np.ndarray:
    """``(N,)`` bool: the frames the simulated prior can encode. Every frame with surface
    maps (appearance keys) or without any ground truth (the prior then says what is
    missing); otherwise those with a ground-truth pose
    (:attr:`~como3r.data.agent_input.AgentInput.has_gt_pose`: not before the first sample, after
    the last or in a gap wider than :data:`como3r.data.poses.MAX_GAP`)."""
    if source.has_surface or source.groundtruth is None:
        return np.ones(source.num_frames, dtype=bool)
    return source.has_gt_pose


def skipped_warning(source: AgentInput) -> str | None:
    """The one warning line for the frames :func:`encodable` leaves out, or None."""
    line = None if source.has_surface else source.missing_gt_warning()
    return None if line is None else f"{line}; --prior simulated skips them"
