"""The coordinator: Level 2 of CoMo3R-SLAM (C-Sec. 3.1, 3.4, 3.5, A.3, A.4, A.8).

It receives every agent's keyframes (:class:`~como3r.frontend.packets.KeyframePacket`) in
any interleaving, and for each one

1. inserts it and its sequential edge into the unified factor graph
   (:class:`~como3r.backend.global_graph.GlobalGraph`); a relocalized keyframe, which comes
   without one, is verified against its agent's latest keyframes and tied to its chain
   (:meth:`~.linking.InterAgentLinking._relink`);
2. retrieves up to ``k_NN`` keyframes of other agents from the shared ASMK database and
   verifies each candidate densely (C-Eq. 12; :mod:`.association`);
3. admits a verified edge between two agents of ONE gauge component straight into the
   graph, provided its matched points agree with the current poses
   (``verification.max_residual_ratio``); an edge between two components is held until
   ``gauge.min_consistent_edges`` such edges agree on one aligning transform, then the
   higher-rooted component is transported into the lower one's gauge (Umeyama over all
   their lifted correspondences or rigid snap, C-Eq. 14-15; :mod:`.gauge`) and the edges
   enter the graph; edges still waiting when the stream ends merge their components on
   the set most of them agree with (:meth:`~.linking.InterAgentLinking._merge_waiting`).
   With 1 and ``inf`` this is the paper's rule (synchronize on the first verified edge);
   the defaults (2 and 0.25) add the consistency tests because the dense test of C-Eq. 12
   alone accepts edges that a prior hallucinates on repeated façades, and a single such
   edge that comes first would merge two maps on its own;
4. once ``trigger_interval_edges`` new inter-agent edges have been admitted, runs the
   global Sim(3) BA (C-Eq. 5) over every component that received one, with the
   component's first keyframe pinned (keyframe 0 of agent 0 for the global gauge);

and returns :class:`~como3r.frontend.packets.PoseUpdate` s for the agents whose keyframes
moved (C-Sec. A.8). Keyframes that waited for a busy coordinator come as one batch
(:meth:`Coordinator.add_keyframes`): steps 1 to 3 in time order (verification newest first
under a batch budget), step 4 once after the batch (issue 41: a coordinator that falls
behind does not solve once per waiting keyframe). :meth:`Coordinator.finish` runs the terminal pose-depth alternation
(C-Sec. A.7; :mod:`como3r.backend.alternation`) and returns the final poses and the refined
canonical pointmaps.

No BA ever runs across components: before their gauges are synchronized, two agents' poses
live in unrelated frames, and a joint solve would drag one chain across the other.

Poses in a packet are taken to be in the frame of the most recent update the coordinator
sent to that agent (the single-process runner applies updates before the next frame; a
multi-process runtime must apply pending updates before exporting a keyframe).

Agents in singleton components (never verified against anyone) get no pose updates: the
coordinator's copy of their chain lacks the intra-agent loop edges their own front-end
optimizes, so the front-end's poses are the better ones.

:class:`Coordinator` holds the state and the public API; steps 2 and 3 are its part
:mod:`.linking`, the keyframes a batch budget deferred its part :mod:`.deferral`, the
verifications it leaves to the agents (``verification.on_agents``) :mod:`.remote`, the focal
lengths of self-calibrated agents its part :mod:`.focal_alignment`,
the terminal cleanup's records and solvers are in :mod:`.cleanup`, its counters
:class:`~.stats.CoordinatorStats` and its ``graph.json`` and ``metrics.json`` documents
:mod:`.documents`.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
from torch import Tensor

from como3r.backend.alternation import AlternationReport, AlternationSettings, alternate
from como3r.backend.global_graph import BAResult, GlobalGraph
from como3r.config import Config
from como3r.coordination.association import Candidate, CrossAgentRetrieval
from como3r.coordination.cleanup import Cleanup, ComponentCleanup, MapSnapshot, scoped_progress
from como3r.coordination.decode_pool import VerificationPool
from como3r.coordination.deferral import DeferredKeyframe
from como3r.coordination.documents import CoordinatorDocuments
from como3r.coordination.encodings import KeyframeEncodings
from como3r.coordination.focal_alignment import FocalAlignment
from como3r.coordination.gauge import GaugeComponents
from como3r.coordination.remote import RemoteJob, RemoteVerification
from como3r.coordination.stats import CoordinatorStats
from como3r.errors import InputError
from como3r.frontend.packets import KeyframePacket, PointmapRefresh, PointmapUpdate, PoseUpdate
from como3r.frontend.paging import KeyframeParking, read_fields
from como3r.frontend.timing import StageTimer, TimedPrior
from como3r.heap import TrimOnGrowth, give_back_freed_memory
from como3r.prior.base import Prior
from como3r.prior.retrieval import Hit
from como3r.progress import PhaseCallback

logger = logging.getLogger(__name__)


class Journal(Protocol):
    """Where the coordinator's durable state goes as it changes: the session store
    (:class:`como3r.store.writer.SessionStore`)."""

    def record(
        self, coordinator: Coordinator, updates: Sequence[PoseUpdate], finished: bool = False
    ) -> None:
        """Keep the state after one message's effect (one transaction); ``updates`` are the
        pose updates it made, ``finished`` says the terminal cleanup ran."""

    def prepare(self, coordinator: Coordinator) -> None:
        """Start coding, off this thread, what the next :meth:`record` writes as the state
        is now (what changes before is coded again there); quick."""


class Coordinator(RemoteVerification, FocalAlignment, CoordinatorDocuments):
    """Cross-agent association, gauge synchronization and global BA (Level 2).

    Args:
        prior: the two-view prior (decodes candidate pairs for verification).
        config: the run's configuration.
        codebook: ``(K, d)`` ASMK codebook; without one there is no cross-agent retrieval.
        num_agents: number of agents; agent ids are ``0 .. num_agents - 1``.
    """

    def __init__(
        self, prior: Prior, config: Config, codebook: np.ndarray | None, num_agents: int
    ) -> None:
        if num_agents < 1:
            raise InputError(f"coordinator: num_agents must be >= 1, got {num_agents}")
        self.config = config
        self.num_agents = num_agents
        self.graph = GlobalGraph(config.tracking, config.global_ba)
        self.gauges = GaugeComponents()
        for agent in range(num_agents):
            self.gauges.add(agent)
        enabled = config.loop_closure and codebook is not None
        self.retrieval = CrossAgentRetrieval(codebook, config.retrieval) if enabled else None
        self.stats = CoordinatorStats()
        # the prior's decodes (verification) are charged to stage_seconds["prior_decode"]
        self.prior = TimedPrior(prior, StageTimer(self.stats.stage_seconds), self._decoded)
        #: keyframe encodings, remade from their colours where they were not sent
        self.encodings = KeyframeEncodings(
            prior, config.session.encoding_cache, round(config.session.encoding_cache_mb * 2**20)
        )
        #: verifications run ahead on threads (verification.workers; .decode_pool)
        self.pool = VerificationPool(prior, config.verification.workers)
        #: gives what a batch's verifications freed back to the system as it goes (.heap)
        self.heap = TrimOnGrowth()
        self.candidates: list[Candidate] = []
        self.gauge_events: list[dict[str, Any]] = []
        self._waiting: list[Candidate] = []  # verified edges between two components
        self._new_edges = 0
        self._dirty_roots: set[int] = set()
        #: edges refused inside one gauge since the last in-stream BA, and whether by the
        #: scale watch (tested again after it: InterAgentLinking._recheck_refused)
        self._refused: list[tuple[Candidate, bool]] = []
        #: keyframes skipped under the batch budget, to verify later (.deferral)
        self._deferred: list[DeferredKeyframe] = []
        #: verification on the agents (.remote): off until a runtime that serves it sets it
        self.delegate = False
        self._jobs_out: list[RemoteJob] = []
        self._outstanding: dict[int, RemoteJob] = {}
        self._requests = 0
        self.alternation: list[dict[str, Any]] = []
        #: agent -> its keyframes as they were before the terminal depth refinement
        #: (pointmaps as streamed, poses after the pose-only cleanup passes)
        self.pre_refinement: dict[int, list[MapSnapshot]] = {}
        #: told the state after every keyframe, refresh and the cleanup (None: not kept)
        self.journal: Journal | None = None
        #: agent sets refined by an earlier session (a saved map's components): the
        #: terminal cleanup leaves a component alone that no other agent joined
        self.refined: list[set[int]] = []

    # ------------------------------------------------------------------ public API

    def add_agent(self) -> int:
        """Room for one more agent, in a gauge component of its own; returns its id (the
        multi-process runtime makes one per restarted agent process: a new map segment)."""
        agent = self.num_agents
        self.num_agents += 1
        self.gauges.add(agent)
        return agent

    def add_keyframe(self, packet: KeyframePacket) -> list[PoseUpdate]:
        """Insert, associate, synchronize and (maybe) optimize one new keyframe: a batch of
        one (:meth:`add_keyframes`).

        A keyframe the coordinator holds already (an agent re-sending after the coordinator
        resumed from its session store) changes nothing; the last one it holds of that agent
        is answered with the current poses of all the agent's keyframes up to it
        (:meth:`_resent`).

        Returns:
            Pose updates for the agents whose keyframes moved (gauge transports first,
            then the global BA's), possibly none.

        Raises:
            InputError: unknown agent id, a keyframe out of order, or a re-sent keyframe of
                another frame than the one held.
        """
        return self.add_keyframes([packet])

    def add_keyframes(
        self, packets: Sequence[KeyframePacket], solve: bool = True
    ) -> list[PoseUpdate]:
        """Take the keyframes that waited for the coordinator as one batch.

        In the given order (the runtimes' ``(timestamp, agent)`` order) each keyframe is
        inserted into the graph and its retrieval query made and indexed (cheap), so every
        keyframe's hits are those it would have had alone; then the keyframes are verified
        and their edges admitted in the same order, each within its own decode budget
        (``verification.max_decodes_per_keyframe``), so each keyframe's hits are chosen by
        the gauge merges before it, as alone (:meth:`_verify` spends a merged agent's slots
        on loop candidates); under a batch budget (``verification.max_decodes_per_batch``)
        they are verified NEWEST FIRST while it lasts, and older keyframes past it are
        deferred (the part of the map the agents are in now is linked first), verified with
        what later batches leave of their budget or at the end (:mod:`.deferral`). The
        in-stream global BA (C-Eq. 5) runs at most once, after the whole batch, if
        ``global_ba.trigger_interval_edges`` new inter-agent edges are waiting by then (and
        ``solve``); the journal keeps the batch's effect in one transaction. A batch of one is
        :meth:`add_keyframe`'s single keyframe, step for step. The result depends on the
        batch's content and order only, never on timing.

        Args:
            packets: the keyframes, oldest first; re-sent ones are answered as in
                :meth:`add_keyframe`.
            solve: whether the global BA may run after the batch; False: the edges it
                admits wait for the next batch's (a runtime hands a long backlog over in
                parts and solves after the last, :mod:`como3r.runtime.processes`).

        Returns:
            The pose updates of the batch in the order they were made (re-sent keyframes'
            answers, gauge transports, the global BA's).

        Raises:
            InputError: as :meth:`add_keyframe`, for any keyframe of the batch.
        """
        updates: list[PoseUpdate] = []
        fresh: list[tuple[KeyframePacket, list[Hit]]] = []
        skipped: list[tuple[KeyframePacket, list[Hit]]] = []
        for packet in packets:
            if not 0 <= packet.agent < self.num_agents:
                raise InputError(
                    f"coordinator: agent id {packet.agent} is out of range for "
                    f"{self.num_agents} agents"
                )
            if packet.kf_id < len(self.graph.agent_keyframes(packet.agent)):
                updates.extend(self._resent(packet))
                continue
            self.graph.add_keyframe(packet)
            self.stats.keyframes += 1
            if packet.kf_id > 0 and packet.sequential_ij is None:
                self._relink(packet)
            fresh.append((packet, self._retrieve(packet)))
        self._prepare()  # the inserted pointmaps are coded while the batch is verified
        spent, budget = self.stats.prior_decodes, self._batch_budget(len(fresh))
        # in time order, as one at a time (which hits a keyframe verifies depends on the
        # merges before it); newest first only when a batch budget must choose
        order = fresh if math.isinf(budget) else fresh[::-1]
        self._speculate(order)
        try:
            for packet, hits in order:
                found = len(updates)
                if hits and self.stats.prior_decodes - spent + self._keyframe_budget() > budget:
                    skipped.append((packet, hits))
                    continue
                for candidate in self._verify_or_request(packet, hits):
                    updates.extend(self._admit(candidate))
                self.heap.check()  # what the verification freed (.heap)
                logger.debug(
                    "coordinator: agent %d kf %d: %d gauge update(s)",
                    packet.agent,
                    packet.kf_id,
                    len(updates) - found,
                )
        finally:
            self._settle()
        if fresh:
            updates.extend(self._defer(skipped, self.stats.prior_decodes - spent))
            if solve:
                self._solve_on_trigger(updates)
        self.stats.batches += int(bool(fresh))
        self.stats.largest_batch = max(self.stats.largest_batch, len(fresh))
        self.heap.check()  # before the journal codes what the batch changed
        return self._record(self._count(updates))

    def refresh(self, agent: int, refresh: PointmapRefresh) -> None:
        """Replace the canonical pointmap of a sent keyframe by its newer fused one."""
        self.graph.refresh(agent, refresh)
        self._record([])

    def finish(
        self, agent_poses: Mapping[int, Tensor] | None = None, progress: PhaseCallback | None = None
    ) -> Cleanup:
        """Terminal cleanup of every component (C-Sec. A.7): the pose-depth alternation.

        A multi-agent component runs the whole schedule (global pose passes, then rounds of
        depth step + pose pass) and its agents get their final poses. A single-agent
        component keeps the agent's own poses (its front-end optimised them with intra-agent
        loop edges the coordinator does not hold) and runs the depth steps alone at them.
        Every refined keyframe's pointmap is returned. The agents have stopped streaming by
        now, so the per-round broadcast of step 2e collapses into the final updates. The
        keyframes still deferred under a batch budget are verified first (:mod:`.deferral`).

        Args:
            agent_poses: each agent's final keyframe poses ``(K_a, 8)`` in keyframe order,
                for the agents whose front-end outlived the stream; single-agent
                components adopt them before refining.
            progress: called as each step starts (focal refinement, cleanup passes,
                alternation rounds), the component's agents first in its ``detail``.

        Raises:
            InputError: an agent's pose count differs from the keyframes it sent.
        """
        start = time.perf_counter()
        cleanup = Cleanup(pointmap_update=self._pointmaps)
        self.take_back_all()  # jobs still out are verified here now (.remote)
        cleanup.updates.extend(self._verify_all_deferred())
        # nothing decodes from here on (the cleanup works on pointmaps): the pool's threads
        # end and the re-encoded keyframes go (16 agents: 1.5 GB of the simulated prior's)
        self.pool.shutdown()
        self.encodings.retain(())
        give_back_freed_memory()
        spill = Path(self.config.session.spill_dir) if self.config.session.spill_dir else None
        parking = self.cleanup_parking = KeyframeParking(spill)
        settings = AlternationSettings.from_config(self.config.global_ba, self.config.depth)
        # components that edges still wait between merge now (their poses reach the agents
        # with the cleanup's updates)
        self._merge_waiting()
        for members in self.components():
            if not self.graph.agent_keyframes(members[0]) or any(
                set(members) <= done for done in self.refined
            ):
                continue
            multi_agent = len(members) > 1
            if not multi_agent:
                if settings.rounds == 0:
                    continue
                self._adopt(members[0], (agent_poses or {}).get(members[0]))
            scoped = scoped_progress(progress, members)
            if multi_agent:
                self._refine_focals(members, scoped)
                give_back_freed_memory()  # the focal BA's factors (.heap)
            component = ComponentCleanup(
                self.graph, members, self._anchor(members[0]), self.config.depth, parking, spill
            )
            report = alternate(
                component.pose_pass if multi_agent else None,
                component.depth_step,
                settings,
                progress=scoped,
            )
            self._record_cleanup(members, component, report)
            if multi_agent:
                cleanup.updates.extend(self._updates(members, "cleanup"))
            if component.depth_reports:
                cleanup.refined.extend(members)
                self.pre_refinement.update(component.snapshot)
        self.cleanup_parking = None
        self.stats.add_time("cleanup", time.perf_counter() - start)
        self._record(self._count(cleanup.updates), finished=True)
        return cleanup

    def restore(
        self,
        graph: GlobalGraph,
        gauges: GaugeComponents,
        candidates: list[Candidate],
        stats: CoordinatorStats,
        gauge_events: list[dict[str, Any]],
        backlog: tuple[int, list[int]],
    ) -> None:
        """Continue from a stored state (:func:`como3r.store.resume.load_state`):
        the graph, gauge components, candidates (the pending ones wait again), counters,
        gauge events and the BA backlog. The caller rebuilds the retrieval database."""
        self.graph, self.gauges, self.candidates = graph, gauges, candidates
        self._waiting = [c for c in candidates if c.status == "pending"]
        self._new_edges, self._dirty_roots = backlog[0], set(backlog[1])
        self.gauge_events = gauge_events
        seconds = self.stats.stage_seconds  # the prior's timer adds to this very dict
        seconds.update(stats.stage_seconds)
        self.stats = replace(stats, stage_seconds=seconds)

    def _resent(self, packet: KeyframePacket) -> list[PoseUpdate]:
        """The answer to a re-sent keyframe: once the agent has re-sent the last keyframe
        held of it, the current poses of all its keyframes (the agent goes on in the shared
        frame); before that, nothing.

        Answering every re-sent keyframe with the poses up to it made the re-run agent's
        local solve remake the quadratic model of every old edge after each answer (its own
        solve moves the stored poses by more than ``local_solve.relinearize_tol`` between
        answers): a resumed run took 2-3x the time of an uninterrupted one.
        """
        indices = self.graph.agent_keyframes(packet.agent)
        held = self.graph.keyframes[indices[packet.kf_id]]
        if held.frame_index != packet.frame_index:
            raise InputError(
                f"coordinator: agent {packet.agent} re-sent keyframe "
                f"{packet.kf_id} at frame {packet.frame_index}, but the stored "
                f"session has it at frame {held.frame_index}"
            )
        if packet.kf_id < len(indices) - 1:
            return []
        return [
            PoseUpdate(
                agent=packet.agent,
                kf_ids=torch.arange(len(indices)),
                T_WC=self.graph.poses(indices).clone(),
                reason="resume",
                focal=self.graph.focal.get(packet.agent),
            )
        ]

    def current_poses(self, agent: int, reason: str) -> PoseUpdate | None:
        """An update with the current poses of all of ``agent``'s keyframes (None before
        its first); made, not sent: it is neither counted nor recorded."""
        updates = self._updates([agent], reason)
        return updates[0] if updates else None

    @property
    def backlog(self) -> tuple[int, list[int]]:
        """Inter-agent edges admitted since the last in-stream BA and the roots of the
        components they touched (what triggers and scopes the next one)."""
        return self._new_edges, sorted(self._dirty_roots)

    def _decoded(self, pairs: int) -> None:
        self.stats.prior_decodes += pairs

    def _prepare(self) -> None:
        """Let the journal start coding what it will write (:meth:`Journal.prepare`; its
        time here is the stage ``journal``'s too)."""
        if self.journal is not None:
            start = time.perf_counter()
            self.journal.prepare(self)
            self.stats.add_time("journal", time.perf_counter() - start)

    def _record(self, updates: list[PoseUpdate], finished: bool = False) -> list[PoseUpdate]:
        """Hand the state after one message's effect to the journal (its time is the stage
        ``journal``: the session store's compression and writes); returns ``updates``."""
        if self.journal is not None:
            start = time.perf_counter()
            self.journal.record(self, updates, finished)
            self.stats.add_time("journal", time.perf_counter() - start)
        return updates

    def _adopt(self, agent: int, T_WC: Tensor | None) -> None:
        """Take an agent's own final keyframe poses (single-agent components)."""
        if T_WC is None:
            return
        indices = self.graph.agent_keyframes(agent)
        if T_WC.shape != (len(indices), 8):
            raise InputError(
                f"coordinator: agent {agent} reported final poses of shape "
                f"{tuple(T_WC.shape)} for the {len(indices)} keyframes it sent"
            )
        self.graph.set_poses(indices, T_WC)

    def _record_cleanup(
        self, members: list[int], component: ComponentCleanup, report: AlternationReport
    ) -> None:
        self.stats.cleanup_passes += len(component.results)
        self.stats.cleanup_iterations += sum(r.iterations for r in component.results)
        self.stats.cleanup_seconds += sum(r.seconds for r in component.results)
        depth = component.depth_reports
        self.alternation.append(
            {
                "agents": list(members),
                **report.to_json(),
                "depth_variant": self.config.depth.variant,
                "depth_parameters": depth[-1].num_parameters if depth else 0,
                "depth_matches": depth[-1].num_matches if depth else 0,
                "depth_iterations": sum(r.iterations for r in depth),
            }
        )

    def _pointmaps(self, agent: int) -> PointmapUpdate:
        """An update with the current pointmaps of all of ``agent``'s keyframes."""
        indices = self.graph.agent_keyframes(agent)
        return PointmapUpdate(
            agent=agent,
            kf_ids=torch.arange(len(indices), dtype=torch.int64),
            X_hat=torch.stack([read_fields(self.graph.keyframes[g], "X_hat") for g in indices]),
        )

    # ------------------------------------------------------------------ global BA

    def _anchor(self, root: int) -> int:
        """Pinned keyframe of a component: the first keyframe of its lowest agent."""
        return self.graph.global_index(root, 0)

    def _global_ba(self) -> list[PoseUpdate]:
        """In-stream BA (C-Eq. 5) of every component that received new inter edges."""
        self._prepare()  # the merges' rescaled pointmaps and new edges, coded during it
        start = time.perf_counter()
        updates: list[PoseUpdate] = []
        for root in sorted({self.gauges.find(r) for r in self._dirty_roots}):
            members = self.gauges.members(root)
            result = self.graph.optimize(
                members,
                self._anchor(root),
                self.config.global_ba.max_iters_stream,
                self.config.global_ba.stream_max_matches,
            )
            self._count_ba(result)
            if result.moved:
                moved = sorted({self.graph.agent_of[g] for g in result.keyframes})
                updates.extend(self._updates(moved, "global_ba"))
        self._new_edges = 0
        self._dirty_roots.clear()
        self.stats.add_time("global_ba", time.perf_counter() - start)
        return updates

    def _count_ba(self, result: BAResult) -> None:
        self.stats.ba_runs += 1
        self.stats.ba_iterations += result.iterations
        self.stats.ba_seconds += result.seconds
        self.stats.ba_restored += int(result.restored)

    # ------------------------------------------------------------------ helpers

    def _updates(self, agents: Iterable[int], reason: str) -> list[PoseUpdate]:
        """One update per agent with the current poses of all its keyframes."""
        updates = []
        for agent in agents:
            indices = self.graph.agent_keyframes(agent)
            if indices:
                updates.append(
                    PoseUpdate(
                        agent=agent,
                        kf_ids=torch.arange(len(indices), dtype=torch.int64),
                        T_WC=self.graph.poses(indices).clone(),
                        reason=reason,
                        focal=self.graph.focal.get(agent),
                    )
                )
        return updates

    def _count(self, updates: list[PoseUpdate]) -> list[PoseUpdate]:
        self.stats.pose_updates += len(updates)
        return updates
