"""The coordinator's terminal cleanup (C-Sec. A.7; :meth:`Coordinator.finish
<como3r.coordination.coordinator.Coordinator.finish>`): what it hands back to the agents
(:class:`Cleanup`), the keyframes as they were before the depth refinement
(:class:`MapSnapshot`), and the two solvers of one component's pose-depth alternation
(:class:`ComponentCleanup`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from torch import Tensor

from como3r.backend.depth_refinement import DepthRefinementReport
from como3r.backend.global_graph import BAResult, GlobalGraph
from como3r.config import DepthRefinementConfig
from como3r.frontend.keyframes import Keyframe
from como3r.frontend.packets import PointmapUpdate, PoseUpdate
from como3r.frontend.paging import KeyframeParking, paged_out, read_fields
from como3r.progress import PhaseCallback, PhaseEvent


@dataclass
class Cleanup:
    """What the terminal cleanup (C-Sec. A.7) hands back to the agents.

    Attributes:
        updates: final poses of the agents of multi-agent components.
        refined: the agents whose pointmaps the depth refinement refined.
        pointmap_update: an agent's refined pointmaps, read when asked for (a whole map of
            them would not fit a bounded memory).
    """

    updates: list[PoseUpdate] = field(default_factory=list)
    refined: list[int] = field(default_factory=list)
    pointmap_update: Callable[[int], PointmapUpdate] | None = None

    @property
    def pointmaps(self) -> Iterator[PointmapUpdate]:
        """Refined canonical pointmaps of every refined agent, one update at a time."""
        return (self.pointmap_update(agent) for agent in self.refined)


@dataclass(frozen=True)
class MapSnapshot:
    """What a fused map reads of a keyframe (:func:`como3r.runtime.outputs.fused_map`), as
    it was before the terminal depth refinement; not its encoding, first prediction or
    retrieval features, which a copy of the keyframe would read back from a paged-out
    graph and hold for the whole map (~0.5 MB per keyframe at 64x48, 326 KB of it the
    simulated prior's encoding). A paged-out keyframe's arrays are kept in the cleanup's
    parking and read back when asked for.

    Attributes:
        T_WC: ``(8,)`` pose; fused_frames: how many frames contributed.
        arrays: ``(X_hat (H, W, 3), C_hat (H, W), colors (H, W, 3) uint8)``: the fused
            pointmap, its accumulated confidence and the image; None: in ``parking``.
        parking: where the arrays are kept when ``arrays`` is None, as keyframe ``key``.
    """

    T_WC: Tensor
    fused_frames: int
    arrays: tuple[Tensor, Tensor, np.ndarray] | None
    parking: KeyframeParking | None = None
    key: int = -1

    @classmethod
    def of(cls, kf: Keyframe, parking: KeyframeParking, key: int) -> MapSnapshot:
        """The snapshot of ``kf`` (global index ``key``) now, its pose copied (the cleanup
        moves it in place); a paged-out keyframe's arrays go to ``parking``."""
        if not paged_out(kf):
            return cls(kf.T_WC.clone(), kf.fused_frames, (kf.X_hat, kf.C_hat, kf.colors))
        X_hat, C_hat, colors = read_fields(kf, "X_hat", "C_hat", "colors")
        parking.put(key, "snapshot", {"X_hat": X_hat, "C_hat": C_hat, "colors": colors})
        return cls(kf.T_WC.clone(), kf.fused_frames, None, parking, key)

    def _arrays(self) -> tuple[Tensor, Tensor, np.ndarray]:
        if self.arrays is not None:
            return self.arrays
        kept = self.parking.get(self.key, "snapshot")
        return kept["X_hat"], kept["C_hat"], kept["colors"]

    @property
    def X_hat(self) -> Tensor:
        return self._arrays()[0]

    @property
    def C_hat(self) -> Tensor:
        return self._arrays()[1]

    @property
    def colors(self) -> np.ndarray:
        return self._arrays()[2]

    def mean_confidence(self) -> Tensor:
        """``(H, W)`` confidence per contributing frame (:meth:`Keyframe.mean_confidence`)."""
        return self.C_hat / self.fused_frames


class ComponentCleanup:
    """The two solvers of one component's alternation (C-Sec. A.7) and their records.

    Keyframes paged out when the cleanup starts stay paged out (issue 14, bounded memory):
    the depth steps read them a working set at a time and park what they change
    (:class:`~como3r.frontend.paging.KeyframeParking`), which the session store takes at
    the end; a pose pass, which reads every pointmap of the component, lets go of them
    after it.

    Args:
        graph: the global graph.
        members: the component's agents.
        anchor: global index of its pinned keyframe.
        depth: the depth-refinement settings.
        parking: where paged-out keyframes' changed pointmaps, labels and snapshots go.
        spill_dir: where the depth steps spill the problems of working sets with paged-out
            keyframes (``session.spill_dir``; None: the system's temporary folder).
    """

    def __init__(
        self,
        graph: GlobalGraph,
        members: Sequence[int],
        anchor: int,
        depth: DepthRefinementConfig,
        parking: KeyframeParking,
        spill_dir: Path | None = None,
    ) -> None:
        self.graph, self.members, self.anchor, self.depth = graph, members, anchor, depth
        self.parking, self.spill_dir = parking, spill_dir
        self.results: list[BAResult] = []
        self.depth_reports: list[DepthRefinementReport] = []
        self.snapshot: dict[int, list[MapSnapshot]] = {}
        self.labels: Mapping[int, Tensor] = {}
        self.paged = [
            graph.keyframes[g]
            for a in members
            for g in graph.agent_keyframes(a)
            if paged_out(graph.keyframes[g])
        ]

    def pose_pass(self, max_iters: int) -> float:
        """A global pose solve; its largest camera move over the component's scene depth
        (0 if it kept the poses)."""
        result = self.graph.optimize(self.members, self.anchor, max_iters)
        self.results.append(result)
        change = (
            result.max_translation_change / self.graph.scene_depth(self.members)
            if result.moved
            else 0.0
        )
        for kf in self.paged:
            kf.release()
        return change

    def depth_step(self) -> float:
        """Segments, log-scale refinement, write-back; its ``max |ds|``."""
        graph, parking = self.graph, self.parking
        if not self.snapshot:
            self.snapshot = {
                a: [
                    MapSnapshot.of(graph.keyframes[g], parking, g) for g in graph.agent_keyframes(a)
                ]
                for a in self.members
            }
            if self.depth.refine_from == "fused":
                graph.freeze_refinement_base(self.members, parking)
            self.labels = graph.segment(self.members, self.anchor, self.depth, parking)
        report = graph.refine_depths(
            self.members, self.anchor, self.depth, self.labels, parking, spill_dir=self.spill_dir
        )
        self.depth_reports.append(report)
        return report.max_change


def scoped_progress(progress: PhaseCallback | None, members: Sequence[int]) -> PhaseCallback | None:
    """``progress`` naming a component's agents at the start of every event's detail."""
    if progress is None:
        return None
    agents = ("agents " if len(members) > 1 else "agent ") + ", ".join(map(str, members))

    def report(event: PhaseEvent) -> None:
        progress(replace(event, detail="; ".join(filter(None, (agents, event.detail)))))

    return report
