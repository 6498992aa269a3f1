"""An agent process's side of verification on the agents (``verification.on_agents``;
the coordinator's side: :mod:`.remote_verification`): :func:`serve` encodes a request's
keyframes again from their images (:meth:`~como3r.prior.base.Prior.encode_again`), verifies
its pairs as the coordinator would (:func:`~como3r.coordination.association.
verify_candidates`) and makes the reply, with the decodes and the thread CPU seconds by
stage. An agent imports it on its first request (:mod:`.agent_worker`): one that verifies
nothing imports no part of the coordinator.
"""

from __future__ import annotations

import time

from como3r.config import Config
from como3r.coordination.association import verify_candidates
from como3r.coordination.decode_pool import CountingPrior
from como3r.prior.base import Encoding, EncodingRecord, Prior
from como3r.prior.retrieval import Hit
from como3r.transport.verification_messages import (
    VerificationReply,
    VerificationRequest,
    VerifiedPair,
)


def serve(
    agent: int,
    prior: Prior,
    config: Config,
    request: VerificationRequest,
    after_stream: bool = False,
) -> VerificationReply:
    """Verify a request's pairs in agent ``agent``'s process as the coordinator would;
    ``after_stream``: the agent's frames are done."""
    start = time.thread_time()
    encodings: dict[tuple[int, int], Encoding] = {}
    for image in request.images:
        held = image.encoding
        if held is None or isinstance(held, EncodingRecord):
            encodings[(image.agent, image.kf_id)] = prior.encode_again(
                image.colors, image.agent, image.frame_index, held
            )
        else:
            encodings[(image.agent, image.kf_id)] = held
    reencode = time.thread_time() - start
    counting = CountingPrior(prior)
    query = (int(request.query[0]), int(request.query[1]))
    verifications = verify_candidates(
        counting,  # type: ignore[arg-type]
        query,
        encodings[query],
        [
            (Hit(int(agent), int(kf_id), float(similarity)), encodings[(agent, kf_id)])
            for (agent, kf_id), similarity in zip(request.candidates, request.similarities)
        ],
        config.matching,
        config.tracking.q_min,
        config.verification,
    )
    total = time.thread_time() - start
    return VerificationReply(
        agent=agent,
        request=request.request,
        query=query,
        pairs=[
            VerifiedPair(
                v.ij,
                v.covisible_j,
                None if v.link is None else v.link.ji,
                v.covisible_i,
                v.accepted,
            )
            for v in verifications
        ],
        decodes=counting.decodes,
        seconds={
            "reencode": reencode,
            "prior_decode": counting.seconds,
            "verification": max(0.0, total - reencode - counting.seconds),
        },
        after_stream=after_stream,
    )
