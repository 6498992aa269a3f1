"""The focal lengths of self-calibrated agents in one map (``gauge.align_focal``;
:mod:`como3r.frontend.focal`): a merging component takes the anchor's focal length on the
edges that merged it, and the terminal cleanup re-aligns each agent on the admitted edges to
the agents already settled.

:class:`FocalAlignment` is one part of :class:`~como3r.coordination.coordinator.Coordinator`
(its base class): its methods read and change the coordinator's graph and counters.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence

import numpy as np
import torch

from como3r.backend.focal_solver import optimize_focal
from como3r.backend.global_graph import GlobalGraph
from como3r.config import Config
from como3r.coordination.association import Candidate
from como3r.frontend.focal import FocalEstimate, FocalPair, estimate_log_focal, relative_pose
from como3r.frontend.paging import KeyframeParking
from como3r.progress import PhaseCallback, report_phase

# the coordinator's logger: its messages read as they did before this part had a module
logger = logging.getLogger("como3r.coordination.coordinator")


#: Edges an agent's focal length is re-aligned on at the terminal cleanup (the most similar
#: ones): each adds its matches to every iteration of the joint pose and focal solve.
FOCAL_REFINEMENT_PAIRS = 4


class FocalAlignment:
    """Focal-length alignment of the :class:`~como3r.coordination.coordinator.Coordinator`
    (the coordinator's attributes it uses are declared below; it also counts in the
    coordinator's ``stats`` and calls its helpers)."""

    config: Config
    graph: GlobalGraph
    candidates: list[Candidate]
    #: the terminal cleanup's parking while it runs (None otherwise): where a rescale puts
    #: paged-out keyframes' pointmaps (:meth:`GlobalGraph.rescale_focal`)
    cleanup_parking: KeyframeParking | None = None

    def _align_focal(
        self, supporters: Sequence[Candidate], moved_agents: list[int]
    ) -> float | None:
        """Give the moving component the anchor's focal length (``gauge.align_focal``,
        self-calibrated runs; :mod:`como3r.frontend.focal`); returns the log correction
        applied, or None."""
        if not self._aligns_focal() or any(self._frozen(a) for a in moved_agents):
            return None
        pairs = [self._focal_pair(c, self._moving_is_j(c)) for c in supporters]
        if any(pair is None for pair in pairs):
            return None
        return self._apply_focal(moved_agents, pairs, "aligned")

    def _aligns_focal(self) -> bool:
        config = self.config
        return (
            config.gauge.align_focal and config.tracking.self_calibration and not config.calibrated
        )

    def _apply_focal(self, agents: list[int], pairs: Sequence[FocalPair], how: str) -> float | None:
        """Estimate the moving side's log focal correction on ``pairs`` and give it to
        ``agents``; returns the correction (None without pairs)."""
        if not pairs:
            return None
        start = time.perf_counter()
        estimate = self._estimate_log_focal(pairs)
        for agent in agents:
            self.graph.rescale_focal(agent, estimate.log_focal, self.cleanup_parking)
        self.stats.add_time("focal", time.perf_counter() - start)
        logger.info(
            "focal: agents %s %s on %d pair(s) (x %.4f, %d evaluations)",
            agents,
            how,
            len(pairs),
            math.exp(estimate.log_focal),
            estimate.evaluations,
        )
        return estimate.log_focal

    def _refine_focals(self, members: list[int], progress: PhaseCallback | None = None) -> None:
        """Re-align the agents' focal lengths on every admitted pair (``gauge.align_focal``).

        A merge aligns the moving component's focal length on the few edges that made it
        (often one pair); by the end of the stream the agents usually share many more.
        Starting from the anchor agent ``members[0]``, the agent with the most admitted
        edges to the agents already settled is re-aligned on (at most
        ``FOCAL_REFINEMENT_PAIRS`` of) those edges, then counts as settled, until every
        connected agent is. Measured on a 3-agent room (320x240 -> 512, 12 frames each,
        realistic prior, seed 0; agent 2 merged into agent 1 on one pair, then both into
        agent 0 on one pair): focal lengths 339 / 337 / 349 px after the merges (true 334),
        merged ATE 4.97 cm = 2.7 % of path; refined on 4 (or 8) pairs per agent 1.97 cm =
        1.07 %, for 8 s more of coordinator time. The same run calibrated: 0.70 cm. Seed 1:
        0.72 -> 0.85 % (focal lengths 329.5 / 330.6 / 330.7 px after, but agents 1 and 2 sit
        3 % smaller than agent 0, joined by one edge: an offset the focal errors had hidden).
        With ``gauge.focal_loops``, where the agents' pairs close loops,
        :meth:`_close_focal_loops` then spreads what this chain leaves around them.
        """
        if not self._aligns_focal():
            return
        if self.config.gauge.focal_ba:
            self._solve_focals(members, progress)
            return
        settled = {members[0]} | {agent for agent in members if self._frozen(agent)}
        admitted = [c for c in self.candidates if c.status == "admitted"]
        while True:
            edges = {
                agent: [c for c in admitted if self._joins(c, agent, settled)]
                for agent in members
                if agent not in settled
            }
            agent = max(edges, key=lambda a: len(edges[a]), default=None)
            if agent is None or not edges[agent]:
                break
            report_phase(
                progress,
                "focal refinement",
                f"agent {agent} on {min(len(edges[agent]), FOCAL_REFINEMENT_PAIRS)} pair(s)",
                len(settled) - 1,
                len(members) - 1,
            )
            pairs = self._focal_pairs(edges[agent], agent)
            if self._apply_focal([agent], pairs, "refined") is not None:
                self.stats.focal_refinements += 1
            settled.add(agent)
        if self.config.gauge.focal_loops:
            self._close_focal_loops(members, progress)

    def _solve_focals(self, members: list[int], progress: PhaseCallback | None = None) -> None:
        """One focal length per agent estimated inside the global BA over all the
        component's edges at once (``gauge.focal_ba``; :func:`optimize_focal`), with the
        prior ``gauge.focal_prior`` on each agent's own self-calibration. Keyframes without
        intrinsics (a run whose agents did not self-calibrate) have no focal length to solve:
        nothing changes."""
        graph = self.graph
        if any(graph.keyframes[g].K is None for a in members for g in graph.agent_keyframes(a)):
            return
        report_phase(progress, "focal BA", f"{len(members)} agents", 0, 1)
        start = time.perf_counter()
        result = optimize_focal(
            self.graph,
            members,
            self._anchor(members[0]),
            self.config.global_ba.max_iters_stream,
            self.config.gauge.focal_prior,
            self.graph.own_focal,
            self.config.gauge.focal_max_matches,
            self.cleanup_parking,
        )
        self.stats.add_time("focal", time.perf_counter() - start)
        self.stats.focal_refinements += sum(1 for v in result.log_focal.values() if v != 0.0)
        logger.info(
            "focal: joint BA over agents %s, %d iterations (%s): %s px",
            members,
            result.iterations,
            result.reason,
            ", ".join(f"{self.graph.agent_focal(a) or math.nan:.1f}" for a in members),
        )

    def _close_focal_loops(self, members: list[int], progress: PhaseCallback | None = None) -> None:
        """Spread what the chain of :meth:`_refine_focals` leaves around loops of agents.

        Each pair of agents with admitted edges gives one measurement at the focal lengths
        the chain left: the log focal correction of its higher agent against its lower one
        on (at most ``FOCAL_REFINEMENT_PAIRS`` of) those edges, the most similar first
        (:func:`~como3r.frontend.focal.estimate_log_focal`), a target for the difference of
        their log focal lengths; all agents' corrections then solve these differences in
        least squares (:func:`solve_log_focals`, each weighted by its edge count) with the
        anchor agent ``members[0]`` and frozen agents held: a 1-D pose graph over log focal
        lengths. Only where the agents' pairs close a loop (at least as many pairs as
        agents): on a tree of pairs the chain already meets every measurement.

        Issue 41: the chain settles agents outwards from the anchor, so around a ring of
        agents its ratio errors add up on both sides and meet at the far end. On a 16-agent
        ring (160x120 -> 512, 8 processed frames per agent, realistic prior, seed 0; true
        focal 333.6 px) it left 306-337 px and a merged ATE of 62.1 mm; the BA from the
        ground-truth poses at those focal lengths settles 56 mm off, at the true ones 11 mm
        (their disagreement is what the ring could not close); this sweep at the chain's
        focal lengths, then the BA: 38.7 mm (keyframes, offline on the stored session).
        """
        if not self._aligns_focal():
            return
        held = {members[0]} | {agent for agent in members if self._frozen(agent)}
        inside = set(members)
        by_pair: dict[tuple[int, int], list[Candidate]] = {}
        for c in self.candidates:
            ends = (self.graph.agent_of[c.i], self.graph.agent_of[c.j])
            if c.status == "admitted" and set(ends) <= inside and ends[0] != ends[1]:
                by_pair.setdefault((min(ends), max(ends)), []).append(c)
        if len(by_pair) < len(members):
            return
        rows: list[tuple[int, int, float, int]] = []  # (lower, higher, log correction, pairs)
        for done, ((low, high), edges) in enumerate(sorted(by_pair.items())):
            report_phase(
                progress,
                "focal loops",
                f"agents {low}-{high} on {min(len(edges), FOCAL_REFINEMENT_PAIRS)} pair(s)",
                done,
                len(by_pair),
            )
            known = self._focal_pairs(edges, high)
            if not known:
                continue
            start = time.perf_counter()
            estimate = self._estimate_log_focal(known)
            self.stats.add_time("focal", time.perf_counter() - start)
            rows.append((low, high, estimate.log_focal, len(known)))
        for agent, log_focal in solve_log_focals(rows, held).items():
            self._apply_log_focal(agent, log_focal)

    def _estimate_log_focal(self, pairs: Sequence[FocalPair]) -> FocalEstimate:
        """:func:`estimate_log_focal` on ``pairs`` without autograd's bookkeeping: its
        hundreds of small tensor operations per relative solve (of which only floats come
        out) each cost a few microseconds less (measured: ~10 % of a merge's focal search)."""
        with torch.inference_mode():
            return estimate_log_focal(
                pairs, self.config.tracking, search=self.config.gauge.focal_search
            )

    def _apply_log_focal(self, agent: int, log_focal: float) -> None:
        """Move one agent onto ``f exp(log_focal)`` (a joint refinement's result)."""
        focal = self.graph.rescale_focal(agent, log_focal, self.cleanup_parking)
        self.stats.focal_refinements += 1
        logger.info(
            "focal: agent %d refined (x %.4f) to %.1f px", agent, math.exp(log_focal), focal
        )

    def _frozen(self, agent: int) -> bool:
        """Whether an agent's keyframes are held fixed (a saved map under --freeze-map)."""
        return any(g in self.graph.fixed for g in self.graph.agent_keyframes(agent))

    def _joins(self, candidate: Candidate, agent: int, settled: set[int]) -> bool:
        """Whether an edge links ``agent`` to one of the ``settled`` agents."""
        ends = {self.graph.agent_of[candidate.i], self.graph.agent_of[candidate.j]}
        return agent in ends and bool(ends & settled)

    def _focal_pairs(self, candidates: Sequence[Candidate], moving: int) -> list[FocalPair]:
        """At most ``FOCAL_REFINEMENT_PAIRS`` of ``candidates``, the most similar first, as
        keyframe pairs with agent ``moving``'s second (those with intrinsics)."""
        chosen = sorted(candidates, key=lambda c: -c.verification.similarity)
        pairs = [
            self._focal_pair(c, self.graph.agent_of[c.j] == moving)
            for c in chosen[:FOCAL_REFINEMENT_PAIRS]
        ]
        return [p for p in pairs if p is not None]

    def _focal_pair(self, candidate: Candidate, moving_is_j: bool) -> FocalPair | None:
        """The candidate's keyframe pair, anchor side first (None without intrinsics)."""
        anchor, moving = (candidate.i, candidate.j) if moving_is_j else (candidate.j, candidate.i)
        kf_a, kf_m = self.graph.keyframes[anchor], self.graph.keyframes[moving]
        if kf_a.K is None or kf_m.K is None:
            return None
        link = candidate.link  # ij: every pixel of j looked up in i
        in_anchor, in_moving = (link.ij, link.ji) if moving_is_j else (link.ji, link.ij)
        return FocalPair(
            kf_a.X_hat,
            kf_m.X_hat,
            kf_a.K,
            kf_m.K,
            relative_pose(kf_a.T_WC, kf_m.T_WC),
            in_anchor,
            in_moving,
        )


def solve_log_focals(
    rows: Sequence[tuple[int, int, float, int]], held: set[int]
) -> dict[int, float]:
    """The agents' log focal corrections from pairwise measurements, in least squares.

    Args:
        rows: ``(a, b, d, w)``: agent ``b``'s log focal length should exceed its current
            difference to agent ``a``'s by ``d``, with weight ``w``.
        held: agents whose focal length stays (the anchor, frozen agents).

    Returns:
        The correction of every agent connected to a held one through rows (held agents
        and unconnected ones are left out).
    """
    reached = set(held)
    grew = True
    while grew:  # agents tied to a held one through measurements
        grew = False
        for a, b, _, _ in rows:
            if (a in reached) != (b in reached):
                reached |= {a, b}
                grew = True
    free = sorted(reached - held)
    if not free:
        return {}
    column = {agent: k for k, agent in enumerate(free)}
    used = [r for r in rows if r[0] in reached and r[1] in reached]
    A = np.zeros((len(used), len(free)))
    y = np.zeros(len(used))
    for r, (a, b, d, w) in enumerate(used):
        scale = math.sqrt(w)
        if b in column:
            A[r, column[b]] = scale
        if a in column:
            A[r, column[a]] = -scale
        y[r] = scale * d
    x = np.linalg.lstsq(A, y, rcond=None)[0]
    return {agent: float(x[column[agent]]) for agent in free}
