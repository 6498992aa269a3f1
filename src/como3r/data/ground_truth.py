"""The simulated prior's ground truth read from the agent folders of a run.

Only :class:`como3r.prior.simulated.SimulatedPrior` holds one of these: the runtime builds
it with the run's agent inputs and hands it to the prior, so depth maps, surface maps,
ground-truth poses and the true intrinsics never travel with a frame through the system.
"""

from __future__ import annotations

from typing import Mapping

from como3r.data.agent import AgentInput
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
