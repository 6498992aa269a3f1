"""The messages of verification on the agents (``verification.on_agents``; issue 41,
:mod:`como3r.coordination.remote`).

Coordinator -> agent: :class:`VerificationRequest`, a keyframe's selected candidate pairs
with every keyframe image the pairs need (the query's and its candidates', which may be of
other agents), so any agent process can serve it whatever it holds itself.

Coordinator -> agent: :class:`VerificationDone`, no more requests: an agent process whose
stream has ended leaves as it would have at its end (across machines once the coordinator
stored every message; a :class:`~.messages.Shutdown` would abort it instead).

Agent -> coordinator: :class:`VerificationReply`, one :class:`VerifiedPair` per candidate
in the request's order, as :func:`~como3r.coordination.association.verify_candidates`
returned them, with the decodes and CPU seconds they cost the agent.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from como3r.frontend.pairs import DirectedMatches
from como3r.prior.base import Encoding
from como3r.transport import codec_registry
from como3r.transport.codec_types import require as _require
from como3r.transport.codec_types import require_shape as _shape


@dataclass(frozen=True)
class KeyframeImage:
    """What encoding one keyframe again needs (:meth:`~como3r.prior.base.Prior.
    encode_again`).

    Attributes:
        agent: the keyframe's agent (the coordinator's numbering).
        kf_id: its index within the agent.
        frame_index: its frame.
        colors: ``(H, W, 3)`` uint8 image at network resolution.
        encoding: the record the prior makes the encoding from with the colours
            (:meth:`~como3r.prior.base.Encoding.portable`), the encoding itself where the
            coordinator holds nothing smaller, or None (the prior encodes the colours alone).
    """

    agent: int
    kf_id: int
    frame_index: int
    colors: np.ndarray
    encoding: Encoding | None
    version: int = 1


@dataclass(frozen=True)
class VerificationRequest:
    """Coordinator -> agent: verify keyframe ``query``'s candidate pairs.

    Attributes:
        request: the coordinator's number of the request (the reply names it).
        query: ``(agent, kf_id)`` of the keyframe.
        candidates: ``(agent, kf_id)`` of each candidate, in the order to verify them.
        similarities: the retrieval similarity of each candidate (NaN for a loop candidate).
        images: the query's image and every candidate's (each once).
    """

    request: int
    query: tuple[int, int]
    candidates: list[tuple[int, int]]
    similarities: list[float]
    images: list[KeyframeImage]
    version: int = 1


@dataclass(frozen=True)
class VerificationDone:
    """Coordinator -> agent: no more verification requests will come."""

    version: int = 1


@dataclass(frozen=True)
class VerifiedPair:
    """One candidate pair verified (:class:`~como3r.coordination.association.Verification`).

    Attributes:
        ij: the query's pixels looked up in the candidate.
        covisible_ij: share of the query's pixels co-visible in the candidate.
        ji: the candidate's pixels looked up in the query, None when ``ij`` failed.
        covisible_ji: share of the candidate's pixels co-visible in the query.
        accepted: both tests passed in both directions.
    """

    ij: DirectedMatches
    covisible_ij: float | None
    ji: DirectedMatches | None
    covisible_ji: float | None
    accepted: bool
    version: int = 1


@dataclass(frozen=True)
class VerificationReply:
    """Agent -> coordinator: a :class:`VerificationRequest` served.

    Attributes:
        agent: the agent whose process served it (across machines, the key it came
            under must be this agent's).
        request: the request's number.
        query: its keyframe.
        pairs: one per candidate, in the request's order.
        decodes: the prior decodes it took.
        seconds: the agent's thread CPU seconds by stage (``reencode``, ``prior_decode``,
            ``verification``: the matching).
        after_stream: served after the agent's last frame (its frame rate did not pay it).
    """

    agent: int
    request: int
    query: tuple[int, int]
    pairs: list[VerifiedPair]
    decodes: int
    seconds: dict[str, float] = field(default_factory=dict)
    after_stream: bool = False
    version: int = 1


def _check_image(m: KeyframeImage) -> None:
    _require(m.agent >= 0 and m.kf_id >= 0 and m.frame_index >= 0, "ids must be >= 0")
    _shape(m.colors, (None, None, 3), "colors")
    _require(m.colors.dtype == np.uint8, f"colors must be uint8, got {m.colors.dtype}")


def _check_request(m: VerificationRequest) -> None:
    _require(m.request >= 0, "request must be >= 0")
    _require(
        len(m.candidates) == len(m.similarities) and len(m.candidates) > 0,
        "one similarity per candidate, at least one candidate",
    )
    held = {(image.agent, image.kf_id) for image in m.images}
    _require(
        tuple(m.query) in held and all(tuple(c) in held for c in m.candidates),
        "every keyframe of the request needs its image",
    )


def _check_pair(m: VerifiedPair) -> None:
    for value in (m.covisible_ij, m.covisible_ji):
        _require(value is None or 0.0 <= value <= 1.0, "co-visible shares lie in [0, 1]")
    _require(m.ji is not None or not m.accepted, "an accepted pair has both directions")


def _check_reply(m: VerificationReply) -> None:
    _require(
        m.agent >= 0 and m.request >= 0 and m.decodes >= 0,
        "agent, request and decodes must be >= 0",
    )
    _require(
        all(math.isfinite(v) and v >= 0 for v in m.seconds.values()),
        "seconds must be finite and >= 0",
    )


# on the lossy wire: the image lossless (it is encoded again), the matches as an
# inter-agent edge's in the session store (the confidences in its finer steps)
codec_registry.register(KeyframeImage, coded={"colors": "image"})
codec_registry.register(VerificationRequest)
codec_registry.register(VerificationDone)
codec_registry.register(VerifiedPair, coded={"ij": "inter_matches", "ji": "inter_matches"})
codec_registry.register(VerificationReply)
for _name, _check in (
    ("KeyframeImage", _check_image),
    ("VerificationRequest", _check_request),
    ("VerifiedPair", _check_pair),
    ("VerificationReply", _check_reply),
):
    codec_registry.add_check(_name, _check)
