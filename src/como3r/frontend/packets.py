"""What an agent sends to the coordinator and receives back (C-Sec. 3.1, A.8, B.1).

Two payloads cross the agent/coordinator boundary:

* :class:`KeyframePacket`, agent -> coordinator, once per new keyframe: everything the
  coordinator needs to retrieve, verify and optimise with the keyframe (its encoding for
  pair decodes, unless the coordinator encodes its colours again, retrieval features, canonical pointmap, pose, and the dense sequential edge
  to the agent's previous keyframe), plus a refresh of the previous keyframe's fused
  canonical pointmap, which kept absorbing frames after it was sent.
* :class:`PoseUpdate`, coordinator -> agent, after every gauge transport or global solve.
* :class:`PointmapUpdate`, coordinator -> agent, once at the end: the canonical pointmaps of
  the terminal depth refinement (C-Sec. A.7).

They are plain dataclasses of tensors; ``como3r.runtime`` encodes them for transport.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from torch import Tensor

from como3r.frontend.pairs import DirectedMatches
from como3r.prior.base import Encoding
from como3r.prior.retrieval import Aggregated


@dataclass(frozen=True)
class PointmapRefresh:
    """The current fused canonical pointmap of an already sent keyframe.

    Attributes:
        kf_id: keyframe id within the agent.
        X_hat: ``(H, W, 3)`` float32 canonical pointmap (camera frame).
        C_hat: ``(H, W)`` float32 accumulated confidence.
        fused_frames: frames fused into it.
        K: ``(3, 3)`` intrinsics whose rays ``X_hat`` lies on (calibrated and
            self-calibrated runs), None otherwise.
    """

    kf_id: int
    X_hat: Tensor
    C_hat: Tensor
    fused_frames: int
    K: Tensor | None = None


@dataclass(frozen=True)
class KeyframePacket:
    """A new keyframe of one agent.

    Attributes:
        agent: agent id.
        kf_id: keyframe id within the agent (0, 1, ...).
        frame_index: frame index in the agent's stream.
        timestamp: seconds.
        T_WC: ``(8,)`` pose in the agent's current world frame.
        X_hat: ``(H, W, 3)`` canonical pointmap at insertion (also the frozen ``X_init``
            of C-Eq. 19).
        C_hat: ``(H, W)`` its confidence.
        colors: ``(H, W, 3)`` uint8 image at network resolution.
        encoding: the prior's encoding of the keyframe; None when the receiver encodes
            ``colors`` again itself (it said so at the session start:
            :attr:`~como3r.transport.messages.AgentTask.send_encoding`;
            :mod:`como3r.coordination.encodings`).
        retrieval: ``(descriptors (N, d_r), attention (N,))``, or what the coordinator's
            binary ASMK reads of them (:class:`~como3r.prior.retrieval.Aggregated`, which an
            agent with a codebook sends: a third smaller at MASt3R's shapes), or None
            without retrieval.
        sequential_ij: matches of the edge (kf_id - 1, kf_id), None for the first keyframe.
        sequential_ji: matches of the edge (kf_id, kf_id - 1).
        previous: refresh of keyframe ``kf_id - 1`` (None for the first keyframe).
        K: ``(3, 3)`` intrinsics at the pointmap's resolution in a calibrated run (the
            global BA then uses the calibrated residual of C-Eq. 17), else None.
        retrieval_words: ``(N, MA)`` int32 nearest visual words of ``retrieval``'s
            descriptors, nearest first, in the agent's codebook (MA: the larger multiple
            assignment), or None. A coordinator whose codebook has the fingerprint
            ``codebook_id`` takes them instead of searching its own codebook (at the
            released codebook's size 0.3 s of a CPU core per keyframe).
        codebook_id: :func:`~como3r.prior.retrieval.codebook_fingerprint` of that codebook.
    """

    agent: int
    kf_id: int
    frame_index: int
    timestamp: float
    T_WC: Tensor
    X_hat: Tensor
    C_hat: Tensor
    colors: np.ndarray
    encoding: Encoding | None
    retrieval: tuple[Tensor, Tensor] | Aggregated | None
    sequential_ij: DirectedMatches | None
    sequential_ji: DirectedMatches | None
    previous: PointmapRefresh | None
    K: Tensor | None = None
    retrieval_words: np.ndarray | None = None
    codebook_id: str | None = None


@dataclass(frozen=True)
class PoseUpdate:
    """New world poses of some of an agent's keyframes.

    Attributes:
        agent: agent id.
        kf_ids: ``(K,)`` int64 keyframe ids.
        T_WC: ``(K, 8)`` their poses in the shared world frame.
        reason: ``"gauge"``, ``"global_ba"``, ``"cleanup"`` or ``"resume"`` (a re-sent
            keyframe answered by a coordinator that resumed from its session store).
        focal: the agent's focal length (``fx`` at network resolution, pixels) in the
            shared map (:mod:`como3r.frontend.focal`): keyframes on another focal length
            are rescaled to it first; None leaves them as they are.
    """

    agent: int
    kf_ids: Tensor
    T_WC: Tensor
    reason: str
    focal: float | None = None


@dataclass(frozen=True)
class PointmapUpdate:
    """Refined canonical pointmaps of some of an agent's keyframes (C-Eq. 19, C-Sec. A.7).

    Attributes:
        agent: agent id.
        kf_ids: ``(K,)`` int64 keyframe ids.
        X_hat: ``(K, H, W, 3)`` their refined canonical pointmaps (camera frames).
    """

    agent: int
    kf_ids: Tensor
    X_hat: Tensor
