"""What the coordinator writes about itself: ``graph.json``'s document (keyframes, edges
with their scores, candidates, gauge events, components) and ``metrics.json``'s
``coordinator`` section.

:class:`CoordinatorDocuments` is one part of
:class:`~como3r.coordination.coordinator.Coordinator` (its base class): its methods read the
coordinator's graph, candidates, counters and events.
"""

from __future__ import annotations

from dataclasses import asdict
from typing import Any

from como3r.backend.global_graph import GlobalGraph
from como3r.backend.graph_link import GraphLink
from como3r.coordination.association import Candidate
from como3r.coordination.gauge import GaugeComponents
from como3r.coordination.stats import CoordinatorStats


class CoordinatorDocuments:
    """The coordinator's JSON documents (the attributes they read are declared below)."""

    graph: GlobalGraph
    gauges: GaugeComponents
    candidates: list[Candidate]
    gauge_events: list[dict[str, Any]]
    alternation: list[dict[str, Any]]
    stats: CoordinatorStats
    num_agents: int
    retrieval: object | None

    def components(self) -> list[list[int]]:
        """Gauge components (sorted agent lists), agent 0's first."""
        return self.gauges.components()

    def graph_document(self) -> dict[str, Any]:
        """JSON-ready graph: keyframes, intra/inter edges with scores, candidates, components."""
        keyframes = [
            {
                "global": g,
                "agent": self.graph.agent_of[g],
                "keyframe": kf.kf_id,
                "frame": kf.frame_index,
                "timestamp": kf.timestamp,
                "T_WC": kf.T_WC.tolist(),
            }
            for g, kf in enumerate(self.graph.keyframes)
        ]
        return {
            "keyframes": keyframes,
            "edges": [self._link_json(link) for link in self.graph.links],
            "candidates": [self._candidate_json(c) for c in self.candidates],
            "gauge_events": list(self.gauge_events),
            "components": self.components(),
        }

    def metrics(self) -> dict[str, Any]:
        """Counters, timings and gauge events."""
        stats = asdict(self.stats)
        stats["stage_seconds"] = dict(self.stats.stage_seconds)
        stats["gauge_events"] = list(self.gauge_events)
        stats["components"] = self.components()
        stats["cross_agent_retrieval"] = self.retrieval is not None
        stats["alternation"] = list(self.alternation)
        stats["focal_lengths"] = self._focal_lengths()
        return stats

    def _focal_lengths(self) -> dict[str, float]:
        """Each self-calibrated or calibrated agent's focal length in the map [px]."""
        focal = {agent: self.graph.agent_focal(agent) for agent in range(self.num_agents)}
        return {str(agent): f for agent, f in focal.items() if f is not None}

    def _key(self, g: int) -> list[int]:
        """``[agent, kf_id]`` of global keyframe ``g``."""
        return [self.graph.agent_of[g], self.graph.keyframes[g].kf_id]

    def _link_json(self, link: GraphLink) -> dict[str, Any]:
        document: dict[str, Any] = {
            "type": link.kind,
            "from": self._key(link.i),
            "to": self._key(link.j),
            "global": [link.i, link.j],
            "nu_i": link.link.ji.match_fraction,
            "nu_j": link.link.ij.match_fraction,
        }
        if link.similarity is not None:
            document["similarity"] = link.similarity
        return document

    def _candidate_json(self, c: Candidate) -> dict[str, Any]:
        v = c.verification
        return {
            "from": list(v.candidate),
            "to": list(v.query),
            "similarity": v.similarity,
            "nu_i": v.nu_i,
            "nu_j": v.nu_j,
            "covisible_ratio": v.covisible_ratio,
            "verified": v.accepted,
            "status": c.status,
            "residual_ratio": None if c.residual_ratio != c.residual_ratio else c.residual_ratio,
        }
