"""The geometry of an edge between two agents' gauge components (C-Sec. A.4, C-Eq. 14):
its matched points lifted into the world, oriented from the moving component to the
anchor, the transform ``T*`` edges between the same two components agree on, and the
record of a merge.

:class:`GaugeGeometry` is a base of :class:`~.linking.InterAgentLinking` (and so of the
:class:`~como3r.coordination.coordinator.Coordinator`): its methods read the coordinator's
graph, gauge components and configuration, count in its ``stats`` and append to its
``gauge_events``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any, TypeVar

import torch
from torch import Tensor

from como3r.backend.global_graph import GlobalGraph
from como3r.config import Config
from como3r.coordination.association import Candidate
from como3r.coordination.gauge import (
    GaugeComponents,
    GaugeTransform,
    lift,
    residual_ratio,
    solve_gauge_transform,
)
from como3r.coordination.stats import CoordinatorStats
from como3r.frontend.pairs import matched_points
from como3r.geometry.lie import sim3_act_points

T = TypeVar("T")

# the coordinator's logger: its messages read as they did before this part had a module
logger = logging.getLogger("como3r.coordination.coordinator")


class GaugeGeometry:
    """Edges between gauge components, in the world (the coordinator's attributes it uses
    are declared below; it also names keyframes with the coordinator's ``_key``)."""

    config: Config
    graph: GlobalGraph
    gauges: GaugeComponents
    gauge_events: list[dict[str, Any]]
    stats: CoordinatorStats
    #: lifted correspondences and transforms by candidate ids while poses hold still
    #: (:meth:`_poses_held`); None outside
    _held: dict[tuple[Any, ...], Any] | None = None

    @contextmanager
    def _poses_held(self) -> Iterator[None]:
        """While no pose, pointmap or component changes, an edge's lifted correspondences
        and a set of edges' ``T*`` are computed once: a merge decision tests the same edges
        for agreement, for scale and for the merge itself (issue 41: at 16 agents the
        recomputation was the largest serial part of the coordinator). Nothing may move a
        keyframe inside the block."""
        outer = self._held
        self._held = {} if outer is None else outer
        try:
            yield
        finally:
            self._held = outer

    def _once(self, key: tuple[Any, ...], compute: Callable[[], T]) -> T:
        """``compute()``, computed once per ``key`` while poses are held (:meth:`_poses_held`);
        every time outside."""
        if self._held is None:
            return compute()
        if key not in self._held:
            self._held[key] = compute()
        return self._held[key]

    def _scale_supporters(self, supporters: list[Candidate]) -> list[Candidate]:
        """The supporters whose own ``T*`` scale agrees with the joint one within
        ``gauge.scale_alarm_log`` (a wrong link must not set the gauge's scale); the others
        are logged and counted (``gauge_scale_held``) and wait on."""
        if len(supporters) < 2:
            return supporters
        joint = math.log(float(self._gauge_transform(supporters).T[7]))
        kept = []
        for c in supporters:
            own = math.log(float(self._gauge_transform([c]).T[7]))
            if abs(own - joint) > self.config.gauge.scale_alarm_log:
                self.stats.gauge_scale_held += 1
                logger.warning(
                    "coordinator: scale alarm: edge %s-%s would merge at scale "
                    "x%.3f, the others at x%.3f; not counted as support",
                    c.verification.candidate,
                    c.verification.query,
                    math.exp(own),
                    math.exp(joint),
                )
            else:
                kept.append(c)
        return kept

    def _agrees(self, candidate: Candidate, hypothesis: GaugeTransform) -> bool:
        """Whether a waiting edge's points agree once the moving side is transported."""
        x_moving, x_anchor, _ = self._oriented_correspondences(candidate)
        anchor = candidate.i if self._moving_is_j(candidate) else candidate.j
        candidate.residual_ratio = residual_ratio(
            x_anchor,
            sim3_act_points(hypothesis.T, x_moving),
            self.graph.keyframes[anchor].T_WC[:3],
        )
        return candidate.residual_ratio <= self.config.verification.max_residual_ratio

    def _gauge_transform(self, candidates: Sequence[Candidate]) -> GaugeTransform:
        """``T*`` from the lifted correspondences of edges between the same two components
        (C-Eq. 14); the rigid snap uses the first edge's endpoints."""
        key = ("T*", *(id(c) for c in candidates))
        return self._once(key, lambda: self._solve_transform(candidates))

    def _solve_transform(self, candidates: Sequence[Candidate]) -> GaugeTransform:
        parts = [self._oriented_correspondences(c) for c in candidates]
        first = candidates[0]
        moving, anchor = (first.j, first.i) if self._moving_is_j(first) else (first.i, first.j)
        return solve_gauge_transform(
            torch.cat([p[0] for p in parts]),
            torch.cat([p[1] for p in parts]),
            torch.cat([p[2] for p in parts]),
            self.graph.keyframes[moving].T_WC,
            self.graph.keyframes[anchor].T_WC,
            self.config.gauge.min_correspondences,
        )

    def _roots(self, candidate: Candidate) -> tuple[int, int]:
        """``(anchor root, moving root)`` of the components an edge connects."""
        root_i = self.gauges.find(self.graph.agent_of[candidate.i])
        root_j = self.gauges.find(self.graph.agent_of[candidate.j])
        return min(root_i, root_j), max(root_i, root_j)

    def _same_component(self, candidate: Candidate) -> bool:
        return self.gauges.same(self.graph.agent_of[candidate.i], self.graph.agent_of[candidate.j])

    def _moving_is_j(self, candidate: Candidate) -> bool:
        return self.gauges.find(self.graph.agent_of[candidate.j]) == self._roots(candidate)[1]

    def _oriented_correspondences(self, candidate: Candidate) -> tuple[Tensor, Tensor, Tensor]:
        """``(x_moving, x_anchor, q)``: lifted correspondences of an edge between two
        components, the moving component's side first."""
        x_i, x_j, q = self._lifted_correspondences(candidate)
        return (x_j, x_i, q) if self._moving_is_j(candidate) else (x_i, x_j, q)

    def _lifted_correspondences(self, candidate: Candidate) -> tuple[Tensor, Tensor, Tensor]:
        """Matched canonical points of both endpoints lifted into their world frames.

        Both match directions contribute their valid matches (``q > Q_min``, the
        high-confidence matches of C-Sec. A.4), weighted by ``q``.

        Returns:
            ``x_i (N, 3)``, ``x_j (N, 3)``, ``q (N,)``.
        """
        return self._once(("lifted", id(candidate)), lambda: self._lift_matches(candidate))

    def _lift_matches(self, candidate: Candidate) -> tuple[Tensor, Tensor, Tensor]:
        kf_i, kf_j = self.graph.keyframes[candidate.i], self.graph.keyframes[candidate.j]
        ij, ji = candidate.link.ij, candidate.link.ji
        most = self.config.gauge.max_correspondences
        x_i_ij, x_j_ij, q_ij = matched_points(ij, kf_i.X_hat, kf_j.X_hat, most)
        x_j_ji, x_i_ji, q_ji = matched_points(ji, kf_j.X_hat, kf_i.X_hat, most)
        x_i = lift(kf_i.T_WC, torch.cat([x_i_ij, x_i_ji]))
        x_j = lift(kf_j.T_WC, torch.cat([x_j_ij, x_j_ji]))
        return x_i, x_j, torch.cat([q_ij, q_ji])

    def _record_gauge_event(
        self,
        transform: GaugeTransform,
        kept: int,
        moved: list[int],
        supporters: Sequence[Candidate],
        log_focal: float | None,
    ) -> None:
        event = {
            "keyframes": self.stats.keyframes,
            "anchor_component": kept,
            "moved_agents": moved,
            "edges": [[self._key(c.i), self._key(c.j)] for c in supporters],
            "method": transform.method,
            "correspondences": transform.correspondences,
            "rmse": None if transform.method == "rigid_snap" else transform.rmse,
            "scale": float(transform.T[7]),
            "focal_factor": None if log_focal is None else math.exp(log_focal),
        }
        self.gauge_events.append(event)
        logger.info(
            "gauge: agents %s join component %d by %s over %d edge(s), %d correspondences",
            moved,
            kept,
            transform.method,
            len(supporters),
            transform.correspondences,
        )
