"""Deferred verification (issue 41, "Teams of sixteen"): under a batch budget
(``verification.max_decodes_per_batch``) a coordinator that fell behind verifies a batch's
keyframes newest first and skips those whose worst case no longer fits; they wait here
and are verified later, newest first:

* with what a later batch leaves of its budget after its own keyframes
  (:meth:`DeferredVerification._defer`);
* one at a time while no keyframe waits (:meth:`DeferredVerification.verify_deferred_one`,
  called by the multi-process runtime when it is idle);
* all that remain when the input ends, before the terminal cleanup
  (:meth:`DeferredVerification._verify_all_deferred`, from
  :meth:`~como3r.coordination.coordinator.Coordinator.finish`): the final map has every
  verification a run without the budget attempts, each keyframe verified once.

A deferred keyframe keeps its retrieval hits (found when it came: the database it was
queried in), not its packet: verification needs only its ``(agent, kf_id)``, the graph holds
its encoding. Which of its hits it verifies is chosen when it is verified, by the gauge
components as they are then (:meth:`~.linking.InterAgentLinking._selection`): a hit whose
agent has merged with it since is verified only if the budget leaves room for hits within
one component. The session store keeps the list (:meth:`DeferredVerification.
deferred_keyframes`): the hits depend on the database at the time of the query, which a
resumed run cannot query again.

:class:`DeferredVerification` is a base of
:class:`~como3r.coordination.coordinator.Coordinator`; its own base is the linking.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

from como3r.coordination.linking import InterAgentLinking
from como3r.frontend.packets import KeyframePacket, PoseUpdate
from como3r.heap import give_back_freed_memory
from como3r.prior.retrieval import Hit

# the coordinator's logger: its messages read as they did before this part had a module
logger = logging.getLogger("como3r.coordination.coordinator")

#: a deferred keyframe as the session store keeps it: agent, keyframe index and its hits'
#: ``[agent, keyframe, similarity]``
StoredDeferred = tuple[int, int, list[tuple[int, int, float]]]

#: deferred keyframes the end of the input verifies per opening of the pool (their worst
#: case in decodes each; :meth:`DeferredVerification._verify_all_deferred`)
FINISH_CHUNK_KEYFRAMES = 4


@dataclass(frozen=True)
class DeferredKeyframe:
    """A keyframe skipped under the batch budget: what its verification needs."""

    agent: int
    kf_id: int
    hits: tuple[Hit, ...]


class DeferredVerification(InterAgentLinking):
    """The deferred verification of the :class:`~como3r.coordination.coordinator.
    Coordinator` (it uses the coordinator's ``_global_ba``, ``_record`` and ``_count``)."""

    #: keyframes skipped under the batch budget and not verified yet, oldest first
    _deferred: list[DeferredKeyframe]

    def _keyframe_budget(self) -> int:
        return self.config.verification.max_decodes_per_keyframe

    def _batch_budget(self, keyframes: int) -> float:
        """The decodes a batch of ``keyframes`` new keyframes may spend on verification
        (``verification.max_decodes_per_batch``; a batch of one always has its keyframe's)."""
        if keyframes <= 1 or self.config.verification.max_decodes_per_batch == 0:
            return math.inf
        return self._deferred_budget()

    def _deferred_budget(self) -> int:
        """The batch budget the deferred keyframes may use what is left of (a batch of one
        too: its own keyframe is always verified, the deferred ones within this)."""
        return max(self.config.verification.max_decodes_per_batch, self._keyframe_budget())

    def _defer(
        self, skipped: Sequence[tuple[KeyframePacket, list[Hit]]], spent: int
    ) -> list[PoseUpdate]:
        """After a batch's own verification: keep its ``skipped`` keyframes (newest first,
        as they were skipped) and verify deferred ones, newest first, with what the batch
        left of its budget after its ``spent`` decodes; returns the updates they made."""
        self.stats.verification_skipped += len(skipped)
        self._deferred.extend(
            DeferredKeyframe(p.agent, p.kf_id, tuple(hits)) for p, hits in reversed(skipped)
        )
        if not self._deferred or self.config.verification.max_decodes_per_batch == 0:
            return []
        return self._verify_deferred(self._deferred_budget() - spent)

    def _verify_deferred(self, budget: int) -> list[PoseUpdate]:
        """Verify deferred keyframes newest first while the decodes so far plus one
        keyframe's worst case fit ``budget``; their edges are admitted as a batch's. The
        keyframes certain to fit run ahead on the pool (:mod:`.decode_pool`)."""
        worst = self._keyframe_budget()
        certain = max(0, budget // worst)
        self._speculate([(d, list(d.hits)) for d in self._deferred[::-1][:certain]])
        start, updates = self.stats.prior_decodes, []
        try:
            while self._deferred and self.stats.prior_decodes - start + worst <= budget:
                deferred = self._deferred.pop()
                self.stats.verification_deferred += 1
                for candidate in self._verify(deferred, list(deferred.hits)):
                    updates.extend(self._admit(candidate))
        finally:
            self._settle()
        return updates

    def _solve_on_trigger(self, updates: list[PoseUpdate]) -> list[PoseUpdate]:
        """The in-stream global BA after a batch's or deferred verifications, on its trigger
        (``global_ba.trigger_interval_edges``), and the recheck of refused edges after it;
        its updates are added to ``updates``, which is returned."""
        if self._new_edges >= self.config.global_ba.trigger_interval_edges:
            updates.extend(self._global_ba())
            self._recheck_refused()
        return updates

    def verify_deferred_one(self) -> list[PoseUpdate]:
        """Verify the newest deferred keyframe (none: nothing happens), as a batch of its
        own would: its edges admitted, the global BA on its trigger, the journal told.
        For a runtime whose coordinator has no keyframe waiting; returns the updates."""
        if not self._deferred:
            return []
        updates = self._solve_on_trigger(self._verify_deferred(self._keyframe_budget()))
        return self._record(self._count(updates))

    def _verify_all_deferred(self) -> list[PoseUpdate]:
        """At the end of the input: verify every deferred keyframe (newest first), then
        solve as after a batch; returns the updates.

        The pool is opened on :data:`FINISH_CHUNK_KEYFRAMES` keyframes' worst case at a time,
        not on all of them: a batch keeps the encodings its planned keyframes need until they
        are verified. The same verifications in the same order (the pool only runs ahead),
        one solve after all of them. Measured on the 16-agent scene of
        benchmarks/team_scale.py (its calls replayed at ``max_decodes_per_batch=12``, 32
        keyframes deferred, RSS 2.0 GB before): peak RSS 3.72 -> 3.35 GB, the same 203
        decodes, thread CPU 10.2 -> 9.9 s.

        The encoding cache (:mod:`.encodings`) keeps, chunk by chunk, only the keyframes
        still deferred and their hits (:meth:`~.coordinator.Coordinator.finish` then lets go
        of the rest: nothing decodes after them, the terminal cleanup works on pointmaps).
        On the same replay it had grown from 20 to 40 encodings (23 MB each, the simulated
        prior's at that size): peak RSS 3.63 / 3.57 -> 2.77 / 2.91 GB (two runs), 2.24-2.32
        -> 1.42-1.43 GB held after (heap trimmed); the same decodes, re-encodes (40), edges
        and poses. The heap's freed pages go back to the system after each chunk
        (:mod:`como3r.heap`): peak RSS 2.77 / 2.91 -> 2.44 / 2.52 GB (defer41b's script, load
        10-13).
        """
        if not self._deferred:
            return []
        logger.info(
            "coordinator: verifying %d deferred keyframe(s) before the terminal cleanup",
            len(self._deferred),
        )
        self.stats.verification_deferred_at_finish += len(self._deferred)
        chunk = self._keyframe_budget() * FINISH_CHUNK_KEYFRAMES
        updates: list[PoseUpdate] = []
        while self._deferred:
            # nothing decodes after these verifications: an encoding that no keyframe still
            # deferred nor any of its hits is would only be held
            self.encodings.retain(self._deferred_keyframes_and_hits())
            updates.extend(self._verify_deferred(chunk))
            give_back_freed_memory()  # the chunk's decodes and released encodings
        return self._solve_on_trigger(updates)

    def _deferred_keyframes_and_hits(self) -> set[int]:
        """Global indices of the deferred keyframes and of their hits: the keyframes whose
        encodings their verifications may decode."""
        index = self.graph.global_index
        return {index(d.agent, d.kf_id) for d in self._deferred} | {
            index(h.agent, h.keyframe) for d in self._deferred for h in d.hits
        }

    def deferred_keyframes(self) -> list[StoredDeferred]:
        """The deferred keyframes, oldest first, as the session store keeps them."""
        return [
            (d.agent, d.kf_id, [(h.agent, h.keyframe, h.similarity) for h in d.hits])
            for d in self._deferred
        ]

    def restore_deferred(self, stored: Sequence[StoredDeferred]) -> None:
        """Wait again to verify the stored :meth:`deferred_keyframes`."""
        self._deferred = [
            DeferredKeyframe(
                int(agent), int(kf_id), tuple(Hit(int(a), int(k), float(s)) for a, k, s in hits)
            )
            for agent, kf_id, hits in stored
        ]
