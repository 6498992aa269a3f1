"""The coordinator: Level 2 of CoMo3R-SLAM (C-Sec. 3.1, 3.4, 3.5, A.3, A.4, A.8).

It receives every agent's keyframes (:class:`~como3r.frontend.packets.KeyframePacket`) in
any interleaving, and for each one

1. inserts it and its sequential edge into the unified factor graph
   (:class:`~como3r.backend.global_graph.GlobalGraph`);
2. retrieves up to ``k_NN`` keyframes of other agents from the shared ASMK database and
   verifies each candidate densely (C-Eq. 12; :mod:`.association`);
3. admits a verified edge between two agents of ONE gauge component straight into the
   graph, provided its matched points agree with the current poses
   (``verification.max_residual_ratio``); an edge between two components is held until
   ``gauge.min_consistent_edges`` such edges agree on one aligning transform, then the
   higher-rooted component is transported into the lower one's gauge (Umeyama over all
   their lifted correspondences or rigid snap, C-Eq. 14-15; :mod:`.gauge`) and the edges
   enter the graph. With 1 and ``inf`` this is the paper's rule (synchronize on the first
   verified edge); the defaults add the consistency tests because the dense test of
   C-Eq. 12 alone accepts edges that a prior hallucinates on repeated façades;
4. once ``trigger_interval_edges`` new inter-agent edges have been admitted, runs the
   global Sim(3) BA (C-Eq. 5) over every component that received one, with the
   component's first keyframe pinned (keyframe 0 of agent 0 for the global gauge);

and returns :class:`~como3r.frontend.packets.PoseUpdate` s for the agents whose keyframes
moved (C-Sec. A.8). :meth:`Coordinator.finish` runs the terminal pose-depth alternation
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
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
from torch import Tensor

from como3r.backend.alternation import AlternationReport, AlternationSettings, alternate
from como3r.backend.depth_refinement import DepthRefinementReport
from como3r.backend.global_graph import BAResult, GlobalGraph, GraphLink
from como3r.config import Config, DepthRefinementConfig
from como3r.coordination.association import (
    CrossAgentRetrieval,
    Verification,
    budget_candidates,
    verify_candidates,
)
from como3r.coordination.gauge import (
    GaugeComponents,
    GaugeTransform,
    edge_log_scale,
    lift,
    residual_ratio,
    solve_gauge_transform,
    transport,
)
from como3r.errors import Como3rError, InputError
from como3r.frontend.focal import FocalPair, estimate_log_focal, relative_pose
from como3r.frontend.keyframes import Keyframe
from como3r.frontend.packets import KeyframePacket, PointmapRefresh, PointmapUpdate, PoseUpdate
from como3r.frontend.paging import KeyframeParking, paged_out, read_fields
from como3r.frontend.pairs import DirectedMatches, PairLink, gather_points
from como3r.frontend.timing import StageTimer, TimedPrior
from como3r.geometry.lie import sim3_act
from como3r.prior.base import Prior
from como3r.prior.retrieval import Quantized
from como3r.progress import PhaseCallback, PhaseEvent, report_phase

logger = logging.getLogger(__name__)

#: Edges an agent's focal length is re-aligned on at the terminal cleanup (the most similar
#: ones): each costs one relative solve per evaluation of the golden-section search.
FOCAL_REFINEMENT_PAIRS = 4


@dataclass
class CoordinatorStats:
    """Counters and timings reported in metrics.json."""

    keyframes: int = 0
    retrieval_queries: int = 0
    edges_tried: int = 0
    edges_verified: int = 0
    edges_accepted: int = 0
    edges_inconsistent: int = 0
    # of those, edges whose own similarity would rescale the map (gauge.scale_alarm_log)
    edges_scale_inconsistent: int = 0
    # edges a merge did not count as support: their T* scale disagreed with the joint one
    gauge_scale_held: int = 0
    gauge_syncs: int = 0
    focal_refinements: int = 0
    ba_runs: int = 0
    ba_iterations: int = 0
    ba_seconds: float = 0.0
    ba_restored: int = 0
    cleanup_passes: int = 0
    cleanup_iterations: int = 0
    cleanup_seconds: float = 0.0
    pose_updates: int = 0
    # ordered pairs the prior decoded for the coordinator (verification): the prior's work
    # its keyframes caused, as the agents' decodes are theirs (benchmarks/report.py)
    prior_decodes: int = 0
    stage_seconds: dict[str, float] = field(default_factory=dict)

    def add_time(self, stage: str, seconds: float) -> None:
        """Accumulate wall-clock seconds of a stage."""
        self.stage_seconds[stage] = self.stage_seconds.get(stage, 0.0) + seconds


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


class _ComponentCleanup:
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


@dataclass(eq=False)
class Candidate:
    """A verified cross-agent candidate edge and what became of it.

    Attributes:
        verification: the dense verification (C-Eq. 12).
        i: global index of the candidate keyframe (endpoint i).
        j: global index of the new keyframe (endpoint j).
        status: ``"rejected"`` (C-Eq. 12 failed), ``"pending"`` (waiting for agreeing
            edges between two components), ``"admitted"`` (in the graph) or
            ``"inconsistent"`` (disagrees with the poses it would constrain).
        residual_ratio: the consistency measure of the last test (NaN if untested).
    """

    verification: Verification
    i: int
    j: int
    status: str = "rejected"
    residual_ratio: float = float("nan")

    @property
    def link(self) -> PairLink:
        """Both directions' matches; only verified candidates reach the code that asks."""
        link = self.verification.link
        if link is None or not self.verification.accepted:
            raise Como3rError(
                f"candidate {self.verification.candidate}-"
                f"{self.verification.query} was not verified"
            )
        return link


class Journal(Protocol):
    """Where the coordinator's durable state goes as it changes: the session store
    (:class:`como3r.store.writer.SessionStore`)."""

    def record(
        self, coordinator: Coordinator, updates: Sequence[PoseUpdate], finished: bool = False
    ) -> None:
        """Keep the state after one message's effect (one transaction); ``updates`` are the
        pose updates it made, ``finished`` says the terminal cleanup ran."""


class Coordinator:
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
        self.candidates: list[Candidate] = []
        self.gauge_events: list[dict[str, Any]] = []
        self._waiting: list[Candidate] = []  # verified edges between two components
        self._new_edges = 0
        self._dirty_roots: set[int] = set()
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
        """Insert, associate, synchronize and (maybe) optimize one new keyframe.

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
        if not 0 <= packet.agent < self.num_agents:
            raise InputError(
                f"coordinator: agent id {packet.agent} is out of range for {self.num_agents} agents"
            )
        if packet.kf_id < len(self.graph.agent_keyframes(packet.agent)):
            return self._record(self._count(self._resent(packet)))
        g = self.graph.add_keyframe(packet)
        self.stats.keyframes += 1
        updates: list[PoseUpdate] = []
        for candidate in self._associate(packet):
            updates.extend(self._admit(candidate))
        if self._new_edges >= self.config.global_ba.trigger_interval_edges:
            updates.extend(self._global_ba())
        logger.debug(
            "coordinator: keyframe %d (agent %d, kf %d): %d update(s)",
            g,
            packet.agent,
            packet.kf_id,
            len(updates),
        )
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
        now, so the per-round broadcast of step 2e collapses into the final updates.

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
        spill = Path(self.config.session.spill_dir) if self.config.session.spill_dir else None
        parking = KeyframeParking(spill)
        settings = AlternationSettings.from_config(self.config.global_ba, self.config.depth)
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
            scoped = _scoped(progress, members)
            if multi_agent:
                self._refine_focals(members, scoped)
            component = _ComponentCleanup(
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
        """Continue from a stored state (:meth:`como3r.store.writer.SessionStore.open`):
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
        self, members: list[int], component: _ComponentCleanup, report: AlternationReport
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

    # ------------------------------------------------------------------ association

    def _associate(self, packet: KeyframePacket) -> list[Candidate]:
        """Retrieve candidates of other agents and verify them densely (C-Eq. 12)."""
        if self.retrieval is None or packet.retrieval is None:
            return []
        start = time.perf_counter()
        descriptors, attention = packet.retrieval
        if (
            packet.retrieval_words is not None
            and packet.codebook_id == self.retrieval.database.codebook_id
        ):
            descriptors = Quantized(descriptors, packet.retrieval_words)  # the agent's search
        hits = self.retrieval.query_and_add(packet.agent, packet.kf_id, (descriptors, attention))
        self.stats.retrieval_queries += 1
        middle = time.perf_counter()
        self.stats.add_time("retrieval", middle - start)
        root = self.gauges.find(packet.agent)
        hits = budget_candidates(
            hits, lambda agent: self.gauges.find(agent) == root, self.config.verification
        )
        if not hits:
            return []
        candidates = [
            (h, self.graph.keyframes[self.graph.global_index(h.agent, h.keyframe)].encoding)
            for h in hits
        ]
        decoded = self.stats.stage_seconds.get("prior_decode", 0.0)
        verifications = verify_candidates(
            self.prior,
            (packet.agent, packet.kf_id),
            packet.encoding,
            candidates,
            self.config.matching,
            self.config.tracking.q_min,
            self.config.verification,
        )
        decoded = self.stats.stage_seconds.get("prior_decode", 0.0) - decoded
        self.stats.add_time("verification", time.perf_counter() - middle - decoded)
        self.stats.edges_tried += len(verifications)
        records = [
            Candidate(v, self.graph.global_index(*v.candidate), self.graph.global_index(*v.query))
            for v in verifications
        ]
        self.candidates.extend(records)
        verified = [c for c in records if c.verification.accepted]
        self.stats.edges_verified += len(verified)
        return verified

    def _admit(self, candidate: Candidate) -> list[PoseUpdate]:
        """Route a verified edge: into its component's graph, or towards a gauge merge."""
        if self._same_component(candidate):
            self._admit_within(candidate)
            return []
        candidate.status = "pending"
        self._waiting.append(candidate)
        return self._try_merge(candidate)

    def _admit_within(self, candidate: Candidate) -> None:
        """Add an edge between agents sharing a gauge if it agrees with their poses."""
        x_i, x_j, q = self._lifted_correspondences(candidate)
        centre = self.graph.keyframes[candidate.i].T_WC[:3]
        candidate.residual_ratio = residual_ratio(x_i, x_j, centre)
        if candidate.residual_ratio > self.config.verification.max_residual_ratio:
            candidate.status = "inconsistent"
            self.stats.edges_inconsistent += 1
            logger.info(
                "coordinator: edge %s-%s disagrees with the poses (ratio %.3f); rejected",
                candidate.verification.candidate,
                candidate.verification.query,
                candidate.residual_ratio,
            )
            return
        if not self._scale_agrees(candidate, x_j, x_i, q):
            return
        self._add_inter_link(candidate)

    def _scale_agrees(self, candidate: Candidate, x_j: Tensor, x_i: Tensor, q: Tensor) -> bool:
        """The scale watch of an edge inside one gauge (``gauge.scale_alarm_log``): its own
        similarity from endpoint j's lifted points to endpoint i's must not rescale the map;
        otherwise it is held back as inconsistent and reported."""
        log_scale = edge_log_scale(x_j, x_i, q, self.config.gauge.min_correspondences)
        if not abs(log_scale) > self.config.gauge.scale_alarm_log:
            return True
        candidate.status = "inconsistent"
        self.stats.edges_inconsistent += 1
        self.stats.edges_scale_inconsistent += 1
        logger.warning(
            "coordinator: scale alarm: edge %s-%s would rescale the map by %.3f "
            "(threshold exp(%.3f)); held back",
            candidate.verification.candidate,
            candidate.verification.query,
            math.exp(log_scale),
            self.config.gauge.scale_alarm_log,
        )
        return False

    def _add_inter_link(self, candidate: Candidate) -> None:
        candidate.status = "admitted"
        v = candidate.verification
        self.graph.add_inter_link(candidate.i, candidate.j, candidate.link, v.similarity)
        self.stats.edges_accepted += 1
        self._new_edges += 1
        self._dirty_roots.add(self.gauges.find(self.graph.agent_of[candidate.i]))

    # ------------------------------------------------------------------ gauge

    def _try_merge(self, candidate: Candidate) -> list[PoseUpdate]:
        """Merge the two components of ``candidate`` once enough waiting edges between them
        agree with its transform; then admit them and re-test the rest."""
        needed = self.config.gauge.min_consistent_edges
        supporters = [candidate]
        if needed > 1:
            hypothesis = self._gauge_transform([candidate])
            supporters += [
                c
                for c in self._waiting
                if c is not candidate
                and self._roots(c) == self._roots(candidate)
                and self._agrees(c, hypothesis)
            ]
            supporters = self._scale_supporters(supporters)
        if len(supporters) < needed:
            return []
        start = time.perf_counter()
        transform = self._gauge_transform(supporters)
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
        # Other waiting edges now inside one component are tested like any such edge.
        inside = [c for c in self._waiting if self._same_component(c) and c not in supporters]
        self._waiting = [c for c in self._waiting if not self._same_component(c)]
        for c in inside:
            self._admit_within(c)
        return self._updates(moved_agents, "gauge")

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
        estimate = estimate_log_focal(
            pairs, self.config.tracking, search=self.config.gauge.focal_search
        )
        for agent in agents:
            self.graph.rescale_focal(agent, estimate.log_focal)
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
        """
        if not self._aligns_focal():
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
                return
            chosen = sorted(edges[agent], key=lambda c: -c.verification.similarity)
            report_phase(
                progress,
                "focal refinement",
                f"agent {agent} on {min(len(chosen), FOCAL_REFINEMENT_PAIRS)} pair(s)",
                len(settled) - 1,
                len(members) - 1,
            )
            pairs = [
                self._focal_pair(c, self.graph.agent_of[c.j] == agent)
                for c in chosen[:FOCAL_REFINEMENT_PAIRS]
            ]
            if (
                self._apply_focal([agent], [p for p in pairs if p is not None], "refined")
                is not None
            ):
                self.stats.focal_refinements += 1
            settled.add(agent)

    def _frozen(self, agent: int) -> bool:
        """Whether an agent's keyframes are held fixed (a saved map under --freeze-map)."""
        return any(g in self.graph.fixed for g in self.graph.agent_keyframes(agent))

    def _joins(self, candidate: Candidate, agent: int, settled: set[int]) -> bool:
        """Whether an edge links ``agent`` to one of the ``settled`` agents."""
        ends = {self.graph.agent_of[candidate.i], self.graph.agent_of[candidate.j]}
        return agent in ends and bool(ends & settled)

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

    def _agrees(self, candidate: Candidate, hypothesis: GaugeTransform) -> bool:
        """Whether a waiting edge's points agree once the moving side is transported."""
        x_moving, x_anchor, _ = self._oriented_correspondences(candidate)
        anchor = candidate.i if self._moving_is_j(candidate) else candidate.j
        candidate.residual_ratio = residual_ratio(
            x_anchor,
            sim3_act(hypothesis.T.to(x_moving)[None], x_moving),
            self.graph.keyframes[anchor].T_WC[:3],
        )
        return candidate.residual_ratio <= self.config.verification.max_residual_ratio

    def _gauge_transform(self, candidates: Sequence[Candidate]) -> GaugeTransform:
        """``T*`` from the lifted correspondences of edges between the same two components
        (C-Eq. 14); the rigid snap uses the first edge's endpoints."""
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
        kf_i, kf_j = self.graph.keyframes[candidate.i], self.graph.keyframes[candidate.j]
        ij, ji = candidate.link.ij, candidate.link.ji
        x_i_ij, x_j_ij = _matched_points(ij, kf_i.X_hat, kf_j.X_hat)
        x_j_ji, x_i_ji = _matched_points(ji, kf_j.X_hat, kf_i.X_hat)
        x_i = lift(kf_i.T_WC, torch.cat([x_i_ij, x_i_ji]))
        x_j = lift(kf_j.T_WC, torch.cat([x_j_ij, x_j_ji]))
        return x_i, x_j, torch.cat([ij.q[ij.valid], ji.q[ji.valid]])

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

    # ------------------------------------------------------------------ global BA

    def _anchor(self, root: int) -> int:
        """Pinned keyframe of a component: the first keyframe of its lowest agent."""
        return self.graph.global_index(root, 0)

    def _global_ba(self) -> list[PoseUpdate]:
        """In-stream BA (C-Eq. 5) of every component that received new inter edges."""
        start = time.perf_counter()
        updates: list[PoseUpdate] = []
        for root in sorted({self.gauges.find(r) for r in self._dirty_roots}):
            members = self.gauges.members(root)
            result = self.graph.optimize(
                members, self._anchor(root), self.config.global_ba.max_iters_stream
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


def _scoped(progress: PhaseCallback | None, members: Sequence[int]) -> PhaseCallback | None:
    """``progress`` naming a component's agents at the start of every event's detail."""
    if progress is None:
        return None
    agents = ("agents " if len(members) > 1 else "agent ") + ", ".join(map(str, members))

    def report(event: PhaseEvent) -> None:
        progress(replace(event, detail="; ".join(filter(None, (agents, event.detail)))))

    return report


def _matched_points(
    matches: DirectedMatches, X_target: Tensor, X_source: Tensor
) -> tuple[Tensor, Tensor]:
    """Valid matches of ``matches`` as point pairs ``(X_target[idx[n]], X_source[n])``.

    Args:
        matches: every pixel ``n`` of the source keyframe looked up in the target.
        X_target: ``(H, W, 3)`` target canonical pointmap.
        X_source: ``(H, W, 3)`` source canonical pointmap.

    Returns:
        ``(M, 3)`` target points and ``(M, 3)`` source points (camera frames).
    """
    valid = matches.valid
    return gather_points(X_target, matches.idx[valid]), X_source.reshape(-1, 3)[valid]
