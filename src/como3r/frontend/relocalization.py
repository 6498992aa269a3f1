"""Relocalization of a lost agent (step 5 of :mod:`como3r.frontend.agent`): the frame tracked
against the most recent keyframes and the agent's keyframes most like it, re-anchored on the
first that matches well enough and whose pose the motion since tracking was lost allows (or
the next lost frame confirms), or counted as lost.

:class:`Relocalization` is one part of :class:`~como3r.frontend.agent.AgentFrontend` (its
base class): its methods read and change the front-end's state and counters.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from torch import Tensor

from como3r.config import Config
from como3r.frontend.keyframe_linking import LOOP_MAX_ROTATION_DEG, turn_deg
from como3r.frontend.keyframes import (
    FrameRecord,
    Keyframe,
    KeyframeStore,
)
from como3r.frontend.pairs import (
    link_pairs,
)
from como3r.frontend.timing import StageTimer, TimedPrior
from como3r.frontend.tracker import FrameTracker, TrackResult
from como3r.geometry.lie import sim3_compose, sim3_identity
from como3r.prior.base import Encoding
from como3r.prior.retrieval import RetrievalDatabase

# the front-end's logger: its messages read as they did before this part had a module
logger = logging.getLogger("como3r.frontend.agent")


#: The most recent keyframes, which relocalization always tries and accepts on tracking's
#: own tests (any other retrieved keyframe needs ``tracking.reloc_match_fraction``).
RECENT_KEYFRAMES = 3

#: How many times its fastest recent turn rate the camera may turn while the agent is lost:
#: a relocalization whose pose turned further from the last tracked frame than
#: ``RELOC_TURN_RATE_FACTOR`` x that rate x the time since, plus
#: :data:`~como3r.frontend.keyframe_linking.LOOP_MAX_ROTATION_DEG` (the disagreement beyond
#: which a loop is a look-alike place, not drift), is held back until the next lost frame
#: confirms it. Not in the paper (MASt3R-SLAM accepts the first retrieved keyframe over the
#: match bar). Measured (benchmarks/robustness.py, prior v2, aliasing, 160x120 at long side
#: 512, seed 0): frame 66, lost one processed frame after the last tracked one, relocalized
#: on keyframe 11, a look-alike facade, 44 deg off (ATE 5.51 % of the path); the camera
#: turns at most 10 deg per processed frame there (18 deg in the fast family, whose turn
#: rate triples from one frame to the next: the factor 2 with the 15 deg floor allows it),
#: and the covered family's lost frames (6 processed, about 50 deg) stay well inside.
RELOC_TURN_RATE_FACTOR = 2.0

#: The latest tracked frames whose turn rates (degrees per second between consecutive ones)
#: bound the motion of a lost camera.
RELOC_RATE_FRAMES = 5


@dataclass(frozen=True)
class HeldRelocalization:
    """A relocalization its motion did not allow, held back: the next lost frame confirms it
    when it relocalizes where the held frame's pose and the motion since allow (a camera
    carried to a mapped place is confirmed, a single look-alike match is not); the held
    frame is then placed as it relocalized.

    Attributes:
        T_WC: ``(8,)`` the held frame's pose from its relocalization.
        timestamp: the held frame's time [s].
        index: the held frame's index.
        kf_id: the keyframe it relocalized on.
        result: its tracking on that keyframe.
        encoding: the held frame's encoding.
        colors: ``(H, W, 3)`` uint8, its image at network resolution.
    """

    T_WC: Tensor
    timestamp: float
    index: int
    kf_id: int
    result: TrackResult
    encoding: Encoding
    colors: np.ndarray


class Relocalization:
    """Relocalization of the :class:`~como3r.frontend.agent.AgentFrontend` (the front-end's
    attributes it uses are declared below; it also counts in the front-end's ``stats`` and
    calls its helpers)."""

    config: Config
    agent: int
    keyframes: KeyframeStore
    timer: StageTimer
    prior: TimedPrior
    tracker: FrameTracker
    database: RetrievalDatabase | None
    records: list[FrameRecord]
    _lost: bool
    _T_kf_prev: Tensor | None
    _held: HeldRelocalization | None

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

        A candidate must also agree with the camera's motion (:meth:`_turn_allowed`): one
        that turned further from the last tracked frame than its motion allows is a look-alike
        place, or the camera was carried away; it is held back (the frame is lost), and the
        next lost frame confirms it by relocalizing where the held pose allows: the held
        frame is then placed as it relocalized and this one tracked from it. Every
        candidate is tried before a confirming one is taken, so that a frame which the
        motion allows on another keyframe refutes the held one.
        """
        identity = sim3_identity(
            dtype=self.keyframes.last.T_WC.dtype, device=self.keyframes.last.T_WC.device
        )
        recent = self._recent_keyframes()
        held, self._held = self._held, None
        confirmed: tuple[TrackResult, Keyframe] | None = None
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
            T_WC = sim3_compose(keyframe.T_WC, result.T_kf)
            if self._turn_allowed(T_WC, timestamp):
                self._resume(result, keyframe, index, timestamp, enc, colors)
                return "relocalized"
            if confirmed is None and held is not None and self._turn_allowed(T_WC, timestamp, held):
                confirmed = (result, keyframe)
            elif self._held is None:
                self._held = HeldRelocalization(T_WC, timestamp, index, kf_id, result, enc, colors)
        if confirmed is not None:
            assert held is not None
            return self._confirm(held, confirmed, enc, index, timestamp, colors)
        if self._held is not None:
            logger.info(
                "agent %d: frame %d's relocalization on keyframe %d held back: its pose turned "
                "further than the motion since the last tracked frame allows",
                self.agent,
                index,
                self._held.kf_id,
            )
        self.stats.lost += 1
        self.stats.lost_frames.append(index)
        return "lost"

    def _confirm(
        self,
        held: HeldRelocalization,
        confirmed: tuple[TrackResult, Keyframe],
        enc: Encoding,
        index: int,
        timestamp: float,
        colors: np.ndarray,
    ) -> str:
        """The held frame placed as it relocalized (no longer lost), then this frame tracked
        from it, or, where that fails, re-anchored where it relocalized (``confirmed``)."""
        logger.info(
            "agent %d: frame %d confirms frame %d's relocalization", self.agent, index, held.index
        )
        self.stats.lost -= 1
        self.stats.lost_frames.remove(held.index)
        self._resume(
            held.result,
            self.keyframes[held.kf_id],
            held.index,
            held.timestamp,
            held.encoding,
            held.colors,
        )
        result = self.tracker.track(enc, self.keyframes.last, self._T_kf_prev)
        if result.ok:
            return self._accept(result, index, timestamp, enc, colors)
        self._resume(*confirmed, index, timestamp, enc, colors)
        return "relocalized"

    def _resume(
        self,
        result: TrackResult,
        keyframe: Keyframe,
        index: int,
        timestamp: float,
        enc: Encoding,
        colors: np.ndarray,
    ) -> None:
        """Re-anchor the frame on the keyframe it relocalized on: on the current keyframe the
        sequence resumes (a keyframe when due), on an earlier one it becomes a keyframe
        joined to it by a loop edge."""
        self._lost = False
        self._held = None
        self.stats.relocalized += 1
        logger.info(
            "agent %d: frame %d relocalized on keyframe %d", self.agent, index, keyframe.kf_id
        )
        if keyframe is self.keyframes.last:
            self._accept(result, index, timestamp, enc, colors)
        else:
            self._promote_after_reloc(result, keyframe, index, timestamp, enc, colors)

    def _turn_allowed(
        self, T_WC: Tensor, timestamp: float, since: HeldRelocalization | None = None
    ) -> bool:
        """Whether a lost frame's relocalized pose ``T_WC`` ``(8,)`` turned from the last
        tracked frame's (or from a held relocalization's, ``since``) no further than the
        camera's motion allows (:data:`RELOC_TURN_RATE_FACTOR`).

        The turn rate is the fastest between consecutive frames of the latest
        :data:`RELOC_RATE_FRAMES` tracked ones; with fewer than two of them, or none apart
        in time, nothing bounds the motion and every pose is allowed. The allowance grows
        with the time lost, so an agent lost long enough takes any relocalization.
        """
        rate = self._turn_rate()
        if rate is None:
            return True
        if since is None:
            last = self.records[-1]
            origin, start = self._record_pose(last), last.timestamp
        else:
            origin, start = since.T_WC, since.timestamp
        allowed = LOOP_MAX_ROTATION_DEG + RELOC_TURN_RATE_FACTOR * rate * max(
            0.0, timestamp - start
        )
        turn = turn_deg(origin, T_WC)
        logger.debug(
            "agent %d: relocalization turned %.1f deg in %.2f s (allowed %.1f)",
            self.agent,
            turn,
            timestamp - start,
            allowed,
        )
        return turn <= allowed

    def _turn_rate(self) -> float | None:
        """The fastest turn [deg/s] between consecutive frames of the latest
        :data:`RELOC_RATE_FRAMES` tracked ones, or None where they do not tell."""
        latest = self.records[-RELOC_RATE_FRAMES:]
        rates = [
            turn_deg(self._record_pose(a), self._record_pose(b)) / (b.timestamp - a.timestamp)
            for a, b in zip(latest, latest[1:])
            if b.timestamp > a.timestamp
        ]
        return max(rates) if rates else None

    def _record_pose(self, record: FrameRecord) -> Tensor:
        """``(8,)`` world pose of a tracked frame."""
        anchor = self.keyframes[record.anchor].T_WC
        return sim3_compose(anchor, record.T_rel.to(anchor))

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
