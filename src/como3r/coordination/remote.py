"""Verification on the agents (``verification.on_agents``; issue 41, "Teams of sixteen").

A coordinator that verifies every keyframe's candidates itself does work per second of
input that grows with the team: each keyframe's verification is bounded (its decode
budget), but 16 agents bring 16 times the keyframes of one. Of that work the dense
verification is most (at 16 agents of ``benchmarks/team_scale.py``: 1.6 s of 1.9 s of CPU
per keyframe), and it is the same kind of work the agents do for their own edges. Here it
moves to them:

1. The coordinator retrieves and selects a keyframe's candidates as it would verify them
   (:meth:`~.linking.InterAgentLinking._selection`: its budget, by the gauge components as
   they are then) and, instead of verifying them, makes a :class:`RemoteJob` of them
   (:meth:`RemoteVerification._request`); the runtime takes the jobs
   (:meth:`RemoteVerification.take_jobs`) and sends each, with the images every pair needs
   (:meth:`RemoteVerification.job_images`), to an agent process.
2. The agent verifies the pairs between its frames (the same
   :func:`~.association.verify_candidates`) and returns the matches; the runtime hands them
   back (:meth:`RemoteVerification.add_verified`), several at a time, and the coordinator
   admits the edges as it does its own (:meth:`~.linking.InterAgentLinking._admit`), then
   runs the in-stream global BA on its trigger, once for all of them.
3. A job no agent can serve (its agent is gone, or every agent process has ended) is taken
   back (:meth:`RemoteVerification.take_back`) and waits with the deferred keyframes
   (:mod:`.deferral`): the coordinator verifies it itself when idle or before the terminal
   cleanup. The session store keeps the jobs still out as deferred keyframes, so a resumed
   run verifies them.

What differs from verifying in line: an edge enters the graph when its reply comes (the
agent's next frame, or later), so a keyframe verified before a merge's edges came back
chose its candidates without that merge, and the results depend on timing (as the
batches do). The matches travel in the session store's coding of inter-agent edges.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from como3r.coordination.association import Candidate, Verification
from como3r.coordination.deferral import DeferredKeyframe, DeferredVerification, StoredDeferred
from como3r.coordination.linking import KeyframeKey
from como3r.frontend.packets import PoseUpdate
from como3r.prior.base import Encoding
from como3r.prior.retrieval import Hit

logger = logging.getLogger("como3r.coordination.coordinator")


@dataclass(frozen=True)
class RemoteJob:
    """A keyframe's selected candidates, to be verified by an agent.

    Attributes:
        request: the job's number in this coordinator.
        query: ``(agent, kf_id)`` of the keyframe.
        hits: its cross-agent candidates, then its loop candidates (its own agent's).
        cross: how many of ``hits`` are cross-agent.
    """

    request: int
    query: tuple[int, int]
    hits: tuple[Hit, ...]
    cross: int


@dataclass(frozen=True)
class Verified:
    """An agent's verification of a job: one :class:`~.association.Verification` per hit
    in the job's order, the decodes it took and its CPU seconds by stage."""

    request: int
    verifications: list[Verification]
    decodes: int
    seconds: dict[str, float] = field(default_factory=dict)


#: one keyframe's image for a job: ``(agent, kf_id, frame_index, colors (H, W, 3) uint8,
#: the encoding or the record it is made from with the colours, or None)``
JobImage = tuple[int, int, int, np.ndarray, Encoding | None]


class RemoteVerification(DeferredVerification):
    """The coordinator's side of verification on the agents (module docstring); off until a
    runtime that can serve it says so (:attr:`delegate`)."""

    #: jobs made and not yet taken by the runtime, oldest first
    _jobs_out: list[RemoteJob]
    #: every job out (taken or not) by its number
    _outstanding: dict[int, RemoteJob]
    _requests: int
    #: whether keyframes' verifications go to the agents (set by the runtime)
    delegate: bool

    def _verify_or_request(self, packet: KeyframeKey, hits: list[Hit]) -> list[Candidate]:
        """A new keyframe's accepted cross-agent candidates verified here
        (:meth:`~.linking.InterAgentLinking._verify`), or none yet: its job made for an
        agent (:attr:`delegate`)."""
        if not self.delegate:
            return self._verify(packet, hits)
        self._request(packet, hits)
        return []

    def _request(self, packet: KeyframeKey, hits: list[Hit]) -> None:
        if not hits:
            return
        cross, loops = self._selection(packet, hits)
        if not cross and not loops:
            return
        job = RemoteJob(self._requests, (packet.agent, packet.kf_id), (*cross, *loops), len(cross))
        self._requests += 1
        self._jobs_out.append(job)
        self._outstanding[job.request] = job

    def take_jobs(self) -> list[RemoteJob]:
        """The jobs made since the last call, oldest first (the runtime sends them)."""
        jobs, self._jobs_out = self._jobs_out, []
        return jobs

    @property
    def jobs_out(self) -> int:
        """Jobs made and not yet answered or taken back."""
        return len(self._outstanding)

    def job_images(self, job: RemoteJob) -> list[JobImage]:
        """The image of every keyframe ``job`` decodes (its query first, each once), with
        what encoding it again takes besides (:meth:`~como3r.prior.base.Prior.
        encode_again`): the record, or the encoding where the coordinator holds nothing
        smaller, or None where the prior needs the colours alone."""
        keys = dict.fromkeys([job.query, *((h.agent, h.keyframe) for h in job.hits)])
        images = []
        for agent, kf_id in keys:
            kf = self.graph.keyframes[self.graph.global_index(agent, kf_id)]
            held = kf.encoding
            images.append(
                (agent, kf_id, kf.frame_index, kf.colors, None if held is None else held.portable())
            )
        return images

    def add_verified(self, replies: Sequence[Verified], solve: bool = True) -> list[PoseUpdate]:
        """Admit the edges of the agents' verifications (jobs no longer out are ignored),
        then, if ``solve``, the in-stream global BA on its trigger, once; returns the pose
        updates. False: the edges wait for the next batch's BA (a runtime about to hand
        over a batch: one BA per batch, as when the coordinator verifies)."""
        updates: list[PoseUpdate] = []
        for reply in replies:
            job = self._outstanding.pop(reply.request, None)
            if job is None or len(reply.verifications) != len(job.hits):
                logger.warning(
                    "coordinator: a verification reply for request %d that is not out or "
                    "does not verify each of its candidates; ignored",
                    reply.request,
                )
                continue
            self.stats.prior_decodes += reply.decodes
            self.stats.remote_verifications += 1
            self.stats.remote_decodes += reply.decodes
            for stage, value in reply.seconds.items():
                self.stats.remote_seconds[stage] = self.stats.remote_seconds.get(stage, 0.0) + value
            key = DeferredKeyframe(*job.query, job.hits)
            for candidate in self._take(key, job.cross, reply.verifications):
                updates.extend(self._admit(candidate))
        if solve:
            self._solve_on_trigger(updates)
        return self._record(self._count(updates))

    def take_back(self, request: int) -> None:
        """A job no agent will answer: its keyframe waits with the deferred ones, which
        this coordinator verifies itself (:mod:`.deferral`)."""
        job = self._outstanding.pop(request, None)
        if job is None:
            return
        self._jobs_out = [j for j in self._jobs_out if j.request != request]
        self.stats.remote_taken_back += 1
        self._deferred.append(DeferredKeyframe(*job.query, job.hits))

    def take_back_all(self) -> None:
        """Every job still out taken back (:meth:`take_back`), oldest first."""
        for request in sorted(self._outstanding):
            self.take_back(request)

    def deferred_keyframes(self) -> list[StoredDeferred]:
        """The deferred keyframes, then the jobs still out, oldest first: a resumed
        coordinator verifies them all itself."""
        out: list[StoredDeferred] = [
            (job.query[0], job.query[1], [(h.agent, h.keyframe, h.similarity) for h in job.hits])
            for _, job in sorted(self._outstanding.items())
        ]
        return super().deferred_keyframes() + out
