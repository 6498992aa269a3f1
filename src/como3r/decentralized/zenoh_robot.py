"""A robot's radio over Zenoh (``como3r robot``): peer to peer, the link filter at the
receiver (manual: docs/commands/robot.md).

Key expressions of a session ``S``::

    como3r/S/robot/<r>/alive                liveliness token of robot r's process
    como3r/S/robot/<r>/hello                queryable: robot r's RobotHello (start-up)
    como3r/S/robot/<r>/done                 liveliness token: robot r's mission is over
    como3r/S/robot/<to>/from/<from>         the mission messages of robot <from> to <to>;
                                            in a team run the key ends in
                                            /<sender's certificate name>

Start-up (:meth:`ZenohRobotLink.meet_team`): every robot answers hello queries and asks
for its peers' until the whole team has answered; robots whose plans differ (configuration,
rendezvous schedule, team size, prior) refuse each other. This is set-up, as a team is
briefed before it parts: not radio traffic, not filtered, not counted. A robot then waits
until each of its publishers (one per peer) matches the peer's subscriber: Zenoh delivers
a put only to subscribers the publisher already knows of, and a message lost at the start
would cost a round its timeout.

During the mission a robot puts each message under its recipient's key (reliable,
congestion control ``BLOCK``, from a background thread, so the robot never waits on the
network). The receiver decodes it (size-capped and validated by
:mod:`como3r.transport.codec`), checks that it names this robot as recipient and the sender
its key names (in a team run, also the certificate name the key ends in, which Zenoh's
access control makes the sender's: :mod:`como3r.transport.team_access`), and applies the
**link filter**: a message its sender sent at mission time ``t`` is dropped unless the
receiver hears the sender at ``t`` (:meth:`~como3r.decentralized.schedule.Schedule.hears`),
as radio range would drop it.
Drops and invalid messages are logged and counted, never fatal.

A peer whose liveliness token goes (its process ended, or its link was lost for longer than
the Zenoh lease) is reported to the robot as a
:class:`~como3r.decentralized.routing.PeerLeft`, so it stops waiting for it. At the end
(:meth:`ZenohRobotLink.finish`) a robot declares its ``done`` token and keeps
its session open until every peer it met is done or gone, so its last messages (the
elected robot's estimates) reach their recipients before it leaves.
"""

from __future__ import annotations

import logging
import queue
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

from como3r.decentralized.messages import DRIVER, ROBOT_MESSAGES, RobotHello
from como3r.decentralized.routing import PeerLeft
from como3r.errors import InputError, MessageError
from como3r.transport import codec
from como3r.transport.pacing import CONTROL_BYTES
from como3r.transport.zenoh_protocol import Sender

logger = logging.getLogger(__name__)

#: how often the handshake and the end-of-mission wait ask again [s]
POLL_S = 0.2

Hears = Callable[[int, int, float], bool]
"""The link filter: ``hears(receiver, sender, time_s)``."""


class RobotKeys:
    """The robot key expressions of one session (module docstring); ``member``: this
    process's certificate name in a team run (the keys of its messages end in it)."""

    def __init__(self, session: str, member: str | None = None) -> None:
        if not session or any(c in session for c in "/*$?#"):
            raise InputError(f"session name {session!r}: use letters, digits, - and _")
        self.root = f"como3r/{session}/robot"
        self.member = member

    def robot(self, robot: int | str) -> str:
        return f"{self.root}/{robot}"

    def alive(self, robot: int | str) -> str:
        return f"{self.robot(robot)}/alive"

    def hello(self, robot: int | str) -> str:
        return f"{self.robot(robot)}/hello"

    def done(self, robot: int | str) -> str:
        return f"{self.robot(robot)}/done"

    def messages(self, recipient: int | str, sender: int | str) -> str:
        key = f"{self.robot(recipient)}/from/{sender}"
        return key if self.member is None else f"{key}/{self.member}"

    def inbox(self, recipient: int | str) -> str:
        """Every message to ``recipient``, team run or not."""
        return f"{self.robot(recipient)}/from/**"

    def robot_of(self, key: str, field_index: int = 0) -> str:
        """Field ``field_index`` after the root (0: the robot; 2: a message's sender; 3: its
        certificate name in a team run)."""
        parts = key[len(self.root) + 1 :].split("/")
        return parts[field_index] if len(parts) > field_index else ""


@dataclass
class RobotTraffic:
    """What one robot sent and received, per peer and message type (bytes and messages),
    and what it dropped: by the link filter (per type) or as invalid."""

    sent: dict[int, Counter] = field(default_factory=lambda: defaultdict(Counter))
    received: dict[int, Counter] = field(default_factory=lambda: defaultdict(Counter))
    messages_sent: Counter = field(default_factory=Counter)
    messages_received: Counter = field(default_factory=Counter)
    filtered: Counter = field(default_factory=Counter)
    invalid: int = 0

    def to_json(self) -> dict[str, Any]:
        """``metrics.json``'s ``bytes`` of a robot."""
        sent, received = by_type(self.sent), by_type(self.received)
        return {
            "sent": dict(sent),
            "received": dict(received),
            "sent_total": sum(sent.values()),
            "received_total": sum(received.values()),
            "messages_sent": dict(self.messages_sent),
            "bytes_per_message_sent": {k: v / self.messages_sent[k] for k, v in sent.items()},
            "messages_received": dict(self.messages_received),
            "by_peer": {
                str(p): {
                    "sent": dict(self.sent.get(p, {})),
                    "received": dict(self.received.get(p, {})),
                }
                for p in sorted({*self.sent, *self.received})
            },
            "dropped_by_link_filter": dict(self.filtered),
            "invalid": self.invalid,
        }


def by_type(per_peer: dict[int, Counter]) -> Counter:
    """Bytes (or messages) per message type, over all peers."""
    total: Counter = Counter()
    for counts in per_peer.values():
        total.update(counts)
    return total


class ZenohRobotLink:
    """One robot's :class:`~como3r.decentralized.robot.Link` over Zenoh.

    Args:
        session: an open Zenoh session (the caller closes it, after :meth:`finish`).
        keys: the session's robot key expressions.
        robot: this robot's id.
        team: robots ``0 .. team-1`` take part.
        hello: what this robot answers its peers' start-up queries with.
        hears: the link filter.
        max_bytes: size cap of one message.
        progress: called with the robot's messages to the driver (progress, report).
        certified: a team run: a message counts only if its key ends in the certificate
            name of the robot it claims to come from.
        max_mbps: the rate limit of what it sends (0: none); messages up to
            :data:`~como3r.transport.pacing.CONTROL_BYTES` go before larger ones.
    """

    def __init__(
        self,
        session: Any,
        keys: RobotKeys,
        robot: int,
        team: int,
        hello: RobotHello,
        hears: Hears,
        max_bytes: int,
        progress: Callable[[Any], None] | None = None,
        certified: bool = False,
        max_mbps: float = 0.0,
    ) -> None:
        self.session, self.keys, self.robot, self.team = session, keys, robot, team
        self.certified = certified
        self.hears, self.max_bytes, self.progress = hears, max_bytes, progress
        self.traffic = RobotTraffic()
        self._hello = codec.encode(hello, max_bytes=max_bytes)
        self._plan = hello.plan
        self._inbox: queue.Queue[tuple[str, bytes | int | None]] = queue.Queue()
        self._publishers = {
            keys.messages(peer, robot): _publisher(session, keys.messages(peer, robot))
            for peer in range(team)
            if peer != robot
        }
        self._sender = Sender(
            session,
            self._publishers,
            max_mbps=max_mbps,
            control=lambda nbytes: nbytes <= CONTROL_BYTES,
        )
        self._declared = [
            session.declare_subscriber(keys.inbox(robot), self._on_message),
            session.declare_queryable(keys.hello(robot), self._on_hello),
            session.liveliness().declare_subscriber(keys.alive("*"), self._on_alive),
            *self._publishers.values(),
        ]
        self._declared.append(session.liveliness().declare_token(keys.alive(robot)))

    # ------------------------------------------------------------ Zenoh's threads

    def _on_message(self, sample: Any) -> None:
        size = len(sample.payload)
        key = str(sample.key_expr)
        # an oversized payload is not even copied
        self._inbox.put((key, size if size > self.max_bytes else sample.payload.to_bytes()))

    def _on_alive(self, sample: Any) -> None:
        import zenoh

        if sample.kind == zenoh.SampleKind.DELETE:  # a peer's process is gone
            self._inbox.put((str(sample.key_expr), None))

    def _on_hello(self, query: Any) -> None:
        try:
            query.reply(query.key_expr, self._hello)
        except Exception as exc:  # the asker gave up, or the session is closing
            logger.debug("hello reply failed: %s", exc)
        finally:
            query.drop()

    # ------------------------------------------------------------ Link

    def send(self, message: Any) -> None:
        """Put ``message`` on the network (messages to the driver go to ``progress``)."""
        if message.recipient == DRIVER:
            if self.progress is not None:
                self.progress(message)
            return
        kind = type(message).__name__
        data = codec.encode(message, max_bytes=self.max_bytes, lossy=True)
        self.traffic.sent[message.recipient][kind] += len(data)
        self.traffic.messages_sent[kind] += 1
        self._sender.put(self.keys.messages(message.recipient, self.robot), data)

    def receive(self, timeout: float) -> Any | None:
        """The next message that passes validation and the link filter (or a
        :class:`~como3r.decentralized.routing.PeerLeft` when a peer's process is gone), or
        None after ``timeout`` seconds without one."""
        deadline = time.monotonic() + max(timeout, 0.0)
        while True:
            try:
                key, data = self._inbox.get(timeout=max(deadline - time.monotonic(), 0.0))
            except queue.Empty:
                return None
            message = self._accept(key, data)
            if message is not None:
                return message

    def _accept(self, key: str, data: bytes | int | None) -> Any | None:
        if data is None:
            gone = self.keys.robot_of(key)
            return PeerLeft(int(gone)) if gone.isdigit() and int(gone) != self.robot else None
        claimed, certificate = self.keys.robot_of(key, 2), self.keys.robot_of(key, 3)
        if self.certified and certificate != f"robot-{claimed}":
            self._invalid(claimed, f"sent by the holder of certificate {certificate or '(none)'}")
            return None
        if isinstance(data, int):
            self._invalid(
                claimed, f"message of {data} bytes exceeds the cap of {self.max_bytes} bytes"
            )
            return None
        try:
            message = codec.decode(data, max_bytes=self.max_bytes, expected=ROBOT_MESSAGES)
        except MessageError as exc:
            self._invalid(claimed, str(exc))
            return None
        sender, kind = message.sender, type(message).__name__
        if (
            message.recipient != self.robot
            or str(sender) != claimed
            or not 0 <= sender < self.team
            or sender == self.robot
        ):
            self._invalid(
                claimed,
                f"a {kind} from robot {sender} to robot "
                f"{message.recipient} under robot {claimed}'s key",
            )
            return None
        if not self.hears(self.robot, sender, message.time_s):
            logger.debug(
                "robot %d: out of range of robot %d at %.3f s: %s dropped",
                self.robot,
                sender,
                message.time_s,
                kind,
            )
            self.traffic.filtered[kind] += 1
            return None
        self.traffic.received[sender][kind] += len(data)
        self.traffic.messages_received[kind] += 1
        return message

    def _invalid(self, claimed: str, error: str) -> None:
        logger.warning(
            "robot %d: dropped a message under robot %r's key: %s", self.robot, claimed, error
        )
        self.traffic.invalid += 1

    # ------------------------------------------------------------ start and end

    def meet_team(self, wait_log_s: float = 30.0) -> dict[int, RobotHello]:
        """Every robot's hello, asked until the whole team has answered.

        Raises:
            InputError: a peer runs another mission plan.
        """
        known = {self.robot: codec.decode(self._hello, expected=RobotHello)}  # its own
        said = time.monotonic()
        while len(known) < self.team:
            for reply in self.session.get(self.keys.hello("*"), timeout=2.0):
                if reply.ok is not None:
                    hello = self._peer_hello(reply.ok.payload.to_bytes())
                    if hello is not None:
                        known[hello.robot] = hello
            if len(known) < self.team:
                if time.monotonic() - said > wait_log_s:
                    missing = sorted(set(range(self.team)) - set(known))
                    logger.warning(
                        "robot %d: waiting for robot(s) %s to start",
                        self.robot,
                        ", ".join(map(str, missing)),
                    )
                    said = time.monotonic()
                time.sleep(POLL_S)
        self._wait_for_subscribers(wait_log_s)
        return known

    def _wait_for_subscribers(self, wait_log_s: float) -> None:
        """Until every peer's subscriber is known to this robot's publisher to it."""
        said = time.monotonic()
        while unmatched := [
            key
            for key, publisher in self._publishers.items()
            if not publisher.matching_status.matching
        ]:
            if time.monotonic() - said > wait_log_s:
                logger.warning("robot %d: waiting to reach %s", self.robot, ", ".join(unmatched))
                said = time.monotonic()
            time.sleep(POLL_S)

    def _peer_hello(self, data: bytes) -> RobotHello | None:
        try:
            hello = codec.decode(data, max_bytes=self.max_bytes, expected=RobotHello)
        except MessageError as exc:
            logger.warning("robot %d: dropped an unreadable hello: %s", self.robot, exc)
            return None
        if not 0 <= hello.robot < self.team:
            logger.warning(
                "robot %d: robot %d is not in this team of %d", self.robot, hello.robot, self.team
            )
            return None
        if hello.plan != self._plan:
            raise InputError(
                f"robot {hello.robot} runs another mission plan (configuration, "
                f"rendezvous schedule, --robots or --prior differ from robot "
                f"{self.robot}'s)"
            )
        return hello

    def finish(self, peers: Iterable[int], timeout: float) -> None:
        """Say this robot is done, then wait (at most ``timeout`` seconds) until each of
        ``peers`` is done or gone, and undeclare everything."""
        self._sender.close(timeout)
        self._declared.append(self.session.liveliness().declare_token(self.keys.done(self.robot)))
        waiting = set(peers) - {self.robot}
        deadline = time.monotonic() + timeout
        while waiting and time.monotonic() < deadline:
            waiting &= self._tokens(self.keys.alive("*"))
            waiting -= self._tokens(self.keys.done("*"))
            if waiting:
                time.sleep(POLL_S)
        if waiting:
            logger.warning(
                "robot %d: leaving before robot(s) %s finished",
                self.robot,
                ", ".join(map(str, sorted(waiting))),
            )
        for entity in reversed(self._declared):
            entity.undeclare()

    def _tokens(self, key: str) -> set[int]:
        """Robots with a liveliness token matching ``key``."""
        robots = set()
        for reply in self.session.liveliness().get(key, timeout=max(POLL_S, 1.0)):
            if reply.ok is not None:
                text = self.keys.robot_of(str(reply.ok.key_expr))
                if text.isdigit():
                    robots.add(int(text))
        return robots


def _publisher(session: Any, key: str) -> Any:
    import zenoh

    return session.declare_publisher(
        key,
        congestion_control=zenoh.CongestionControl.BLOCK,
        reliability=zenoh.Reliability.RELIABLE,
    )


def finish_timeout(message_timeout_s: float) -> float:
    """How long a robot waits for its peers at the end [s]: the elected robot's answer can
    take two message timeouts (:mod:`como3r.decentralized.robot`), plus a margin; at most
    a day."""
    return min(2 * message_timeout_s + 5.0, 86400.0)
