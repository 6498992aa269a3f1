"""The messages of the multi-process runtime (C-Sec. B.1, A.8; manual:
docs/architecture.md, "Processes and messages").

Agents and the coordinator share nothing but these messages. Each is a frozen dataclass
with a ``version`` field and is registered with :mod:`como3r.transport.codec`, which encodes
it without pickle and validates it on decode. The payloads of
:mod:`como3r.frontend.packets` travel wrapped in them.

Coordinator -> agent (one pipe per agent):

* :class:`AgentTask` -- the first message: what to run, with which configuration and prior;
* :class:`PoseUpdateMessage` -- new world poses of the agent's keyframes, numbered;
* :class:`Step` -- lockstep mode only: process your next frame;
* :class:`Shutdown` -- stop now (the run is being aborted);
* :class:`~.verification_messages.VerificationRequest` -- verify a keyframe's candidate
  pairs (``verification.on_agents``), and :class:`~.verification_messages.VerificationDone`
  -- no more of them (an agent whose stream ended then leaves).

Agent -> coordinator (one pipe per agent):

* :class:`AgentStarted` -- the input is open and the prior built;
* :class:`KeyframeMessage` -- a new keyframe;
* :class:`FrameDone` -- one frame processed (progress, and the agent's clock);
* :class:`~como3r.live.FrameEvent` -- the frame's pose, intrinsics and a small image, sent
  before its ``FrameDone`` only when the task asks (``AgentTask.live``: a viewer watches);
* :class:`AgentFinished` -- the stream ended: final fused pointmap, statistics and the
  anchored trajectory (C-Sec. A.8) from which the coordinator writes the agent's outputs;
* :class:`AgentFailed` -- the agent hit an error and is exiting;
* :class:`~.verification_messages.VerificationReply` -- a verification request served.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from como3r.errors import MessageError
from como3r.frontend.agent import FrontendStats
from como3r.frontend.packets import KeyframePacket, PointmapRefresh, PoseUpdate
from como3r.frontend.pairs import DirectedMatches
from como3r.live import FrameEvent
from como3r.prior.retrieval import Aggregated
from como3r.transport import codec, codec_registry
from como3r.transport.codec_types import require as _require
from como3r.transport.codec_types import require_shape as _shape
from como3r.transport.verification_messages import (
    VerificationDone,
    VerificationReply,
    VerificationRequest,
)


@dataclass(frozen=True)
class AgentTask:
    """Coordinator -> agent: the agent's whole job (the first message it receives).

    Attributes:
        agent: agent id.
        input_path: the agent input (folder or video).
        config: the effective configuration as a nested mapping
            (:func:`como3r.config.config_to_dict`; the agent re-validates it).
        prior: the prior specification (``name``, ``weights``, ``retrieval_weights``,
            ``codebook``, ``device``, ``precision``; paths as strings or None).
        torch_threads: intra-op threads of the agent's torch.
        lockstep: process a frame only when told by a :class:`Step`.
        max_message_bytes: size cap of every message.
        log_level: the agent's logging level.
        live: send a :class:`~como3r.live.FrameEvent` after every frame (a viewer watches).
        resume_after: process only the frames after this index (a process taking over the
            id of an agent whose earlier process left; -1: every frame).
        send_encoding: send each keyframe's encoding; False when the coordinator encodes
            the keyframes' colours again itself (:mod:`como3r.coordination.encodings`).
        verify: serve the :class:`~.verification_messages.VerificationRequest` messages
            between frames and, once the stream has ended, until a
            :class:`~.verification_messages.VerificationDone` (``verification.on_agents``:
            :mod:`como3r.runtime.remote_verification`).
    """

    agent: int
    input_path: str
    config: dict[str, Any]
    prior: dict[str, Any]
    torch_threads: int = 1
    lockstep: bool = False
    max_message_bytes: int = codec.DEFAULT_MAX_BYTES
    log_level: int = 30
    live: bool = False
    resume_after: int = -1
    send_encoding: bool = True
    verify: bool = False
    version: int = 5


@dataclass(frozen=True)
class AgentStarted:
    """Agent -> coordinator: ready to process ``frames`` frames.

    Attributes:
        agent: agent id.
        pid: the agent's process id.
        frames: frames it will process (after subsampling).
    """

    agent: int
    pid: int
    frames: int
    version: int = 1


@dataclass(frozen=True)
class KeyframeMessage:
    """Agent -> coordinator: a new keyframe.

    Attributes:
        packet: the keyframe's payload; ``packet.T_WC`` is in the agent's world frame after
            the pose updates up to ``applied_seq``.
        applied_seq: number of pose updates the agent had applied when it exported it.
        T_WC_previous: ``(8,)`` the agent's pose of keyframe ``kf_id - 1`` at export (None
            for the first keyframe): lets the coordinator re-anchor a packet exported before
            the agent saw the latest update (C-Sec. A.8).
    """

    packet: KeyframePacket
    applied_seq: int
    T_WC_previous: Tensor | None
    version: int = 1


@dataclass(frozen=True)
class FrameDone:
    """Agent -> coordinator: a frame was processed; every keyframe it released was sent
    (a self-calibrated agent's first keyframes wait for its camera:
    :meth:`~como3r.frontend.agent.AgentFrontend.settle_camera`).

    Attributes:
        agent: agent id.
        frame_index: the frame's index in the agent's stream.
        timestamp: the frame's timestamp (the agent's clock for ordering keyframes).
        outcome: ``"keyframe"``, ``"tracked"``, ``"relocalized"`` or ``"lost"``.
        seconds: front-end wall-clock time of the frame.
        keyframes_waiting: keyframes the agent made but has not sent yet (they wait for its
            camera); its progress counts them.
    """

    agent: int
    frame_index: int
    timestamp: float
    outcome: str
    seconds: float
    keyframes_waiting: int
    version: int = 2


@dataclass(frozen=True)
class EdgeSummary:
    """One directed edge of an agent's local keyframe graph (for graph.json).

    Attributes:
        i, j: keyframe ids of the ordered pair.
        kind: ``"sequential"`` or ``"loop"``.
        match_fraction: ``nu`` of the direction.
    """

    i: int
    j: int
    kind: str
    match_fraction: float
    version: int = 1


@dataclass(frozen=True)
class AgentFinished:
    """Agent -> coordinator: the stream ended.

    The trajectory travels anchored (C-Sec. A.8): frame ``n`` is at
    ``T_WC[anchors[n]] * T_rel[n]``, so pose updates the agent never saw can still be
    applied to its keyframes before the trajectory is composed.

    Attributes:
        agent: agent id.
        final: the last keyframe's fused canonical pointmap (None without keyframes).
        stats: the front-end's counters.
        seconds: total front-end time.
        applied_seq: pose updates applied before finishing.
        frame_indices: ``(N,)`` int64 tracked frames.
        timestamps: ``(N,)`` float64 their timestamps.
        anchors: ``(N,)`` int64 anchor keyframe of each frame.
        T_rel: ``(N, 8)`` each frame's pose in its anchor keyframe.
        keyframe_frames: ``(K,)`` int64 frame index of each keyframe.
        keyframe_timestamps: ``(K,)`` float64.
        keyframe_T_WC: ``(K, 8)`` the agent's keyframe poses.
        edges: the agent's local keyframe graph.
        keyframe_bytes_by_part: bytes of the keyframe messages this process sent, summed
            per part (:data:`~como3r.transport.keyframe_bytes.PARTS`), as they were encoded.
        keyframes_measured: the keyframe messages they sum.
    """

    agent: int
    final: PointmapRefresh | None
    stats: FrontendStats
    seconds: float
    applied_seq: int
    frame_indices: np.ndarray
    timestamps: np.ndarray
    anchors: np.ndarray
    T_rel: Tensor
    keyframe_frames: np.ndarray
    keyframe_timestamps: np.ndarray
    keyframe_T_WC: Tensor
    edges: list[EdgeSummary] = field(default_factory=list)
    keyframe_bytes_by_part: dict[str, int] = field(default_factory=dict)
    keyframes_measured: int = 0
    version: int = 2


@dataclass(frozen=True)
class AgentFailed:
    """Agent -> coordinator: the agent stops on an error.

    Attributes:
        agent: agent id.
        error: one-line description (``Type: message``).
        details: traceback text for errors that are not a Como3rError, else empty.
        frame_index: the frame being processed, -1 outside the frame loop.
    """

    agent: int
    error: str
    details: str = ""
    frame_index: int = -1
    version: int = 1


@dataclass(frozen=True)
class PoseUpdateMessage:
    """Coordinator -> agent: the ``seq``-th pose update for this agent (1, 2, ...)."""

    update: PoseUpdate
    seq: int
    version: int = 1


@dataclass(frozen=True)
class Step:
    """Coordinator -> agent (lockstep mode): process frame ``frame_index`` now; -1: end
    your stream now; -2: the keyframe you sent was taken, go on (its updates came first)."""

    frame_index: int
    version: int = 1


@dataclass(frozen=True)
class Shutdown:
    """Coordinator -> agent: stop without finishing (the run is aborted)."""

    reason: str = ""
    version: int = 1


TO_AGENT = (AgentTask, PoseUpdateMessage, Step, Shutdown, VerificationRequest, VerificationDone)
"""Messages an agent accepts."""

FROM_AGENT = (
    AgentStarted,
    KeyframeMessage,
    FrameDone,
    FrameEvent,
    AgentFinished,
    AgentFailed,
    VerificationReply,
)
"""Messages the coordinator accepts from an agent."""


# ------------------------------------------------------------------ checks on decode
# The codec checks types; these check the shapes and ranges the receiver relies on, so a
# malformed message fails at the boundary with a clear error instead of deep in torch.


def _floating(x: Tensor, name: str) -> None:
    _require(x.is_floating_point(), f"{name} must be floating point, got {x.dtype}")


def _check_pose_update(u: PoseUpdate) -> None:
    _shape(u.kf_ids, (None,), "kf_ids")
    _require(
        u.kf_ids.dtype == torch.int64 and bool((u.kf_ids >= 0).all()),
        "kf_ids must be non-negative int64",
    )
    _shape(u.T_WC, (u.kf_ids.shape[0], 8), "T_WC")
    _floating(u.T_WC, "T_WC")
    _require(
        u.focal is None or (math.isfinite(u.focal) and u.focal > 0),
        f"focal must be positive and finite, got {u.focal}",
    )


def _check_refresh(r: PointmapRefresh) -> None:
    _require(r.kf_id >= 0 and r.fused_frames >= 1, "kf_id must be >= 0 and fused_frames >= 1")
    _shape(r.X_hat, (None, None, 3), "X_hat")
    _shape(r.C_hat, tuple(r.X_hat.shape[:2]), "C_hat")
    _floating(r.X_hat, "X_hat")
    _floating(r.C_hat, "C_hat")
    if r.K is not None:
        _shape(r.K, (3, 3), "K")
        _floating(r.K, "K")


def _check_matches(m: DirectedMatches) -> None:
    _shape(m.idx, (None,), "idx")
    _shape(m.valid, tuple(m.idx.shape), "valid")
    _shape(m.q, tuple(m.idx.shape), "q")
    _require(
        m.idx.dtype == torch.int64 and m.valid.dtype == torch.bool,
        "idx must be int64 and valid bool",
    )
    # both keyframes of an agent's edge share the agent's resolution: P_i == P_j
    _require(
        m.idx.numel() == 0 or bool(((m.idx >= 0) & (m.idx < m.idx.numel())).all()),
        "idx must index pixels of the keyframe",
    )


def _check_packet(p: KeyframePacket) -> None:
    _require(
        p.agent >= 0 and p.kf_id >= 0 and p.frame_index >= 0,
        "agent, kf_id and frame_index must be >= 0",
    )
    _require(math.isfinite(p.timestamp), f"timestamp {p.timestamp} is not finite")
    _shape(p.T_WC, (8,), "T_WC")
    _check_refresh(PointmapRefresh(p.kf_id, p.X_hat, p.C_hat, 1))
    height, width = p.X_hat.shape[:2]
    _shape(p.colors, (height, width, 3), "colors")
    _require(p.colors.dtype == np.uint8, f"colors must be uint8, got {p.colors.dtype}")
    for name in ("sequential_ij", "sequential_ji"):
        matches = getattr(p, name)
        if matches is not None:
            _shape(matches.idx, (height * width,), f"{name}.idx")
    if p.K is not None:
        _shape(p.K, (3, 3), "K")
        _floating(p.K, "K")
    if p.previous is not None:
        _require(p.previous.kf_id == p.kf_id - 1, "previous must refresh keyframe kf_id - 1")
    if isinstance(p.retrieval, tuple):
        descriptors, attention = p.retrieval
        _shape(descriptors, (None, None), "retrieval descriptors")
        _shape(attention, (descriptors.shape[0],), "retrieval attention")
    if p.retrieval_words is not None:
        if not isinstance(p.retrieval, tuple) or p.codebook_id is None:
            raise MessageError("retrieval_words need retrieval descriptors and codebook_id")
        _shape(p.retrieval_words, (p.retrieval[0].shape[0], None), "retrieval_words")
        _require(
            p.retrieval_words.dtype.kind in "iu",
            f"retrieval_words must be integers, got {p.retrieval_words.dtype}",
        )


def _check_aggregated(a: Aggregated) -> None:
    """Shapes and dtypes; the words' range and order are the receiving database's to check
    (:meth:`~como3r.prior.retrieval.RetrievalDatabase.query_and_add`)."""
    for half in ("query", "build"):
        words, bits = getattr(a, f"{half}_words"), getattr(a, f"{half}_bits")
        _require(
            isinstance(words, np.ndarray) and isinstance(bits, np.ndarray),
            f"{half} words and bits must be arrays",
        )
        _shape(words, (None,), f"{half}_words")
        _shape(bits, (words.shape[0], None), f"{half}_bits")
        _require(words.dtype == np.int64, f"{half}_words must be int64, got {words.dtype}")
        _require(bits.dtype == np.uint32, f"{half}_bits must be uint32, got {bits.dtype}")
    _require(a.query_bits.shape[1] == a.build_bits.shape[1], "query and build bits of other widths")


def _check_keyframe_message(m: KeyframeMessage) -> None:
    _require(m.applied_seq >= 0, "applied_seq must be >= 0")
    if m.T_WC_previous is not None:
        _shape(m.T_WC_previous, (8,), "T_WC_previous")


def _check_frame_done(m: FrameDone) -> None:
    _require(
        m.frame_index >= 0 and m.seconds >= 0 and m.keyframes_waiting >= 0,
        "frame_index, seconds and keyframes_waiting must be >= 0",
    )
    _require(math.isfinite(m.timestamp), f"timestamp {m.timestamp} is not finite")


def _check_frame_event(m: FrameEvent) -> None:
    _require(m.frame_index >= 0, "frame_index must be >= 0")
    _shape(m.image, (None, None, 3), "image")
    _require(m.image.dtype == np.uint8, f"image must be uint8, got {m.image.dtype}")
    if m.T_WC is not None:
        _shape(m.T_WC, (8,), "T_WC")
    if m.K is not None:
        _shape(m.K, (3, 3), "K")


def _check_finished(m: AgentFinished) -> None:
    frames, keyframes = len(m.frame_indices), len(m.keyframe_frames)
    for name, shape in (
        ("frame_indices", (frames,)),
        ("timestamps", (frames,)),
        ("anchors", (frames,)),
        ("T_rel", (frames, 8)),
        ("keyframe_timestamps", (keyframes,)),
        ("keyframe_T_WC", (keyframes, 8)),
    ):
        _shape(getattr(m, name), shape, name)
    _require(
        frames == 0 or (int(m.anchors.min()) >= 0 and int(m.anchors.max()) < keyframes),
        "anchors must be keyframe ids",
    )
    _require(m.applied_seq >= 0, "applied_seq must be >= 0")
    _require(
        m.keyframes_measured >= 0 and all(v >= 0 for v in m.keyframe_bytes_by_part.values()),
        "keyframes_measured and keyframe_bytes_by_part must be >= 0",
    )


def _check_update_message(m: PoseUpdateMessage) -> None:
    _require(m.seq >= 1, "seq must be >= 1")


for _cls in (*TO_AGENT, *FROM_AGENT, EdgeSummary):
    # AgentTask 3: resume_after, 4: send_encoding, 5: verify; FrameDone 2: keyframes_waiting;
    # AgentFinished 2: the keyframe bytes per part, measured by the agent (the verification
    # messages register themselves: .verification_messages)
    if _cls not in (VerificationRequest, VerificationDone, VerificationReply):
        codec_registry.register(
            _cls, version={AgentTask: 5, FrameDone: 2, AgentFinished: 2}.get(_cls, 1)
        )

for _name, _check in (
    ("PoseUpdate", _check_pose_update),
    ("PointmapRefresh", _check_refresh),
    ("DirectedMatches", _check_matches),
    ("KeyframePacket", _check_packet),
    ("Aggregated", _check_aggregated),
    ("KeyframeMessage", _check_keyframe_message),
    ("FrameDone", _check_frame_done),
    ("FrameEvent", _check_frame_event),
    ("AgentFinished", _check_finished),
    ("PoseUpdateMessage", _check_update_message),
):
    codec_registry.add_check(_name, _check)
