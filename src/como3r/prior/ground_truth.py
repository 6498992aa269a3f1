"""Ground truth as the simulated prior sees it, and where it comes from.

The SLAM system never reads ground truth: a :class:`~como3r.prior.base.View` carries the
image, its agent and frame index, and (calibrated runs only) the user's intrinsics. The
simulated prior, a stand-in for MASt3R made from ground-truth depth, looks up what it needs
by ``(agent, index)`` in a :class:`GroundTruthSource` it is given when it is built: the
agent folders of the run (:class:`como3r.data.ground_truth.AgentFolderTruth`) or, in tests,
an :class:`InMemoryTruth`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from torch import Tensor

from como3r.errors import PriorError


@dataclass(frozen=True)
class GroundTruth:
    """One frame's ground truth at the network resolution of its view.

    Attributes:
        depth: ``(H, W)`` float32 metric z-depth, 0 where unknown; or None.
        K: ``(3, 3)`` float32 true intrinsics at that resolution; or None.
        surface: ``(H, W, 3)`` float32 appearance keys (texture id, s, t), id < 0 for sky;
            or None.
        T_WC: ``(8,)`` ground-truth pose (Sim(3) layout, s = 1); or None.
    """

    depth: Tensor | None = None
    K: Tensor | None = None
    surface: Tensor | None = None
    T_WC: Tensor | None = None


class GroundTruthSource(Protocol):
    """Where the simulated prior finds a frame's ground truth."""

    def truth(self, agent: int, index: int) -> GroundTruth:
        """Ground truth of frame ``index`` of ``agent`` (fields None where it has none).

        Raises:
            PriorError: the source does not know the frame.
        """
        ...


class InMemoryTruth:
    """A :class:`GroundTruthSource` filled by hand (tests, synthetic views)."""

    def __init__(self) -> None:
        self._frames: dict[tuple[int, int], GroundTruth] = {}

    def add(self, agent: int, index: int, truth: GroundTruth) -> None:
        """Record (or replace) the ground truth of one frame."""
        self._frames[(agent, index)] = truth

    def truth(self, agent: int, index: int) -> GroundTruth:
        try:
            return self._frames[(agent, index)]
        except KeyError:
            raise PriorError(f"no ground truth for agent {agent}, frame {index}") from None
