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
   keyframe on tracking's own tests: the sequence resumes) and whose pose the camera's
   motion since it was lost allows (else the next lost frame must confirm it); frames that
   cannot be relocalized are counted as lost, never invented. A first frame that cannot
   start the map (self-calibration finds nothing in front of the camera) is lost too, and
   the next one tries.

Every tracked frame is stored as ``(frame, anchor keyframe, T_rel)`` (C-Sec. A.8), so the
trajectory written at the end follows every later correction of its anchor keyframe.

Keyframes outside the newest ``session.resident_keyframes``, and the matches of the edges
between them, are paged out to a private spill folder after every frame and every update,
and read back while a step needs them (:class:`~como3r.frontend.paging.AgentPaging`): the
agent's memory does not grow with its keyframes' arrays, its results do not change.

:class:`AgentFrontend` holds the state and the per-frame loop; keyframe creation, linking and
the local solve (step 3) are its part :mod:`.keyframe_linking`, relocalization (step 5) its
part :mod:`.relocalization`.
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
from como3r.frontend.graph import Edge, QuadraticEdgeCache
from como3r.frontend.keyframe_linking import KeyframeLinking
from como3r.frontend.keyframes import (
    FrameRecord,
    Keyframe,
    KeyframeStore,
    apply_pointmap_update,
    apply_pose_update,
)
from como3r.frontend.packets import KeyframePacket, PointmapRefresh, PointmapUpdate, PoseUpdate
from como3r.frontend.paging import AgentPaging, plain_matches
from como3r.frontend.pairs import (
    DirectedMatches,
)
from como3r.frontend.relocalization import HeldRelocalization, Relocalization
from como3r.frontend.timing import StageTimer, TimedPrior
from como3r.frontend.tracker import FrameTracker, TrackResult, solved
from como3r.geometry.camera import to_focal
from como3r.geometry.lie import sim3_compose, sim3_identity
from como3r.prior.base import Encoding, Prior, View
from como3r.prior.retrieval import Quantized, RetrievalDatabase

logger = logging.getLogger(__name__)


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


class AgentFrontend(KeyframeLinking, Relocalization):
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
        self._held: HeldRelocalization | None = None  # a relocalization awaiting confirmation
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
        return self._accept(result, view.index, timestamp, enc, colors)

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
        self, result: TrackResult, index: int, timestamp: float, enc: Encoding, colors: np.ndarray
    ) -> str:
        """Record a frame tracked on the current keyframe; promote it to a keyframe when due.
        Returns ``"keyframe"`` or ``"tracked"``."""
        with self.timer.stage("keyframe"):
            self._record_tracked(result, index, timestamp, enc, colors)
        return "keyframe" if result.new_keyframe else "tracked"

    def _record_tracked(
        self, result: TrackResult, index: int, timestamp: float, enc: Encoding, colors: np.ndarray
    ) -> None:
        """:meth:`_accept`'s work, on the current keyframe."""
        keyframe = self.keyframes.last
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
        retrieval = kf.retrieval
        if self.database is not None and retrieval is not None:
            # what the coordinator's binary ASMK reads of the descriptors, and all it reads
            # of them: per-word sign bits, a third smaller at MASt3R's shapes (issue 39);
            # words quantised again only for a keyframe exported again
            descriptors = retrieval[0] if words is None else Quantized(retrieval[0], words)
            retrieval = self.database.aggregate(descriptors)
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
            retrieval=retrieval,
            sequential_ij=plain_matches(seq.get((kf_id - 1, kf_id))),
            sequential_ji=plain_matches(seq.get((kf_id, kf_id - 1))),
            previous=previous,
            K=kf.K,
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
