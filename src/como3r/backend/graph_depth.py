"""The depth step of the terminal alternation on the coordinator's global graph (C-Sec. A.6,
A.7; C-Eq. 19-24): every keyframe's fused pointmap made the refinement's base, the label
maps of the segments, and one refinement of the keyframes' log-scales at the current poses,
written back (parked for paged-out keyframes).

:class:`GraphDepthSteps` is one part of :class:`~como3r.backend.global_graph.GlobalGraph`
(its base class): its methods read the graph's keyframes and links and write their
pointmaps.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path

from torch import Tensor

from como3r.backend.depth_refinement import DepthRefinementReport
from como3r.backend.graph_link import GraphLink
from como3r.backend.paged_refinement import (
    LabelMaps,
    Pointmaps,
    chunk_edges,
    refine_in_chunks,
)
from como3r.backend.segments import labels_in_order
from como3r.config import DepthRefinementConfig
from como3r.frontend.graph import Edge
from como3r.frontend.keyframes import Keyframe
from como3r.frontend.paging import KeyframeParking, paged_out, read_fields


class GraphDepthSteps:
    """The depth steps of the :class:`~como3r.backend.global_graph.GlobalGraph` (the graph's
    attributes they use are declared below; they also call its ``connected`` and ``poses``)."""

    keyframes: list[Keyframe]
    local_to_global: dict[int, list[int]]
    links: list[GraphLink]
    versions: list[int]
    fixed: set[int]

    def freeze_refinement_base(
        self, agents: Sequence[int], parking: KeyframeParking | None = None
    ) -> None:
        """Make every keyframe's current fused pointmap the base ``X_init`` of C-Eq. 19.

        C-Eq. 19 rebuilds each refined point from the insertion-time prediction, which
        throws away what the fusion of C-Eq. 3 averaged in: on the simulated prior's scenes
        the fused maps carry about two thirds of a single prediction's depth distortion, and
        per-segment refinement from the insertion snapshot ended with a LARGER map error
        than it started with (``depth.refine_from``; the closing note of issue 6).

        Args:
            parking: where paged-out keyframes' new base goes (None: into the keyframes).
        """
        for a in agents:
            for g in self.local_to_global.get(a, []):
                kf = self.keyframes[g]
                self._set_pointmaps(g, {"X_init": read_fields(kf, "X_hat")}, parking)

    def segment(
        self,
        agents: Sequence[int],
        anchor: int,
        config: DepthRefinementConfig,
        parking: KeyframeParking | None = None,
    ) -> LabelMaps:
        """Label maps (C-Sec. A.6) of the keyframes reachable from ``anchor``, by global
        index; a paged-out keyframe's kept in ``parking`` (None: all in memory)."""

        def pointmaps() -> Iterator[tuple[int, Tensor, Tensor]]:
            for g in self.connected(agents, anchor):
                kf = self.keyframes[g]
                X_hat, C_hat = read_fields(kf, "X_hat", "C_hat")
                yield g, X_hat, C_hat / kf.fused_frames

        labels = LabelMaps(parking)
        for g, label_map in labels_in_order(pointmaps(), config):  # on this process's threads
            labels.keep(g, label_map, parked=paged_out(self.keyframes[g]))
        return labels

    def refine_depths(
        self,
        agents: Sequence[int],
        anchor: int,
        config: DepthRefinementConfig,
        labels: Mapping[int, Tensor],
        parking: KeyframeParking | None = None,
        spill_dir: Path | None = None,
    ) -> DepthRefinementReport:
        """One depth step (C-Sec. A.7 step 2b-2c; C-Eq. 19-24) at the current poses.

        The log-scales of the keyframes reachable from ``anchor`` are refined over the
        links' intra- and inter-agent matches with ``anchor``'s segments (and the
        :attr:`fixed` keyframes') fixed, and the refined pointmaps written back into
        ``X_hat``. The data term is summed over working sets of keyframes
        (:mod:`.paged_refinement`): a paged-out keyframe is read back when its working set
        is built (once per step), and its refined pointmap parked (with ``parking``), so the
        step holds a working set of pointmaps and matches at a time, not the map.

        Args:
            labels: global index -> label map (:meth:`segment`) of every reachable keyframe.
            parking: where paged-out keyframes' refined pointmaps go (None: into the
                keyframes).
            spill_dir: where the flattened problems of working sets with paged-out
                keyframes are spilled during the step (None: the system's temporary folder).
        """
        nodes = self.connected(agents, anchor)
        row = {g: r for r, g in enumerate(nodes)}
        links = [link for link in self.links if link.i in row and link.j in row]

        def edges(chosen: Sequence[int]) -> list[Edge]:
            return [
                Edge(row[e.i], row[e.j], e.matches, e.kind)
                for n in chosen
                for e in links[n].edges()
            ]

        def read(r: int) -> Pointmaps:
            return Pointmaps(*read_fields(self.keyframes[nodes[r]], "X_hat", "X_init"))

        return refine_in_chunks(
            len(nodes),
            read,
            self.poses(nodes),
            chunk_edges([(row[link.i], row[link.j]) for link in links], edges),
            lambda r: labels[nodes[r]],
            config,
            lambda r, X: self._set_pointmaps(nodes[r], {"X_hat": X}, parking),
            pinned=[row[g] for g in nodes if g == anchor or g in self.fixed],
            # a chunk of resident keyframes keeps its problem in memory; one with paged-out
            # keyframes is spilled, or the step would hold the whole map's problem
            keep=lambda rows: not any(paged_out(self.keyframes[nodes[r]]) for r in rows),
            spill_dir=spill_dir,
        )

    def _set_pointmaps(
        self, g: int, values: dict[str, Tensor], parking: KeyframeParking | None
    ) -> None:
        """Set pointmap fields of keyframe ``g``: parked if it is paged out and a parking is
        given, else in the keyframe."""
        kf = self.keyframes[g]
        if "X_hat" in values:
            self.versions[g] += 1
        if parking is not None and paged_out(kf):
            parking.park(kf, values)
            return
        for name, value in values.items():
            setattr(kf, name, value)
