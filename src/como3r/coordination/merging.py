"""Gauge merges (C-Sec. A.4, C-Eq. 14-15): a verified edge between two agents' gauge
components waits until ``gauge.min_consistent_edges`` edges between them agree on one
transform ``T*``, which then carries the moving component into the anchor's gauge; edges
still waiting when the stream ends merge on the set most of them agree with.

:class:`GaugeMerging` is a base of :class:`~.linking.InterAgentLinking` (and so of the
:class:`~como3r.coordination.coordinator.Coordinator`): it moves the coordinator's poses,
aligns the moving agents' focal lengths (its part :mod:`.focal_alignment`) and admits the
supporting edges with the linking's ``_add_inter_link`` and ``_admit_within``.
"""

from __future__ import annotations

import logging
import time

from como3r.coordination.association import Candidate
from como3r.coordination.gauge import GaugeTransform, transport
from como3r.coordination.gauge_geometry import GaugeGeometry
from como3r.frontend.packets import PoseUpdate

# the coordinator's logger: its messages read as they did before this part had a module
logger = logging.getLogger("como3r.coordination.coordinator")


class GaugeMerging(GaugeGeometry):
    """Merges of gauge components (the coordinator's attributes it uses are declared below;
    it also calls the linking's and the coordinator's helpers)."""

    _waiting: list[Candidate]

    def _try_merge(self, candidate: Candidate) -> list[PoseUpdate]:
        """Merge the two components of ``candidate`` once enough waiting edges between them
        agree with its transform (``gauge.min_consistent_edges``)."""
        needed = self.config.gauge.min_consistent_edges
        start = time.perf_counter()
        with self._poses_held():
            supporters = [candidate]
            if needed > 1:
                supporters = self._scale_supporters(self._agreeing(candidate))
            transform = self._gauge_transform(supporters) if len(supporters) >= needed else None
        self.stats.add_time("gauge", time.perf_counter() - start)
        return [] if transform is None else self._merge(candidate, supporters, transform)

    def _agreeing(self, candidate: Candidate) -> list[Candidate]:
        """``candidate`` and the waiting edges between the same two components that agree
        with its transform (:meth:`_agrees`)."""
        hypothesis = self._gauge_transform([candidate])
        return [candidate] + [
            c
            for c in self._waiting
            if c is not candidate
            and self._roots(c) == self._roots(candidate)
            and self._agrees(c, hypothesis)
        ]

    def _merge_waiting(self) -> list[PoseUpdate]:
        """At the end of the stream, merge the components that edges still wait between
        (fewer than ``gauge.min_consistent_edges`` agreed) on their best-supported set.

        The wait keeps a single look-alike from merging two maps while true edges may still
        come; when none came, a lone edge is all there is, and the paper's rule (synchronize
        on the first verified edge, C-Sec. A.4) applies. Between two components the edge
        set that agrees with the most waiting edges merges them, provided no edge outside
        it has as much support: two disagreeing edges of one support each leave the maps
        apart (logged), as no edge can tell which is wrong.
        """
        updates: list[PoseUpdate] = []
        ambiguous: set[tuple[int, int]] = set()
        while True:
            apart = [
                c
                for c in self._waiting
                if not self._same_component(c) and self._roots(c) not in ambiguous
            ]
            if not apart:
                return updates
            with self._poses_held():
                support = [self._agreeing(c) for c in apart]
                best = max(range(len(apart)), key=lambda n: len(support[n]))
                roots, chosen = self._roots(apart[best]), support[best]
                rivals = [
                    n
                    for n, c in enumerate(apart)
                    if self._roots(c) == roots and not any(c is s for s in chosen)
                ]
                supporters = self._scale_supporters(chosen)
                transform = self._gauge_transform(supporters) if supporters else None
            if transform is None or any(len(support[n]) >= len(chosen) for n in rivals):
                ambiguous.add(roots)
                logger.warning(
                    "coordinator: components %d and %d stay apart: their %d waiting edges "
                    "disagree, none with more support than the others",
                    *roots,
                    len(rivals) + len(chosen),
                )
                continue
            updates.extend(self._merge(apart[best], supporters, transform))

    def _merge(
        self, candidate: Candidate, supporters: list[Candidate], transform: GaugeTransform
    ) -> list[PoseUpdate]:
        """Transport the moving component of ``candidate`` by ``transform``, the ``T*`` of
        ``supporters`` (C-Eq. 14-15), admit them, and test the other waiting edges now
        inside one component like any such edge."""
        start = time.perf_counter()
        anchor_root, moved_root = self._roots(candidate)
        moved_agents = self.gauges.members(moved_root)
        for agent in moved_agents:
            indices = self.graph.agent_keyframes(agent)
            self.graph.set_poses(indices, transport(transform.T, self.graph.poses(indices)))
        log_focal = self._align_focal(supporters, moved_agents)
        self.gauges.union(anchor_root, moved_root)
        self._record_gauge_event(transform, anchor_root, moved_agents, supporters, log_focal)
        self.stats.gauge_syncs += 1
        self.stats.add_time("gauge", time.perf_counter() - start)
        for c in supporters:
            self._add_inter_link(c)
        inside = [c for c in self._waiting if self._same_component(c) and c not in supporters]
        self._waiting = [c for c in self._waiting if not self._same_component(c)]
        for c in inside:
            self._admit_within(c)
        return self._updates(moved_agents, "gauge")
