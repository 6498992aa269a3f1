"""One agent's dense SLAM front-end (C-Sec. 3.3, A.8; the MASt3R-SLAM design).

``AgentFrontend.process`` takes the agent's frames in order and

1. initialises the first keyframe from the prior's prediction of the frame with itself;
2. tracks each frame against the current keyframe (C-Eq. 2), fusing it (C-Eq. 3);
3. when ``min(nu, nu_uniq)`` drops below the threshold, promotes the frame to a keyframe,
   links it to its predecessor (sequential edge) and to verified intra-agent loop
   candidates from the agent's own retrieval database, and refines the local keyframe
   graph by LM-IRLS (C-Sec. B.2, pin 1);
4. when tracking fails after a frame that tracked well but stayed above the threshold
   (the motion outran the keyframe rule), promotes that frame late and tracks against it
   (not in the paper: at 20 deg per frame one step can go from 36 % overlap to none);
5. when tracking still fails, relocalizes: retrieves the agent's keyframes most like the frame,
   tracks against each and re-anchors on the first that matches well enough (the current
   keyframe on tracking's own tests: the sequence resumes); frames that cannot be
   relocalized are counted as lost, never invented. A first frame that cannot start the map
   (self-calibration finds nothing in front of the camera) is lost too, and the next one
   tries.

Every tracked frame is stored as ``(frame, anchor keyframe, T_rel)`` (C-Sec. A.8), so the
trajectory written at the end follows every later correction of its anchor keyframe.

Keyframes outside the newest ``session.resident_keyframes``, and the matches of the edges
between them, are paged out to a private spill folder after every frame and every update,
and read back while a step needs them (:class:`~como3r.frontend.paging.AgentPaging`): the
agent's memory does not grow with its keyframes' arrays, its results do not change.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from como3r.config import Config
from como3r.errors import GeometryError, InputError
from como3r.frontend.calibration import estimate_intrinsics, refine_focal
from como3r.frontend.graph import Edge, QuadraticEdgeCache, build_factors
from como3r.frontend.keyframes import (
    Keyframe,
    KeyframeStore,
    apply_pointmap_update,
    apply_pose_update,
)
from como3r.frontend.packets import KeyframePacket, PointmapRefresh, PointmapUpdate, PoseUpdate
from como3r.frontend.paging import AgentPaging, PagedKeyframe, plain_matches
from como3r.frontend.pairs import (
    DirectedMatches,
    PairLink,
    directed_matches,
    direction_passes,
    link_pairs,
)
from como3r.frontend.timing import StageTimer, TimedPrior
from como3r.frontend.tracker import FrameTracker, TrackResult, inlier_fraction, solved
from como3r.geometry.camera import lock_to_rays, to_focal
from como3r.geometry.lie import sim3_compose, sim3_identity, sim3_inverse
from como3r.geometry.units import scene_depth
from como3r.optim.factors import Factor
from como3r.optim.optimizer import gauss_newton_irls
from como3r.optim.values import PoseValues
from como3r.prior.base import Encoding, Prior, View
from como3r.prior.retrieval import Quantized, RetrievalDatabase

logger = logging.getLogger(__name__)

#: The most recent keyframes, which relocalization always tries and accepts on tracking's
#: own tests (any other retrieved keyframe needs ``tracking.reloc_match_fraction``).
RECENT_KEYFRAMES = 3


@dataclass(frozen=True)
class FrameRecord:
    """A tracked frame: its pose is ``T_WC(anchor) * T_rel`` (C-Sec. A.8)."""

    frame_index: int
    timestamp: float
    anchor: int
    T_rel: Tensor


@dataclass(frozen=True)
class _TrackedFrame:
    """The last frame tracked without becoming a keyframe: what promoting it late needs."""

    result: TrackResult
    keyframe: Keyframe
    index: int
    timestamp: float
    encoding: Encoding
    colors: np.ndarray


@dataclass(frozen=True)
class _UnsettledFrame:
    """A frame tracked (not a keyframe) before the agent's camera settled: what solving its
    pose again on the settled camera needs."""

    frame_index: int
    keyframe: int
    X_ff: Tensor  # (H, W, 3) its pointmap on the first frame's camera
    matches: DirectedMatches


@dataclass
class FrontendStats:
    """Counters reported in metrics.json."""

    frames: int = 0
    tracked: int = 0
    lost: int = 0
    relocalized: int = 0
    keyframes: int = 0
    #: keyframes made of the previous frame when tracking the next one failed
    late_keyframes: int = 0
    #: sequential edges whose direction (kf - 1, kf) failed tracking's agreement test and
    #: was left without valid matches (:meth:`AgentFrontend._checked_direction`)
    rejected_directions: int = 0
    loop_candidates: int = 0
    loop_edges: int = 0
    local_solves: int = 0
    local_solve_seconds: float = 0.0
    lost_frames: list[int] = field(default_factory=list)
    #: focal length (pixels at network resolution) of the self-calibration, None without
    estimated_focal: float | None = None
    #: the first frame's estimate, before the keyframes' pairs refined it
    first_frame_focal: float | None = None
    #: wall seconds per stage (prior_encode, prior_decode, matching, tracking, ...)
    stage_seconds: dict[str, float] = field(default_factory=dict)


class AgentFrontend:
    """Dense SLAM front-end of one agent.

    Args:
        prior: the two-view prior.
        config: the run's configuration.
        agent: the agent's id.
        codebook: ``(K, d)`` retrieval codebook; without one there is no intra-agent loop
            closure and relocalization only tries the most recent keyframes.
        upsampling: network pixels per pixel of the agent's input
            (:func:`como3r.data.preprocess.upsampling`; see :class:`FrameTracker`).
    """

    def __init__(
        self,
        prior: Prior,
        config: Config,
        agent: int = 0,
        codebook: np.ndarray | None = None,
        upsampling: float = 1.0,
    ) -> None:
        self.config = config
        self.agent = agent
        self.keyframes = KeyframeStore()
        session = config.session
        self.paging = AgentPaging(
            session.resident_keyframes, Path(session.spill_dir) if session.spill_dir else None
        )
        self.edges: list[Edge] = []
        self._quadratic = QuadraticEdgeCache()  # models of the edges far from the newest
        self.records: list[FrameRecord] = []
        self.stats = FrontendStats()
        self.timer = StageTimer(self.stats.stage_seconds)
        self.prior = TimedPrior(prior, self.timer)
        self.tracker = FrameTracker(self.prior, config, self.timer, upsampling)
        self.database = (
            RetrievalDatabase(codebook, config.retrieval) if codebook is not None else None
        )
        self.new_keyframes: list[int] = []  # keyframes not yet handed to a coordinator
        self._unsent_words: dict[int, np.ndarray] = {}  # their retrieval words, by kf_id
        self._T_kf_prev: Tensor | None = None
        self._lost = False
        self._last_tracked: _TrackedFrame | None = None
        self._K: Tensor | None = None  # intrinsics at network resolution (calibrated runs)
        tracking = config.tracking
        # a self-calibrated camera is re-estimated on the first keyframes' pairs before they
        # leave the agent (frontend.calibration)
        self._camera_settled = (
            config.calibrated
            or not tracking.self_calibration
            or tracking.self_calibration_keyframes == 0
        )
        self._unsettled: list[_UnsettledFrame] = []  # tracked before the camera settled

    def process(
        self, view: View, timestamp: float, colors: np.ndarray, encoding: Encoding | None = None
    ) -> str:
        """Process the next frame; returns ``"keyframe"``, ``"tracked"``, ``"relocalized"``
        or ``"lost"``.

        Args:
            view: the pre-processed frame.
            timestamp: seconds.
            colors: ``(H, W, 3)`` uint8 image at network resolution.
            encoding: the prior's encoding of ``view`` when it was made ahead
                (:mod:`como3r.runtime.prefetch`); None encodes it here.
        """
        outcome = self._process(view, timestamp, colors, encoding)
        self.page_out()
        return outcome

    def page_out(self) -> None:
        """Let go of the arrays of the keyframes and edges outside the working set
        (:class:`~como3r.frontend.paging.AgentPaging`); done after every frame and update."""
        self.paging.page_out(self.keyframes.keyframes, self.edges)

    def _process(
        self, view: View, timestamp: float, colors: np.ndarray, encoding: Encoding | None
    ) -> str:
        self.stats.frames += 1
        if self.config.calibrated:
            if view.K is None:
                raise InputError(
                    f"agent {self.agent}: a calibrated run needs calib.txt "
                    "(fx fy cx cy) in the agent folder"
                )
            self._K = view.K
        enc = self.prior.encode(view) if encoding is None else encoding
        if len(self.keyframes) == 0:
            return self._initialise(enc, view.index, timestamp, colors)
        if self._lost:
            with self.timer.stage("relocalization"):
                return self._relocalize(enc, view.index, timestamp, colors)
        result = self.tracker.track(enc, self.keyframes.last, self._T_kf_prev)
        if not result.ok and self._promote_last_tracked():
            result = self.tracker.track(enc, self.keyframes.last, self._T_kf_prev)
        if not result.ok:
            self._lost = True
            with self.timer.stage("relocalization"):
                return self._relocalize(enc, view.index, timestamp, colors)
        with self.timer.stage("keyframe"):
            self._accept(result, self.keyframes.last, view.index, timestamp, enc, colors)
        return "keyframe" if result.new_keyframe else "tracked"

    def _initialise(self, enc: Encoding, index: int, timestamp: float, colors: np.ndarray) -> str:
        """The frame becomes the first keyframe (``"keyframe"``), or, when self-calibration
        finds nothing in front of the camera (a covered lens, a blank wall), it is lost and
        the next frame tries again (``"lost"``): one unusable frame must not end the agent."""
        pred = self.prior.decode(enc, enc)
        if not self.config.calibrated and self.config.tracking.self_calibration:
            try:
                self._K = estimate_intrinsics(pred.X_ii, pred.C_ii)
            except GeometryError as exc:
                logger.warning(
                    "agent %d: frame %d cannot start the map: %s", self.agent, index, exc
                )
                self.stats.lost += 1
                self.stats.lost_frames.append(index)
                return "lost"
            self.stats.estimated_focal = self.stats.first_frame_focal = float(self._K[0, 0])
        T_WC = sim3_identity(dtype=pred.X_ii.dtype, device=pred.X_ii.device)
        kf = self._add_keyframe(enc, index, timestamp, T_WC, pred.X_ii, pred.C_ii, colors)
        self._index(kf)
        self._T_kf_prev = sim3_identity(dtype=pred.X_ii.dtype, device=pred.X_ii.device)
        self.stats.tracked += 1  # the first frame has its pose (it defines the map's frame)
        return "keyframe"

    def _accept(
        self,
        result: TrackResult,
        keyframe: Keyframe,
        index: int,
        timestamp: float,
        enc: Encoding,
        colors: np.ndarray,
    ) -> None:
        """Record a tracked frame; promote it to a keyframe when due."""
        self.stats.tracked += 1
        if not result.new_keyframe:
            self.records.append(FrameRecord(index, timestamp, keyframe.kf_id, result.T_kf))
            if not self._camera_settled:
                self._unsettled.append(
                    _UnsettledFrame(index, keyframe.kf_id, result.X_ff, result.matches)
                )
            self._T_kf_prev = result.T_kf
            self._last_tracked = _TrackedFrame(result, keyframe, index, timestamp, enc, colors)
            return
        T_WC = sim3_compose(keyframe.T_WC, result.T_kf)
        new = self._add_keyframe(enc, index, timestamp, T_WC, result.X_ff, result.C_ff, colors)
        self._link_new_keyframe(new, result.matches)
        self._T_kf_prev = sim3_identity(dtype=T_WC.dtype, device=T_WC.device)

    def _promote_last_tracked(self) -> bool:
        """Make the last tracked frame the keyframe it should have been; False if there is
        none (it is not the latest frame processed on the current keyframe)."""
        last, self._last_tracked = self._last_tracked, None
        if (
            last is None
            or last.keyframe is not self.keyframes.last
            or not self.records
            or self.records[-1].frame_index != last.index
        ):
            return False
        self.records.pop()  # re-recorded as a keyframe, anchored on itself
        with self.timer.stage("keyframe"):
            T_WC = sim3_compose(last.keyframe.T_WC, last.result.T_kf)
            new = self._add_keyframe(
                last.encoding,
                last.index,
                last.timestamp,
                T_WC,
                last.result.X_ff,
                last.result.C_ff,
                last.colors,
            )
            self._link_new_keyframe(new, last.result.matches)
        self._T_kf_prev = sim3_identity(dtype=T_WC.dtype, device=T_WC.device)
        self.stats.late_keyframes += 1
        logger.info(
            "agent %d: frame %d promoted to keyframe after frame tracking failed",
            self.agent,
            last.index,
        )
        return True

    def _add_keyframe(
        self,
        enc: Encoding,
        index: int,
        timestamp: float,
        T_WC: Tensor,
        X: Tensor,
        C: Tensor,
        colors: np.ndarray,
    ) -> Keyframe:
        """A new keyframe with canonical pointmap ``X`` ``(H, W, 3)``, on the agent's
        calibrated rays (C-Eq. 16) when it has intrinsics."""
        if self._K is not None:
            X = lock_to_rays(X, self._K.to(X))
        kf = PagedKeyframe(
            kf_id=len(self.keyframes),
            frame_index=index,
            timestamp=timestamp,
            encoding=enc,
            T_WC=T_WC,
            X_hat=X.clone(),
            C_hat=C.clone(),
            X_init=X.clone(),
            C_init=C.clone(),
            colors=colors,
            retrieval=self.prior.retrieval_features(enc) if self.database is not None else None,
            K=None if self._K is None else self._K.to(X),
        )
        self.keyframes.add(kf)
        self._last_tracked = None
        self.records.append(
            FrameRecord(
                index, timestamp, kf.kf_id, sim3_identity(dtype=T_WC.dtype, device=T_WC.device)
            )
        )
        self.new_keyframes.append(kf.kf_id)
        self.stats.keyframes += 1
        self.tracker.reset_warm_start()
        return kf

    def _link_new_keyframe(self, kf: Keyframe, tracked: DirectedMatches) -> None:
        """Sequential edge, verified loop edges, local solve, then index the keyframe.

        The sequential edge's direction (kf, kf - 1), every pixel of keyframe kf - 1 looked
        up in kf, is ``tracked``: the tracking's matches of the frame that became kf, from
        the same ordered decode (kf, kf - 1). Only (kf - 1, kf) is decoded and matched here.
        """
        quantized = self._quantized(kf)
        candidates = self._loop_candidates(kf, quantized)
        previous = self.keyframes[kf.kf_id - 1]
        pred = self.prior.decode(previous.encoding, kf.encoding)
        with self.timer.stage("matching"):
            ij = directed_matches(pred, self.config.matching, self.config.tracking.q_min)
        with self.timer.stage("tracking"):
            ij = self._checked_direction(ij, previous, kf)
        self._add_edge_pair(previous.kf_id, kf.kf_id, PairLink(ij, tracked), "sequential")
        verification = self.config.verification

        def loop_test(matches: DirectedMatches, covisible: float | None) -> bool:
            # a loop needs matches where the pair's own geometry says both views see: the
            # match fraction alone accepts repeated structure (the coordinator's same test)
            return direction_passes(
                matches,
                covisible,
                self.config.local_solve.min_match_fraction,
                verification.min_covisible_ratio,
            )

        # a loop candidate failing its first direction cannot pass: its second matching is
        # skipped
        links = link_pairs(
            self.prior,
            [(self.keyframes[p].encoding, kf.encoding) for p in candidates],
            self.config.matching,
            self.config.tracking.q_min,
            verification.covisible_min_confidence,
            self.timer,
            screen=lambda k, ij, covisible: loop_test(ij, covisible),
        )
        for partner, link in zip(candidates, links):
            if (
                link is not None
                and loop_test(link.ij, link.covisible_ij)
                and loop_test(link.ji, link.covisible_ji)
            ):
                self._add_edge_pair(partner, kf.kf_id, link, "loop")
                self.stats.loop_edges += 1
        self._local_solve()
        self._index(kf, quantized)
        self._settle_camera_when_due()

    def _checked_direction(
        self, ij: DirectedMatches, previous: Keyframe, kf: Keyframe
    ) -> DirectedMatches:
        """The direction (kf - 1, kf) of a new sequential edge, put to tracking's test.

        Tracking accepted the other direction, (kf, kf - 1), only once its matches agreed
        with the pose solved from them (``tracking.min_inlier_fraction`` within
        :attr:`FrameTracker.inlier_angle_deg` and ``sigma_dist``). This direction comes from
        a decode of its own, (kf - 1, kf), with its own draw of the prior's pose error, and
        nothing tested it: with only the previous keyframe to link to, a wrong one pulled
        the new keyframe towards its pose in the local solve. So it is solved alone as a
        frame is tracked (C-Eq. 2, C-Eq. 17 when calibrated; from the tracked pose) and,
        when its matches do not agree with their own pose, it keeps no valid match: the
        edge stands on the tracked direction, as a frame whose matches disagree is not
        tracked. Measured on the realistic prior (benchmarks/robustness.py scenes, 24
        frames; 16 runs: fast, room, street, forward, rotation, revisit at 640x480 seeds 0
        and 1, fast at 320x240 seeds 0 and 1, low-texture 640x480 and aerial 320x240 seed
        0; 69 sequential edges): agreement 0.65-0.91, except the fast family's seed 1,
        keyframes 14 -> 22 (16 deg of turn): 0.18 at 640x480, 0.36 at 320x240. Its decode
        was 4.1 deg and 28 % of the baseline off; solved alone 2.8 deg off (the tracked
        direction 0.05 deg), it had pulled keyframe 22 1.7 deg off (ATE 1.18 and 1.10 % of
        the path; 0.13 and 0.17 % without it). A decode error that leaves its matches
        agreeing with their (wrong) pose is not caught: a rigid 6 deg turn of ``X_ji``
        injected into one such decode on the default scene at 128x96 passes, and the local
        solve weighs it against the tracked direction as before.

        Args:
            ij: pixel of ``previous`` (keyframe kf - 1) per pixel of ``kf``.
            previous, kf: the two keyframes, ``kf`` posed by tracking.
        """
        tracking = self.config.tracking
        if tracking.min_inlier_fraction <= 0.0 or not bool(ij.valid.any()):
            return ij
        # the previous keyframe posed in the new one's camera, from the tracked pose
        T_init = sim3_compose(sim3_inverse(kf.T_WC), previous.T_WC)
        T, report = self.tracker.solve(previous.X_hat, kf, ij, T_init)
        agreement = (
            inlier_fraction(
                T, previous.X_hat, kf.X_hat, ij, tracking, self.tracker.inlier_angle_deg
            )
            if solved(T, report)
            else 0.0
        )
        if agreement >= tracking.min_inlier_fraction:
            return ij
        self.stats.rejected_directions += 1
        logger.info(
            "agent %d: edge (%d, %d) direction dropped: %.2f of its matches agree with "
            "their own pose (minimum %.2f)",
            self.agent,
            previous.kf_id,
            kf.kf_id,
            agreement,
            tracking.min_inlier_fraction,
        )
        return replace(ij, valid=torch.zeros_like(ij.valid))

    def _quantized(self, kf: Keyframe) -> Quantized | None:
        """``kf``'s retrieval descriptors with their visual words, for its loop query and its
        indexing (one nearest-centroid search, the bulk of both at the released codebook's
        size); None without a database."""
        if self.database is None or kf.retrieval is None:
            return None
        with self.timer.stage("retrieval"):
            return self.database.quantize(kf.retrieval[0])

    def _index(self, kf: Keyframe, quantized: Quantized | None = None) -> None:
        """Add the keyframe to the agent's retrieval database (after querying with it) by
        its :meth:`_quantized` descriptors (made here where not given), whose words then
        wait for the keyframe's packet (a coordinator with the same codebook takes them)."""
        if self.database is not None and kf.retrieval is not None:
            if quantized is None:
                quantized = self._quantized(kf)
            with self.timer.stage("retrieval"):
                self.database.add(self.agent, kf.kf_id, quantized, kf.retrieval[1])
            self._unsent_words[kf.kf_id] = quantized.words.astype(np.int32)

    def _add_edge_pair(self, i: int, j: int, link: PairLink, kind: str) -> None:
        self.edges.append(Edge(i, j, link.ij, kind))
        self.edges.append(Edge(j, i, link.ji, kind))

    def _loop_candidates(self, kf: Keyframe, quantized: Quantized | None) -> list[int]:
        """Own keyframes most like ``kf`` (not its predecessor), above the threshold, by its
        :meth:`_quantized` descriptors."""
        if not self.config.loop_closure or self.database is None or quantized is None:
            return []
        with self.timer.stage("retrieval"):
            hits = self.database.query(
                quantized,
                agent=self.agent,
                exclude_keyframes=[(self.agent, kf.kf_id - 1)],
            )
        self.stats.loop_candidates += len(hits)
        return [h.keyframe for h in hits]

    def _local_solve(self) -> None:
        """LM-IRLS over the agent's keyframe graph with the first keyframe pinned."""
        if not self.edges:
            return
        solve = self.config.local_solve
        with self.timer.stage("local_solve"):
            values = PoseValues.from_poses(
                self.keyframes.poses(), num_pinned=solve.pinned_keyframes
            )
            factors = self._solve_factors()
            # the newest keyframe's depth is the step tolerance's length (O(1) per solve)
            last = self.keyframes.last
            solved, report = gauss_newton_irls(
                factors, values, solve, length_scale=scene_depth([last.T_WC], [last.X_hat])
            )
        self.stats.local_solves += 1
        self.stats.local_solve_seconds += report.seconds
        if report.diverged:
            logger.warning("agent %d: local solve diverged; poses kept", self.agent)
            return
        self.keyframes.set_poses(solved.poses)

    def _solve_factors(self) -> list[Factor]:
        """Every edge of the graph (C-Sec. 3.3): dense factors for those touching the newest
        ``local_solve.dense_keyframes`` keyframes, quadratic models for the others
        (:class:`~.graph.QuadraticEdgeCache`), so a solve's memory does not grow with the
        graph. Paged-out pointmaps are read back for the solve only."""
        solve = self.config.local_solve
        first_dense = len(self.keyframes) - solve.dense_keyframes
        old = [n for n, e in enumerate(self.edges) if max(e.i, e.j) < first_dense]
        dense = [e for e in self.edges if max(e.i, e.j) >= first_dense]
        factors: list[Factor] = []
        if dense:
            points = self.paging.solve_points(self.keyframes.__getitem__)
            factors.append(build_factors(dense, points, lambda k: k, self.config.tracking))
        if old:
            factors.append(
                self._quadratic.factor(
                    self.edges,
                    old,
                    lambda: self.paging.solve_points(self.keyframes.__getitem__),
                    lambda k: self.keyframes[k].version("pointmaps"),
                    self.config.tracking,
                    solve.relinearize_tol,
                )
            )
        return factors

    def _settle_camera_when_due(self) -> None:
        if len(self.keyframes) >= self.config.tracking.self_calibration_keyframes:
            self.settle_camera()

    def settle_camera(self) -> None:
        """Fix the agent's self-calibrated camera (once): the focal length that best aligns
        its keyframe pairs (:func:`~como3r.frontend.calibration.refine_focal`), to which
        every keyframe moves before a local solve; from then on keyframes are sent.

        Called when the agent has ``tracking.self_calibration_keyframes`` keyframes, and by
        the runtimes at the end of an agent's stream (a short one settles on what it has).
        """
        if self._camera_settled:
            return
        self._camera_settled = True
        unsettled, self._unsettled = self._unsettled, []
        with self.timer.stage("calibration"):
            estimate = refine_focal(
                self.keyframes.keyframes,
                self.edges,
                self.config.tracking,
                self.config.gauge.focal_search,
            )
            if estimate is None or estimate.log_focal == 0.0:
                return
            first_K, focal = self._K, float(self._K[0, 0]) * math.exp(estimate.log_focal)
            for kf in self.keyframes.keyframes:
                kf.rescale_focal(focal)
            self._K = self.keyframes.last.K.to(self._K)
        self.stats.estimated_focal = focal
        logger.info(
            "agent %d: camera settled on %d keyframes: focal %.1f px (first frame %.1f)",
            self.agent,
            len(self.keyframes),
            focal,
            self.stats.first_frame_focal,
        )
        self._local_solve()
        with self.timer.stage("tracking"):
            self._track_again(unsettled, first_K, focal)
        self.page_out()  # the focal search and the rescale read every keyframe's pointmaps

    def _track_again(self, frames: list[_UnsettledFrame], first_K: Tensor, focal: float) -> None:
        """Solve the poses of ``frames`` (tracked on the first frame's camera ``first_K``)
        again on the settled one, from their pointmaps and matches (C-Eq. 16-17): a focal
        length 14 % off biased them by up to 7 cm on a room where the keyframes were within
        3 mm once settled."""
        position = {record.frame_index: k for k, record in enumerate(self.records)}
        for frame in frames:
            k = position.get(frame.frame_index)
            if k is None or self.records[k].anchor != frame.keyframe:
                continue  # promoted to a keyframe since: its record is anchored on itself
            X_ff, _ = to_focal(frame.X_ff, first_K.to(frame.X_ff), focal)
            T_kf, report = self.tracker.solve(
                X_ff, self.keyframes[frame.keyframe], frame.matches, self.records[k].T_rel
            )
            if solved(T_kf, report):
                self.records[k] = replace(self.records[k], T_rel=T_kf)

    def _relocalize(self, enc: Encoding, index: int, timestamp: float, colors: np.ndarray) -> str:
        """Re-anchor the frame on a retrieved keyframe, or count it as lost.

        On the :data:`RECENT_KEYFRAMES` most recent keyframes, where tracking would be had
        the agent not been lost, tracking's own tests suffice: on the current keyframe the
        frame resumes the sequence (a keyframe when due), on an earlier one it becomes a
        keyframe joined to it by a loop edge. Any other keyframe needs
        ``reloc_match_fraction`` (MASt3R-SLAM's bar against a wrong retrieval). Measured on
        the ``covered`` family (lens covered for 5 frames, 9 degrees of turn per frame,
        320x240): the first visible frame matched the current keyframe at 0.22, under the
        0.3 bar, and the agent stayed lost in new territory for 8 processed frames. On the
        room family at 640x480 (seed 0) the prior failed grossly on frame 16 with the current
        keyframe and with the promoted last frame; it matched the keyframe before at 0.29,
        and was lost (tracked 11 of 12 frames).
        """
        identity = sim3_identity(
            dtype=self.keyframes.last.T_WC.dtype, device=self.keyframes.last.T_WC.device
        )
        current = self.keyframes.last
        recent = self._recent_keyframes()
        for kf_id in self._relocalization_candidates(enc):
            keyframe = self.keyframes[kf_id]
            self.tracker.reset_warm_start()
            result = self.tracker.track(enc, keyframe, identity, fuse=False)
            if (
                not result.ok
                or kf_id not in recent
                and (result.match_fraction < self.config.tracking.reloc_match_fraction)
            ):
                continue
            resumes = keyframe is current
            self._lost = False
            self.stats.relocalized += 1
            logger.info("agent %d: frame %d relocalized on keyframe %d", self.agent, index, kf_id)
            if resumes:
                with self.timer.stage("keyframe"):
                    self._accept(result, keyframe, index, timestamp, enc, colors)
            else:
                self._promote_after_reloc(result, keyframe, index, timestamp, enc, colors)
            return "relocalized"
        self.stats.lost += 1
        self.stats.lost_frames.append(index)
        return "lost"

    def _promote_after_reloc(
        self,
        result: TrackResult,
        keyframe: Keyframe,
        index: int,
        timestamp: float,
        enc: Encoding,
        colors: np.ndarray,
    ) -> None:
        """The relocalized frame becomes a keyframe linked to the keyframe it matched."""
        self.stats.tracked += 1
        T_WC = sim3_compose(keyframe.T_WC, result.T_kf)
        new = self._add_keyframe(enc, index, timestamp, T_WC, result.X_ff, result.C_ff, colors)
        link = link_pairs(
            self.prior,
            [(keyframe.encoding, new.encoding)],
            self.config.matching,
            self.config.tracking.q_min,
            timer=self.timer,
        )[0]
        self._add_edge_pair(keyframe.kf_id, new.kf_id, link, "loop")
        self._local_solve()
        self._index(new)
        self._settle_camera_when_due()
        self._T_kf_prev = sim3_identity(dtype=T_WC.dtype, device=T_WC.device)

    def _recent_keyframes(self) -> list[int]:
        """Ids of the :data:`RECENT_KEYFRAMES` most recent keyframes, newest first."""
        newest = len(self.keyframes) - 1
        return list(range(newest, max(-1, newest - RECENT_KEYFRAMES), -1))

    def _relocalization_candidates(self, enc: Encoding) -> list[int]:
        recent = self._recent_keyframes()
        if self.database is None or len(self.database) == 0:
            return recent
        desc, _ = self.prior.retrieval_features(enc)
        with self.timer.stage("retrieval"):
            hits = self.database.query(desc, agent=self.agent)
        return list(dict.fromkeys([h.keyframe for h in hits] + recent))

    def trajectory(self) -> tuple[np.ndarray, np.ndarray, Tensor]:
        """Every tracked frame: ``(frame indices (N,), timestamps (N,), T_WC (N, 8))``."""
        records = sorted(self.records, key=lambda r: r.frame_index)
        if not records:
            return np.zeros(0, dtype=np.int64), np.zeros(0), torch.zeros(0, 8)
        anchors = torch.stack([self.keyframes[r.anchor].T_WC for r in records])
        T_rel = torch.stack([r.T_rel.to(anchors) for r in records])
        return (
            np.array([r.frame_index for r in records]),
            np.array([r.timestamp for r in records]),
            sim3_compose(anchors, T_rel),
        )

    def keyframe_trajectory(self) -> tuple[np.ndarray, np.ndarray, Tensor]:
        """Keyframes only: ``(frame indices, timestamps, T_WC (K, 8))``."""
        if len(self.keyframes) == 0:
            return np.zeros(0, dtype=np.int64), np.zeros(0), torch.zeros(0, 8)
        return (
            np.array([kf.frame_index for kf in self.keyframes]),
            np.array([kf.timestamp for kf in self.keyframes]),
            self.keyframes.poses(),
        )

    def export_keyframe(self, kf_id: int) -> KeyframePacket:
        """The packet announcing keyframe ``kf_id`` to a coordinator (C-Sec. B.1)."""
        kf = self.keyframes[kf_id]
        words = self._unsent_words.pop(kf_id, None)
        seq = {(e.i, e.j): e.matches for e in self.edges if e.kind == "sequential"}
        previous = None
        if kf_id > 0:
            prev = self.keyframes[kf_id - 1]
            previous = PointmapRefresh(
                prev.kf_id, prev.X_hat, prev.C_hat, prev.fused_frames, prev.K
            )
        return KeyframePacket(
            agent=self.agent,
            kf_id=kf_id,
            frame_index=kf.frame_index,
            timestamp=kf.timestamp,
            T_WC=kf.T_WC,
            X_hat=kf.X_init,
            C_hat=kf.C_init,
            colors=kf.colors,
            encoding=kf.encoding,
            retrieval=kf.retrieval,
            sequential_ij=plain_matches(seq.get((kf_id - 1, kf_id))),
            sequential_ji=plain_matches(seq.get((kf_id, kf_id - 1))),
            previous=previous,
            K=kf.K,
            retrieval_words=words,
            codebook_id=None if words is None else self.database.codebook_id,
        )

    def drain_new_keyframes(self) -> Iterator[KeyframePacket]:
        """Packets of the keyframes created since the last call, oldest first; none while
        a self-calibrated camera waits for its keyframes (:meth:`settle_camera`).

        Each packet is made when it is taken: the pose updates its predecessor caused
        (a merge moves the agent into another gauge) are in it. Packets made all at once
        would carry the poses of the gauge the agent has just left.
        """
        while self._camera_settled and self.new_keyframes:
            yield self.export_keyframe(self.new_keyframes.pop(0))
            self.page_out()

    def apply_pointmap_update(self, update: PointmapUpdate) -> None:
        """Take the coordinator's refined canonical pointmaps (C-Sec. A.7)."""
        apply_pointmap_update(self.keyframes.keyframes, update)
        self.page_out()

    def apply_pose_update(self, update: PoseUpdate) -> None:
        """Overwrite keyframe poses with the coordinator's (C-Sec. A.8; see
        :func:`~como3r.frontend.keyframes.apply_pose_update`); a focal length in the update
        becomes the agent's camera for the frames to come, as it became its keyframes'."""
        apply_pose_update(self.keyframes.keyframes, update)
        if update.focal is not None and self._K is not None and len(self.keyframes):
            self._K = self.keyframes.last.K.to(self._K)
        self.page_out()  # a focal length read every keyframe's pointmaps
