"""Verification on the agents' processes (``verification.on_agents``; issue 41): both sides
of :mod:`como3r.coordination.remote` over the runtime's transport.

Coordinator side, :class:`AgentVerifiers`: each job the coordinator makes goes to the
process of the agent that made the keyframe, or where that one no longer serves, to the
serving process with the fewest jobs out (a request carries every image its pairs need, so
any agent process can serve any job); the replies are handed to the coordinator together
once per turn of the runtime's loop (the global BA after them only when no batch of
keyframes follows, whose BA solves with their edges); the jobs of a process that left are
taken back (the coordinator verifies them itself). An agent process whose stream has ended
keeps serving until it is told that no more come (:meth:`AgentVerifiers.release`), which the
runtime does once no job is out, before its terminal cleanup.

The agent side, serving a request, is :mod:`.verification_service`.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Iterable

from como3r.coordination.association import Verification
from como3r.coordination.coordinator import Coordinator
from como3r.coordination.remote import RemoteJob, Verified
from como3r.frontend.packets import PoseUpdate
from como3r.frontend.pairs import PairLink
from como3r.transport.links import Hub
from como3r.transport.verification_messages import (
    KeyframeImage,
    VerificationDone,
    VerificationReply,
    VerificationRequest,
)

logger = logging.getLogger(__name__)


def request_message(coordinator: Coordinator, job: RemoteJob) -> VerificationRequest:
    """The request of one of the coordinator's jobs, with its keyframes' images."""
    return VerificationRequest(
        request=job.request,
        query=job.query,
        candidates=[(h.agent, h.keyframe) for h in job.hits],
        similarities=[h.similarity for h in job.hits],
        images=[
            KeyframeImage(agent, kf_id, frame, colors, encoding)
            for agent, kf_id, frame, colors, encoding in coordinator.job_images(job)
        ],
    )


def verified(job: RemoteJob, reply: VerificationReply) -> Verified | None:
    """The coordinator's record of an agent's reply to ``job``; None where the reply does
    not answer it (another number of candidates)."""
    if len(reply.pairs) != len(job.hits):
        return None
    verifications = [
        Verification(
            (hit.agent, hit.keyframe),
            job.query,
            hit.similarity,
            pair.ij,
            pair.covisible_ij,
            None
            if pair.ji is None
            else PairLink(pair.ij, pair.ji, pair.covisible_ij, pair.covisible_ji),
            None if pair.ji is None else pair.covisible_ji,
            pair.accepted,
        )
        for hit, pair in zip(job.hits, reply.pairs)
    ]
    return Verified(job.request, verifications, reply.decodes, dict(reply.seconds))


class AgentVerifiers:
    """The coordinator's jobs sent to agent processes and their replies (module docstring).

    Args:
        coordinator: the coordinator, whose jobs these are (its ``delegate`` is set here).
        hub: the transport to the agents.
    """

    def __init__(self, coordinator: Coordinator, hub: Hub) -> None:
        self.coordinator = coordinator
        self.hub = hub
        coordinator.delegate = True
        #: agent processes that serve requests (their task said so), until they leave
        self.serving: set[int] = set()
        self._sent: dict[int, tuple[int, RemoteJob]] = {}  # request -> (agent, job)
        #: per agent: when it last replied, or was sent a job while it had none out
        self._since: dict[int, float] = {}
        self._replies: list[Verified] = []
        #: per agent process: requests served, their CPU seconds, those after its stream
        self.served: Counter[int] = Counter()
        self.seconds: Counter[int] = Counter()
        self.seconds_after_stream: Counter[int] = Counter()
        #: jobs out when the agents' input ended (metrics.json)
        self.out_at_end = 0

    def join(self, agent: int) -> None:
        """Agent process ``agent`` serves requests from now on."""
        self.serving.add(agent)

    def dispatch(self, owner: dict[int, int]) -> None:
        """Send the coordinator's new jobs; ``owner`` maps a coordinator agent (a map
        segment) to the id of the agent process that runs it."""
        load = Counter(agent for agent, _ in self._sent.values())
        for job in self.coordinator.take_jobs():
            agent = owner.get(job.query[0], -1)
            if agent not in self.serving:
                agent = min(self.serving, key=lambda a: (load[a], a), default=-1)
            if agent < 0:
                self.coordinator.take_back(job.request)
                continue
            self.hub.send(agent, request_message(self.coordinator, job))
            if not load[agent]:
                self._since[agent] = time.monotonic()
            self._sent[job.request] = (agent, job)
            load[agent] += 1

    def received(self, agent: int, reply: VerificationReply) -> None:
        """An agent's reply, kept for :meth:`hand_over`."""
        sent = self._sent.get(reply.request)
        if sent is None or sent[1].query != tuple(reply.query):
            # a request this coordinator did not make (one before it resumed) or no longer
            # waits for (taken back)
            logger.info(
                "agent %d: a verification reply to a request not out (%d, keyframe %s); dropped",
                agent,
                reply.request,
                tuple(reply.query),
            )
            return
        if sent[0] != agent or reply.agent != agent:
            logger.warning(
                "agent %d: a verification reply to request %d it was not sent; dropped",
                agent,
                reply.request,
            )
            return
        del self._sent[reply.request]
        self._since[agent] = time.monotonic()
        seconds = sum(reply.seconds.values())
        self.served[agent] += 1
        self.seconds[agent] += seconds
        self.seconds_after_stream[agent] += seconds if reply.after_stream else 0.0
        made = verified(sent[1], reply)
        if made is None:
            logger.warning(
                "agent %d: its reply to request %d answers %d of %d pairs; verified here",
                agent,
                reply.request,
                len(reply.pairs),
                len(sent[1].hits),
            )
            self.coordinator.take_back(reply.request)
            return
        self._replies.append(made)

    def hand_over(self, solve: bool = True) -> list[PoseUpdate]:
        """The replies received since the last call to the coordinator, at once (its
        global BA on its trigger after them if ``solve``); returns the pose updates they
        made."""
        if not self._replies:
            return []
        replies, self._replies = self._replies, []
        return self.coordinator.add_verified(replies, solve)

    def left(self, agent: int) -> None:
        """Agent process ``agent`` serves no more: its jobs out are taken back."""
        self.serving.discard(agent)
        for request in [r for r, (a, _) in self._sent.items() if a == agent]:
            del self._sent[request]
            self.coordinator.take_back(request)

    def metrics(self, agent: int) -> dict[str, float]:
        """``metrics.json``'s ``runtime.agents[].verification`` of agent process
        ``agent``."""
        return {
            "requests": self.served[agent],
            "cpu_seconds": self.seconds[agent],
            "cpu_seconds_after_stream": self.seconds_after_stream[agent],
        }

    def overdue(self, timeout_s: float) -> list[int]:
        """The agent processes with jobs out that have not replied for ``timeout_s``
        seconds since they were sent one (or replied last)."""
        now, busy = time.monotonic(), {agent for agent, _ in self._sent.values()}
        return sorted(a for a in busy if now - self._since.get(a, now) > timeout_s)

    @property
    def out(self) -> int:
        """Jobs sent and not answered."""
        return len(self._sent)

    def release(self, agents: Iterable[int]) -> None:
        """Tell the serving processes among ``agents`` (their streams ended) that no more
        requests come: they leave as at the end of their stream."""
        for agent in sorted(set(agents) & self.serving):
            self.serving.discard(agent)
            self.hub.send(agent, VerificationDone())
