"""What a keyframe message weighs on the wire, per part.

A keyframe message (:class:`~como3r.transport.messages.KeyframeMessage` around a
:class:`~como3r.frontend.packets.KeyframePacket`) is measured field by field with
:func:`como3r.transport.codec.part_sizes`; :func:`wire_parts` sums the fields into the parts
that :data:`PARTS` names, the ones a decision about what travels is made on (the prior's
encoding split into MASt3R's encoder tokens and the rest, the pointmap, its confidences,
the colours, the retrieval descriptors and words, the sequential edge's matches, the refresh
of the previous keyframe). What no part names (ids, pose, intrinsics) is ``"other"``.
:class:`PartCounter` adds them up over a run for ``metrics.json``: the agent, from the very
encoding it sends (:func:`~como3r.transport.codec.record_parts`), reports its sums in its
final message; the session store counts what it writes itself
(:meth:`~como3r.store.writer.SessionStore.written_metrics`).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping
from typing import Any

from como3r.transport import codec

#: part name -> the field paths (within the packet) it sums, matched by prefix
PARTS: dict[str, tuple[str, ...]] = {
    "tokens": ("encoding.tokens",),
    "encoding_rest": ("encoding.",),
    "pointmap": ("X_hat",),
    "confidences": ("C_hat",),
    "colours": ("colors",),
    # the descriptors, or what the coordinator's ASMK reads of them (prior.retrieval.Aggregated)
    "retrieval_descriptors": ("retrieval", "retrieval."),
    "retrieval_words": ("retrieval_words",),
    "sequential_matches": ("sequential_ij.", "sequential_ji.", "sequential_ij", "sequential_ji"),
    "previous_refresh": ("previous.", "previous"),
}

_PACKET = "packet."


def part_of(path: str) -> str:
    """The :data:`PARTS` name of a field path of a packet (``"other"`` if none)."""
    path = path[len(_PACKET) :] if path.startswith(_PACKET) else path
    for name, prefixes in PARTS.items():
        if any(path == p or (p.endswith(".") and path.startswith(p)) for p in prefixes):
            return name
    return "other"


def wire_parts(message: Any, *, lossy: bool = False) -> dict[str, int]:
    """Bytes of each part (:data:`PARTS`, then ``"other"``) of a keyframe message or packet
    as :func:`codec.encode` with this ``lossy`` writes it.

    The parts add up to the encoding's length less its framing (field names, tags: a few
    hundred bytes).
    """
    parts = dict.fromkeys([*PARTS, "other"], 0)
    for path, size in codec.part_sizes(message, lossy=lossy).items():
        parts[part_of(path)] += size
    return parts


class PartCounter:
    """Bytes per part summed over keyframes (``metrics.json``: per keyframe averages)."""

    def __init__(self) -> None:
        self.bytes: Counter[str] = Counter()
        self.keyframes = 0

    def add(self, parts: Mapping[str, int]) -> None:
        """Count one keyframe's parts (:func:`wire_parts`)."""
        self.bytes.update(parts)
        self.keyframes += 1

    def add_fields(self, sizes: Mapping[str, int]) -> None:
        """Count one keyframe message from its field sizes
        (:func:`~como3r.transport.codec.part_sizes`, as :func:`record_parts` hands them)."""
        parts = dict.fromkeys([*PARTS, "other"], 0)
        for path, size in sizes.items():
            parts[part_of(path)] += size
        self.add(parts)

    def add_totals(self, parts: Mapping[str, int], keyframes: int) -> None:
        """Count ``keyframes`` keyframes whose parts sum to ``parts`` (an agent's report)."""
        self.bytes.update(parts)
        self.keyframes += keyframes

    def per_keyframe(self) -> dict[str, float] | None:
        """Mean bytes per keyframe of each part (None before the first keyframe)."""
        if not self.keyframes:
            return None
        return {name: self.bytes[name] / self.keyframes for name in self.bytes}
