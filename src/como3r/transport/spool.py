"""An agent's outgoing messages, kept until the coordinator has stored them (issue 13).

:class:`Spool` holds every message an agent sent and the coordinator has not acknowledged,
in sequence order, with a cursor at the next one to put on the network. While the
coordinator is away (frozen, restarting, out of radio range) the agent keeps tracking and
its messages pile up here; when it is back, :meth:`Spool.rewind` puts everything not
acknowledged again, from the oldest (the coordinator drops the duplicates by sequence
number). Because nothing leaves the spool before it is acknowledged as stored, a coordinator
that lost messages (or a new one resuming a stored session) gets them again.

Payloads stay in memory up to ``memory_bytes``; past it, new payloads are written to files in
a spill folder (created on first use, removed by :meth:`Spool.close`) and read back when
their turn comes. Thread-safety is the caller's: the agent link guards every call with its
lock.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
from collections import deque
from dataclasses import dataclass
from pathlib import Path

logger = logging.getLogger(__name__)

#: payload bytes an agent keeps in memory before spilling to disk (``--queue-memory-mb``)
DEFAULT_MEMORY_BYTES = 256 * 2**20


@dataclass
class _Entry:
    """One unacknowledged message: in memory (``data``) or spilled (``data`` None)."""

    seq: int
    key: str
    size: int
    data: bytes | None


class Spool:
    """Sequenced messages from :meth:`append` to :meth:`acknowledge`.

    Args:
        memory_bytes: payload bytes kept in memory; later payloads go to disk.
        spill_dir: the folder the spill folder is created in (None: the system's temporary
            folder).
        label: names the spill folder (``como3r-<label>-*``).
    """

    def __init__(
        self,
        memory_bytes: int = DEFAULT_MEMORY_BYTES,
        spill_dir: Path | None = None,
        label: str = "spool",
    ) -> None:
        self.memory_bytes = memory_bytes
        self.spill_parent = spill_dir
        self.label = label
        self.next_seq = 0
        self.in_memory = 0  # payload bytes held in memory
        self.spilled = 0  # messages written to disk so far (metrics, tests)
        self._entries: deque[_Entry] = deque()  # unacknowledged, by sequence number
        self._cursor = 0  # position in _entries of the next message to put
        self._folder: Path | None = None

    def __len__(self) -> int:
        """Messages not acknowledged yet."""
        return len(self._entries)

    def append(self, key: str, data: bytes) -> int:
        """Keep ``data`` for ``key`` as the next message; returns its sequence number.

        Raises:
            OSError: the spill folder cannot be written (a full disk).
        """
        seq, self.next_seq = self.next_seq, self.next_seq + 1
        if self.in_memory + len(data) <= self.memory_bytes:
            self._entries.append(_Entry(seq, key, len(data), data))
            self.in_memory += len(data)
        else:
            self._path(seq).write_bytes(data)
            self._entries.append(_Entry(seq, key, len(data), None))
            self.spilled += 1
        return seq

    def has_next(self) -> bool:
        """Whether a message waits to be put."""
        return self._cursor < len(self._entries)

    def pending_bytes(self) -> int:
        """Payload bytes of the messages that wait to be put (from the cursor on)."""
        return sum(self._entries[i].size for i in range(self._cursor, len(self._entries)))

    def take(self) -> tuple[int, str, bytes]:
        """The next message to put, ``(seq, key, payload)``; the cursor moves past it (it
        stays kept until acknowledged).

        Raises:
            IndexError: nothing waits (:meth:`has_next` is False).
            OSError: a spilled payload cannot be read back.
        """
        entry = self._entries[self._cursor]
        self._cursor += 1
        data = entry.data if entry.data is not None else self._path(entry.seq).read_bytes()
        return entry.seq, entry.key, data

    def acknowledge(self, seq: int) -> None:
        """Every message up to ``seq`` is stored: forget them."""
        while self._entries and self._entries[0].seq <= seq:
            entry = self._entries.popleft()
            self._cursor = max(0, self._cursor - 1)
            if entry.data is not None:
                self.in_memory -= entry.size
            else:
                self._path(entry.seq).unlink(missing_ok=True)

    def rewind(self) -> int:
        """Put every unacknowledged message again, oldest first; returns how many."""
        self._cursor = 0
        return len(self._entries)

    def close(self) -> None:
        """Forget everything and remove the spill folder."""
        self._entries.clear()
        self._cursor, self.in_memory = 0, 0
        if self._folder is not None:
            shutil.rmtree(self._folder, ignore_errors=True)
            self._folder = None

    def _path(self, seq: int) -> Path:
        if self._folder is None:
            self._folder = Path(
                tempfile.mkdtemp(prefix=f"como3r-{self.label}-", dir=self.spill_parent)
            )
            logger.info(
                "%s: over %.0f MB of messages not yet stored by the coordinator; spilling to %s",
                self.label,
                self.memory_bytes / 2**20,
                self._folder,
            )
        return self._folder / f"{seq:012d}.msg"
