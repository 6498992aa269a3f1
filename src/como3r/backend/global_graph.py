"""The coordinator's unified multi-agent factor graph and global Sim(3) BA (C-Sec. 3.5, A.3).

Vertices are the keyframes of ALL agents in one flat global index space ``0 .. N-1``
(arrival order), with a side map ``agent_of[g]`` and, per agent, a local-to-global map
``local_to_global[a][kf_id]``. Links are

* ``"sequential"``: the intra-agent edge ``(k-1, k)`` each keyframe packet brings
  (C-Eq. 12, ``alpha``); intra-agent loop closures stay in the agents' local graphs;
* ``"loop"``: an agent's loop found again by the coordinator (como3r addition,
  ``verification.max_loop_candidates``; :meth:`~como3r.coordination.linking.
  InterAgentLinking._add_loop`);
* ``"inter"``: geometrically verified cross-agent edges (C-Eq. 12, ``nu``).

Every link stores both directions of its dense matches, so intra- and inter-agent edges
give identical ray-and-range residuals on the keyframes' current canonical pointmaps
(C-Eq. 5, 13; the factors of :func:`~como3r.frontend.graph.build_factors`).

:meth:`GlobalGraph.optimize` solves C-Eq. 5 by Gauss-Newton IRLS (C-Sec. B.2) over the
keyframes of a set of agents that share one gauge, with one anchor keyframe pinned (the
first keyframe of the component's lowest agent; for agent 0's component that is the global
gauge anchor of C-Sec. A.3). Only the keyframes connected to the anchor through links take
part: a chain cut by a relocalization (no sequential edge) keeps its poses instead of
floating freely. A divergence guard restores the previous poses when the solver refuses a
step, produces non-finite poses or moves a keyframe implausibly far.
:meth:`GlobalGraph.refine_depths` is the depth step of the terminal alternation (C-Sec. A.7),
which :meth:`~como3r.coordination.coordinator.Coordinator.finish` interleaves with
:meth:`GlobalGraph.optimize`; the depth steps are the graph's part :mod:`.graph_depth`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from como3r.backend.graph_depth import GraphDepthSteps
from como3r.backend.graph_link import GraphLink
from como3r.config import GlobalBAConfig, TrackingConfig
from como3r.errors import InputError
from como3r.frontend.graph import Edge, build_factors, count_batches
from como3r.frontend.keyframes import Keyframe
from como3r.frontend.packets import KeyframePacket, PointmapRefresh
from como3r.frontend.paging import (
    POINTMAP_FIELDS,
    KeyframeParking,
    SolvePoints,
    paged_out,
    read_fields,
    solve_points,
)
from como3r.frontend.pairs import PairLink
from como3r.geometry.camera import to_focal
from como3r.geometry.units import median_depth, median_range
from como3r.optim.factors import Factor
from como3r.optim.optimizer import gauss_newton_irls
from como3r.optim.relinearization import EdgeModels, ThresholdRelinearized
from como3r.optim.values import PoseValues

logger = logging.getLogger(__name__)

#: A whole solve that moves a keyframe by more than this many extents of the optimized
#: graph, or changes a scale by more than this factor, has diverged (the per-step guard of
#: the solver cannot see a slow blow-up over many iterations).
MAX_DISPLACEMENT_EXTENTS = 10.0
MAX_SCALE_FACTOR = 10.0


@dataclass(frozen=True)
class BAResult:
    """What one global solve did.

    Attributes:
        keyframes: global indices of the keyframes that took part (anchor included).
        iterations: Gauss-Newton iterations run.
        seconds: wall-clock time of the solve.
        reason: the solver's stop reason, or ``"no_edges"``.
        restored: the divergence guard kept the previous poses.
        max_translation_change: largest camera-centre move of the solve [world units].
    """

    keyframes: tuple[int, ...]
    iterations: int
    seconds: float
    reason: str
    restored: bool
    max_translation_change: float

    @property
    def moved(self) -> bool:
        """Whether the solve wrote new poses."""
        return bool(self.keyframes) and not self.restored and self.iterations > 0


class GlobalGraph(GraphDepthSteps):
    """Keyframes of all agents, their links, and the global Sim(3) solve.

    Args:
        tracking: noise model and Huber breakpoint of the residuals (C-Eq. 7-8).
        config: the global BA settings (C-Tab. 3).
    """

    def __init__(self, tracking: TrackingConfig, config: GlobalBAConfig) -> None:
        self.tracking = tracking
        self.config = config
        self.keyframes: list[Keyframe] = []
        self.agent_of: list[int] = []
        self.local_to_global: dict[int, list[int]] = {}
        self.links: list[GraphLink] = []
        #: agent -> its focal length in the map (``fx``, pixels) once :meth:`rescale_focal`
        #: moved it; its pointmaps are taken onto it on receipt
        self.focal: dict[int, float] = {}
        #: agent -> the focal length ``fx`` [px] its own self-calibration gave its latest
        #: keyframe (before any :meth:`rescale_focal`)
        self.own_focal: dict[int, float] = {}
        #: global indices of keyframes held fixed, like the anchor, by every solve (a saved
        #: map's keyframes under ``--freeze-map``)
        self.fixed: set[int] = set()
        #: per keyframe, how many times its pointmap or camera changed (a new pointmap,
        #: refresh, focal rescaling or refinement): what stamps the edge models
        self.versions: list[int] = []
        #: the quadratic models of the links' directed edges, kept between solves
        #: (optim.relinearization), by ``(link position, direction)``
        self.edge_models = EdgeModels()
        #: keyframe -> (its version, its pointmap's median range): what :meth:`scene_depth`
        #: reads of a keyframe whose pointmap did not change since (one float a keyframe)
        self._median_ranges: dict[int, tuple[int, float]] = {}

    def __len__(self) -> int:
        return len(self.keyframes)

    # ------------------------------------------------------------------ building

    def add_keyframe(self, packet: KeyframePacket) -> int:
        """Insert a keyframe and its sequential link; returns its global index.

        Raises:
            InputError: the packet does not carry the agent's next keyframe id.
        """
        own = self.local_to_global.setdefault(packet.agent, [])
        if packet.kf_id != len(own):
            raise InputError(
                f"coordinator: agent {packet.agent} sent keyframe {packet.kf_id} "
                f"but keyframe {len(own)} was expected (keyframes arrive in order)"
            )
        if packet.previous is not None:
            self.refresh(packet.agent, packet.previous)
        if packet.K is not None:
            self.own_focal[packet.agent] = float(packet.K[0, 0])
        X_hat, K = self._corrected(packet.agent, packet.X_hat, packet.K)
        g = self.append(
            Keyframe(
                kf_id=packet.kf_id,
                frame_index=packet.frame_index,
                timestamp=packet.timestamp,
                encoding=packet.encoding,
                T_WC=packet.T_WC.clone(),
                X_hat=X_hat,
                C_hat=packet.C_hat,
                X_init=X_hat,
                C_init=packet.C_hat,
                colors=packet.colors,
                retrieval=packet.retrieval,
                K=K,
            ),
            packet.agent,
        )
        if packet.sequential_ij is not None and packet.sequential_ji is not None:
            self.links.append(
                GraphLink(
                    own[-2], g, "sequential", PairLink(packet.sequential_ij, packet.sequential_ji)
                )
            )
        elif packet.kf_id > 0:  # the coordinator ties it to the chain if a pair allows
            logger.debug(
                "agent %d keyframe %d has no sequential edge (relocalized)",
                packet.agent,
                packet.kf_id,
            )
        return g

    def append(self, kf: Keyframe, agent: int) -> int:
        """Add ``kf`` as ``agent``'s next keyframe (no link; a stored session's keyframes
        are read back this way); returns its global index."""
        g = len(self.keyframes)
        self.local_to_global.setdefault(agent, []).append(g)
        self.keyframes.append(kf)
        self.agent_of.append(agent)
        self.versions.append(0)
        return g

    def refresh(self, agent: int, refresh: PointmapRefresh) -> None:
        """Replace a keyframe's canonical pointmap by its newer fused one.

        Raises:
            InputError: the keyframe was never received.
        """
        kf = self.keyframes[self.global_index(agent, refresh.kf_id)]
        X_hat, _ = self._corrected(agent, refresh.X_hat, refresh.K)
        kf.X_hat, kf.C_hat, kf.fused_frames = X_hat, refresh.C_hat, refresh.fused_frames
        self.versions[self.global_index(agent, refresh.kf_id)] += 1

    def rescale_focal(
        self, agent: int, log_focal: float, parking: KeyframeParking | None = None
    ) -> float:
        """Move an agent's keyframes to the focal length ``f exp(log_focal)``
        (:mod:`como3r.frontend.focal`); returns the new focal length. Keyframes and
        refreshes still on the agent's former camera are moved on receipt.

        Args:
            parking: where a paged-out keyframe's rescaled pointmaps go, one keyframe in
                memory at a time (the terminal cleanup's; None: into the keyframes, which
                then hold them until the store writes them: at 16 agents, 1.2 GB of them).

        Raises:
            InputError: the agent sent no keyframe, or its keyframes carry no intrinsics
                (not a calibrated or self-calibrated run).
        """
        current = self.agent_focal(agent)
        if current is None:
            raise InputError(
                f"coordinator: agent {agent} has no keyframe with intrinsics to rescale"
            )
        focal = current * math.exp(log_focal)
        for g in self.agent_keyframes(agent):
            kf = self.keyframes[g]
            if parking is not None and paged_out(kf):
                # as Keyframe.rescale_focal does, read back for this keyframe only; the
                # confidences are parked with the points (unchanged), so that a solve reads
                # the keyframe from the parking alone, not the store's coded pointmaps too
                X_hat, C_hat, X_init, C_init = read_fields(kf, *POINTMAP_FIELDS)
                rescaled, K = to_focal(X_hat, kf.K, focal)
                base = rescaled if X_init is X_hat else to_focal(X_init, kf.K, focal)[0]
                parking.park(
                    kf, {"X_hat": rescaled, "C_hat": C_hat, "X_init": base, "C_init": C_init}
                )
                kf.K = K
            else:
                shared = kf.X_init is kf.X_hat
                kf.rescale_focal(focal)
                if shared:  # one tensor still (the same values): the store codes it once
                    kf.X_init = kf.X_hat
            self.versions[g] += 1
        self.focal[agent] = focal
        return focal

    def agent_focal(self, agent: int) -> float | None:
        """The focal length ``fx`` [px] of an agent's keyframes in the map (they share one
        camera), or None before its first keyframe or without intrinsics."""
        indices = self.agent_keyframes(agent)
        if not indices or self.keyframes[indices[0]].K is None:
            return None
        return float(self.keyframes[indices[0]].K[0, 0])

    def _corrected(
        self, agent: int, X_hat: Tensor, K: Tensor | None
    ) -> tuple[Tensor, Tensor | None]:
        """A pointmap of ``agent`` on camera ``K`` taken onto the agent's focal length in
        the map (unchanged without intrinsics or before any :meth:`rescale_focal`)."""
        if K is None or agent not in self.focal:
            return X_hat, K
        return to_focal(X_hat, K, self.focal[agent])

    def add_inter_link(self, i: int, j: int, link: PairLink, similarity: float) -> GraphLink:
        """Insert a verified inter-agent link between global keyframes ``i`` and ``j``."""
        if self.agent_of[i] == self.agent_of[j]:
            raise InputError(
                f"coordinator: an inter-agent link needs two agents, got keyframes "
                f"{i} and {j} of agent {self.agent_of[i]}"
            )
        record = GraphLink(i, j, "inter", link, similarity)
        self.links.append(record)
        return record

    # ------------------------------------------------------------------ lookups

    def global_index(self, agent: int, kf_id: int) -> int:
        """Global index of keyframe ``kf_id`` of ``agent``."""
        own = self.local_to_global.get(agent, [])
        if not 0 <= kf_id < len(own):
            raise InputError(f"coordinator: agent {agent} keyframe {kf_id} was never received")
        return own[kf_id]

    def agent_keyframes(self, agent: int) -> list[int]:
        """Global indices of an agent's keyframes in local order."""
        return list(self.local_to_global.get(agent, []))

    def scene_depth(self, agents: Sequence[int]) -> float:
        """Median over the agents' keyframes of their median range in world units (scale
        ``s`` of ``T_WC`` times the canonical pointmap's median range): the length that the
        relative tolerances of the global solve refer to (:mod:`como3r.geometry.units`).

        :func:`~como3r.geometry.units.scene_depth`'s arithmetic, with each keyframe's median
        range kept while its :attr:`versions` entry holds: every in-stream solve asks this
        of its whole component, and a median over every pixel of every keyframe (reading
        paged-out pointmaps back) cost the 16-agent replay's two solves 0.2 s of 3.9
        (benchmarks/coordinator_replay.py), growing with the map."""
        members = [g for a in agents for g in self.agent_keyframes(a)]
        return median_depth(
            [float(self.keyframes[g].T_WC[7]) for g in members],
            [self._median_range(g) for g in members],
        )

    def _median_range(self, g: int) -> float:
        """Keyframe ``g``'s pointmap's median range (its camera's unit), made once per
        version of its pointmap."""
        kept = self._median_ranges.get(g)
        if kept is None or kept[0] != self.versions[g]:
            X_hat = read_fields(self.keyframes[g], "X_hat")  # a paged-out one stays out
            kept = (self.versions[g], float(median_range(X_hat)))
            self._median_ranges[g] = kept
        return kept[1]

    def poses(self, indices: Sequence[int]) -> Tensor:
        """``(K, 8)`` poses of the given global keyframes."""
        return torch.stack([self.keyframes[g].T_WC for g in indices])

    def set_poses(self, indices: Sequence[int], T_WC: Tensor) -> None:
        """Overwrite poses of global keyframes from ``(K, 8)``."""
        for g, pose in zip(indices, T_WC):
            self.keyframes[g].T_WC = pose.clone()

    def inter_links(self) -> list[GraphLink]:
        """The verified inter-agent links, in admission order."""
        return [link for link in self.links if link.kind == "inter"]

    # ------------------------------------------------------------------ solving

    def connected(self, agents: Sequence[int], anchor: int) -> list[int]:
        """Keyframes of ``agents`` reachable from ``anchor`` through links, sorted."""
        members = {g for a in agents for g in self.local_to_global.get(a, [])}
        neighbours: dict[int, list[int]] = {g: [] for g in members}
        for link in self.links:
            if link.i in members and link.j in members:
                neighbours[link.i].append(link.j)
                neighbours[link.j].append(link.i)
        reached, frontier = {anchor}, [anchor]
        while frontier:
            for other in neighbours[frontier.pop()]:
                if other not in reached:
                    reached.add(other)
                    frontier.append(other)
        return sorted(reached)

    def optimize(
        self, agents: Sequence[int], anchor: int, max_iters: int, max_matches: int = 0
    ) -> BAResult:
        """Global Sim(3) BA (C-Eq. 5) over ``agents``' keyframes with ``anchor`` (and the
        :attr:`fixed` keyframes) pinned.

        Args:
            agents: agents sharing one gauge.
            anchor: global index of the pinned keyframe (one of ``agents``').
            max_iters: Gauss-Newton iterations (50 in-stream, 100 per cleanup pass).
            max_matches: an edge with more valid matches than this is linearized over an
                even subset of about this many, its blocks and energy weighed by the
                share left out (:func:`~como3r.frontend.graph.thinned`;
                ``global_ba.stream_max_matches``); 0: every match (C-Eq. 5).
        """
        nodes = self.connected(agents, anchor)
        chosen = set(nodes)
        links = [
            (n, link) for n, link in enumerate(self.links) if link.i in chosen and link.j in chosen
        ]
        if not links:
            return BAResult(tuple(nodes), 0, 0.0, "no_edges", False, 0.0)
        row = {g: r for r, g in enumerate(nodes)}
        depth = self.scene_depth(agents)
        factors = [self._relinearized(links, row, depth, max_matches)]
        before = self.poses(nodes)
        pinned = torch.tensor([g == anchor or g in self.fixed for g in nodes], device=before.device)
        # float64 poses (composed and retracted in float64; the per-match work runs in the
        # pointmaps' dtype, see optim.factors); the step's translation is measured in scene
        # depths, so the tolerance holds at every scale
        solved, report = gauss_newton_irls(
            factors,
            PoseValues(before.double(), pinned),
            self.config,
            max_iters=max_iters,
            backend=self.config.linear_solver,
            length_scale=depth,
        )
        after = solved.poses.to(before.dtype)
        problem = "solver refused a step" if report.diverged else _implausible(before, after)
        if problem:
            logger.warning(
                "global BA over agents %s diverged (%s); previous poses restored",
                list(agents),
                problem,
            )
            return BAResult(
                tuple(nodes), report.iterations, report.seconds, report.reason, True, 0.0
            )
        self.set_poses(nodes, after)
        change = float((after[:, :3] - before[:, :3]).norm(dim=-1).max())
        logger.debug(
            "global BA over %d keyframes: %d iterations (%s), %d edges with a "
            "model, %d of %d edge linearizations over the matches, max move %.4g",
            len(nodes),
            report.iterations,
            report.reason,
            factors[0].reused,
            factors[0].linearized,
            factors[0].num_edges * report.iterations,
            change,
        )
        return BAResult(
            tuple(nodes), report.iterations, report.seconds, report.reason, False, change
        )

    def _relinearized(
        self,
        links: Sequence[tuple[int, GraphLink]],
        row: dict[int, int],
        depth: float,
        max_matches: int,
    ) -> ThresholdRelinearized:
        """The solve's factor over the directed edges of ``links`` (by position in
        :attr:`links`): each edge's model kept from earlier solves while its endpoints'
        pointmaps stay (:attr:`versions`) and it is thinned alike, its dense factors built
        when it needs them."""
        edges = [e for _, link in links for e in link.edges()]
        keys = [(n, d) for n, _ in links for d in (0, 1)]
        stamps = [(self.versions[e.i], self.versions[e.j], max_matches) for e in edges]
        device = edges[0].matches.idx.device
        points = solve_points(self.keyframes.__getitem__)
        return ThresholdRelinearized(
            torch.tensor([row[e.i] for e in edges], device=device),
            torch.tensor([row[e.j] for e in edges], device=device),
            keys,
            stamps,
            self.edge_models,
            lambda positions: self._factors(edges, positions, row, max_matches, points),
            self.config.relinearize_tol,
            depth,
        )

    def _factors(
        self,
        edges: Sequence[Edge],
        positions: Sequence[int],
        row: dict[int, int],
        max_matches: int,
        points: Callable[[int], SolvePoints],
    ) -> list[tuple[Factor, list[int]]]:
        """Factor batches over the ``edges`` at ``positions``
        (:func:`~como3r.frontend.graph.build_factors`: their valid matches only, thinned to
        ``max_matches`` and batched by match count:
        :func:`~como3r.frontend.graph.count_batches`), each with the positions of its
        edges; ``points``: what the solve reads of each keyframe."""
        batches: list[tuple[Factor, list[int]]] = []
        for at, chosen, weights in count_batches([edges[p] for p in positions], max_matches):
            batch = build_factors(chosen, points, row.__getitem__, self.tracking)
            if weights is not None:
                batch.weigh_edges(weights)
            batches.append((batch, [positions[k] for k in at]))
        return batches


def _implausible(before: Tensor, after: Tensor) -> str:
    """Why a solve from poses ``before (K, 8)`` to ``after`` is implausible ('' if it is not)."""
    if not bool(after.isfinite().all()) or bool((after[:, 7] <= 0).any()):
        return "non-finite or non-positive-scale poses"
    centres = before[:, :3].double()
    extent = float((centres.amax(0) - centres.amin(0)).norm())
    displacement = float((after[:, :3].double() - centres).norm(dim=-1).max())
    if extent > 0 and displacement > MAX_DISPLACEMENT_EXTENTS * extent:
        return f"a keyframe moved {displacement:.3g} in a graph of extent {extent:.3g}"
    log_ratio = float((after[:, 7].double().log() - before[:, 7].double().log()).abs().max())
    if log_ratio > math.log(MAX_SCALE_FACTOR):
        return f"a keyframe scale changed by a factor {math.exp(log_ratio):.3g}"
    return ""
