"""The coordinator's keyframe encodings, remade from the keyframes' colours when needed.

A keyframe's encoding is what the prior decodes pairs from (MASt3R's encoder tokens at
512x384: 1.25 MB of a 5 MB keyframe message across machines, 2.5 MB of the 7.8 MB a keyframe
writes to the session store; ``benchmarks/message_sizes.py``). When the
coordinator's prior can remake an agent's encodings from its keyframes' uint8 colours
(:meth:`~como3r.prior.base.Prior.can_reencode`: MASt3R, whose tokens are a function of the
image alone), the agent is told at the session start not to send them
(:attr:`~como3r.transport.messages.AgentTask.send_encoding`) and the session store does not
keep them: such a keyframe's ``encoding`` is None, and :class:`KeyframeEncodings` encodes
its colours again the first time a verification decodes a pair with it
(:mod:`.linking`), keeping the newest ``session.encoding_cache`` of them (and where set
within ``session.encoding_cache_mb``; least recently used first out; the end's deferred
verification lets go of those it can no longer use: :mod:`.deferral`). Encoding work is
counted (``reencodes`` and ``stage_seconds["reencode"]`` of the coordinator's statistics).

The simulated prior's encoding is made from the frame's ground truth as well as its image,
which a coordinator does not have (a networked run's agents read their own inputs; a resume,
a saved map and a merge read a store). What travels and is stored in its place is the
smaller :class:`~como3r.prior.base.EncodingRecord` the encoding names
(:meth:`~como3r.prior.base.Encoding.portable`: the simulated prior's ground truth, losslessly packed,
:mod:`como3r.prior.simulated_record`; 0.7-0.9 MB at 512x384 where the encoding is 13.4 MB),
and :class:`KeyframeEncodings` makes the encoding from the colours and the record
(:meth:`~como3r.prior.base.Prior.encode_from_record`) as it does MASt3R's from the colours
alone, with the same cache and counts. A coordinator in the agents' process (``--single-process``)
holds the agents' encodings themselves and encodes nothing.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Callable, Collection

from como3r.coordination.census import census
from como3r.errors import InputError, PriorError
from como3r.frontend.keyframes import Keyframe
from como3r.prior.base import Encoding, EncodingRecord, Prior


class KeyframeEncodings:
    """Encodings of the coordinator's keyframes: the one a keyframe holds, else its colours
    encoded again (with the record it holds in the encoding's place, if any), in a bounded
    least-recently-used cache by global keyframe index.

    Args:
        prior: the coordinator's prior (the one the agents' encodings came from); None for
            a coordinator that decodes nothing (it can remake no encoding).
        capacity: how many re-encoded keyframes are kept (0: none; every use re-encodes).
        max_bytes: the most bytes they take together (their tensors and arrays); 0: no
            bound but ``capacity``.

    Attributes:
        reencodes: keyframes encoded again so far.
        seconds: wall-clock seconds spent encoding them.
    """

    def __init__(self, prior: Prior | None, capacity: int, max_bytes: int = 0) -> None:
        if capacity < 0:
            raise InputError(f"session.encoding_cache must be >= 0, got {capacity}")
        if max_bytes < 0:
            raise InputError(f"session.encoding_cache_mb must be >= 0, got {max_bytes} bytes")
        self.prior = prior
        self.capacity = capacity
        self.max_bytes = max_bytes
        self.reencodes = 0
        self.seconds = 0.0
        self._cache: OrderedDict[int, Encoding] = OrderedDict()
        self._bytes: dict[int, int] = {}  # per cached keyframe: its encoding's bytes

    @property
    def held_bytes(self) -> int:
        """Bytes of the re-encoded keyframes held."""
        return sum(self._bytes.values())

    def can_reencode(self, agent: int) -> bool:
        """Whether ``agent``'s keyframes need not carry (nor the store keep) encodings."""
        return self.prior is not None and self.prior.can_reencode(agent)

    def get(self, g: int, kf: Keyframe, agent: int, made: Encoding | None = None) -> Encoding:
        """The encoding of global keyframe ``g`` (``kf``, of ``agent``); ``made``: the one
        :meth:`maker` made for it on another thread, taken where it must be made.

        Raises:
            InputError: the keyframe holds no encoding and the prior cannot remake it (from
                its colours, or from them and the record it holds), or its colours are not
                at its pointmap's resolution (the image it encoded).
        """
        known = self.peek(g, kf)
        if known is not None:
            if g in self._cache:
                self._cache.move_to_end(g)
            return known
        if made is None:
            start = time.perf_counter()
            made = self.maker(kf, agent)()
            self.seconds += time.perf_counter() - start
        self.reencodes += 1
        if self.capacity > 0:
            self._cache[g], self._bytes[g] = made, sum(census(made).values())
            while len(self._cache) > self.capacity or (
                self.max_bytes and self.held_bytes > self.max_bytes
            ):
                del self._bytes[self._cache.popitem(last=False)[0]]
        return made

    def peek(self, g: int, kf: Keyframe) -> Encoding | None:
        """The encoding of global keyframe ``g`` held or cached (the cache's order
        unchanged), else None."""
        held = kf.encoding
        if held is not None and not isinstance(held, EncodingRecord):
            return held
        return self._cache.get(g)

    def maker(self, kf: Keyframe, agent: int) -> Callable[[], Encoding]:
        """What makes ``kf``'s encoding again, its fields read now: safe to call on another
        thread (it touches neither the keyframe nor the cache; raises as :meth:`get`)."""
        held, colors, shape, prior = kf.encoding, kf.colors, kf.shape, self.prior
        kf_id, frame_index = kf.kf_id, kf.frame_index

        def make() -> Encoding:
            if prior is None or (held is None and not prior.can_reencode(agent)):
                raise InputError(
                    f"coordinator: keyframe {kf_id} of agent {agent} came without its "
                    "encoding and this coordinator's prior cannot encode it again"
                )
            if tuple(colors.shape[:2]) != shape:
                raise InputError(
                    f"coordinator: keyframe {kf_id} of agent {agent} has colours of "
                    f"{tuple(colors.shape[:2])}, not the {shape} image its encoding came from"
                )
            try:
                record = held if isinstance(held, EncodingRecord) else None
                return prior.encode_again(colors, agent, frame_index, record)
            except PriorError as exc:
                raise InputError(f"coordinator: keyframe {kf_id} of agent {agent}: {exc}") from None

        return make

    def retain(self, needed: Collection[int]) -> None:
        """Let go of the re-encoded keyframes held whose global index is not in ``needed``
        (what is left of the work can use no other; the cache's order unchanged)."""
        for g in [g for g in self._cache if g not in needed]:
            del self._cache[g], self._bytes[g]

    def cached(self) -> list[int]:
        """Global indices of the re-encoded keyframes held, least recently used first."""
        return list(self._cache)
