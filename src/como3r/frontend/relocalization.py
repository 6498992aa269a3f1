"""Relocalization of a lost agent (step 5 of :mod:`como3r.frontend.agent`): the frame tracked
against the most recent keyframes and the agent's keyframes most like it, re-anchored on the
first that matches well enough, or counted as lost.

:class:`Relocalization` is one part of :class:`~como3r.frontend.agent.AgentFrontend` (its
base class): its methods read and change the front-end's state and counters.
"""

from __future__ import annotations

import logging

import numpy as np
from torch import Tensor

from como3r.config import Config
from como3r.frontend.keyframes import (
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
    _lost: bool
    _T_kf_prev: Tensor | None

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
