"""Agent messages over Zenoh decoded on threads of their own (issue 41, "Teams of sixteen").

The Zenoh hub (:class:`~como3r.transport.zenoh_hub.ZenohHub`) decided on every message and
decoded it on the coordinator's thread: 65-100 ms of CPU per keyframe at 160x120 in the
lossy wire coding, serial work that grows with the team. Now each agent id has a
:class:`Decoder` thread, as each agent pipe has its reader (:mod:`.pipe_readers`, whose
bound and decode it shares): Zenoh's callback hands a message's bytes to its agent's
decoder (a :class:`Decoding`, queued in the hub's inbox in the same step, under the hub's
condition, so each decoder decodes in the inbox's order), and the coordinator's thread
keeps every decision (who holds the id, the message's sequence, what is rejected), in
arrival order, taking each message's decode once it is done.

* The decode is what the coordinator's thread did (:func:`decode_from`): a message that
  does not decode, or comes under another agent's key, is rejected with the same error.
* Messages are decoded as they arrive, before the coordinator decides on them: one it
  then drops (a duplicate re-sent after a reconnect, a gap, an agent counted as failed) was
  decoded for nothing, where the coordinator's thread skipped it; one from a process that
  does not hold the id was decoded there too (its error, if any, is the one reported).
* ``Received.seconds`` is the decode's CPU time on its decoder's thread
  (``time.thread_time``), as on pipes: the runtime charges it to the coordinator's
  ``stage_seconds["ingest"]``.

Bounded memory: a decoder decodes the next message only while the decoded ones the
coordinator has not taken came in fewer than ``limit`` bytes
(:class:`~.pipe_readers.ReadAhead`); the bytes waiting to be decoded are held as the hub's
inbox held them before (Zenoh's callbacks never wait: a full queue there would stall the
session).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

from como3r.errors import MessageError
from como3r.transport import codec
from como3r.transport.links import Received, Rejected
from como3r.transport.messages import FROM_AGENT, KeyframeMessage
from como3r.transport.pipe_readers import ReadAhead, decoded


def decode_from(agent: int, max_bytes: int, data: bytes) -> tuple[Any, float]:
    """The message of ``data`` sent under agent ``agent``'s key and the CPU seconds its
    decode took on this thread.

    Raises:
        MessageError: not an agent's message, or another agent's.
    """
    start = time.thread_time()
    message = codec.decode(data, max_bytes=max_bytes, expected=FROM_AGENT)
    sender = message.packet.agent if isinstance(message, KeyframeMessage) else message.agent
    if sender != agent:
        raise MessageError(
            f"an {type(message).__name__} of agent {sender} under agent {agent}'s key"
        )
    return message, time.thread_time() - start


class Decoding:
    """One message's bytes (``nbytes`` of them) on their way through a :class:`Decoder`:
    ``item`` is None until decoded, then the :class:`~.links.Received` (its ``seq`` not
    set) or the :class:`~.links.Rejected`."""

    def __init__(self, data: bytes) -> None:
        self.data = data
        self.nbytes = len(data)
        self.item: Received | Rejected | None = None


class Decoder(ReadAhead):
    """Decodes the messages of one agent id, in the order they were fed, on a thread of
    its own.

    Args:
        agent: the agent id.
        max_bytes: size cap of one message.
        bell: the hub's condition, shared by its decoders (see
            :class:`~.pipe_readers.ReadAhead`).
        limit: bytes of decoded messages held before it waits for the hub.
    """

    def __init__(self, agent: int, max_bytes: int, bell: threading.Condition, limit: int) -> None:
        super().__init__(bell, limit)
        self.agent = agent
        self._decode: Callable[[bytes], tuple[Any, float]] = lambda data: decode_from(
            agent, max_bytes, data
        )
        self._fed: deque[Decoding] = deque()
        self.thread = threading.Thread(
            target=self._run, name=f"como3r-zenoh-decoder-{agent}", daemon=True
        )
        self.thread.start()

    def feed(self, data: bytes) -> Decoding:
        """(Under ``bell``) queue ``data`` to be decoded after what was fed before."""
        decoding = Decoding(data)
        self._fed.append(decoding)
        self._bell.notify_all()
        return decoding

    def take(self, decoding: Decoding) -> Received | Rejected:
        """(Under ``bell``) a decoded message's outcome, handed over: its decoder may
        decode on."""
        assert decoding.item is not None, "decoded first"
        self._held -= decoding.nbytes
        self._bell.notify_all()
        return decoding.item

    def _run(self) -> None:
        while self._room(lambda: bool(self._fed)):
            with self._bell:
                decoding = self._fed.popleft()
            item = decoded(self.agent, self._decode, decoding.data)
            with self._bell:
                decoding.item, decoding.data = item, b""
                self._held += decoding.nbytes
                self._bell.notify_all()
