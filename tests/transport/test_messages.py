"""Runtime messages: schema, real front-end payloads across the codec, checks on decode."""

from __future__ import annotations

import dataclasses
from dataclasses import fields, is_dataclass, replace
from typing import Any

import numpy as np
import pytest
import torch

from como3r.config import Config, apply_overrides, config_from_dict, config_to_dict
from como3r.data.agent import open_agent
from como3r.data.ground_truth import AgentFolderTruth
from como3r.data.preprocess import make_view
from como3r.data.synth import synthesize
from como3r.errors import MessageError
from como3r.frontend.agent import AgentFrontend, FrontendStats
from como3r.frontend.packets import KeyframePacket, PoseUpdate
from como3r.prior.retrieval import Aggregated
from como3r.prior.simulated import SimulatedPrior
from como3r.runtime.pipeline import _colors
from como3r.transport import codec_registry, messages
from como3r.transport.codec import decode, encode
from como3r.transport.keyframe_bytes import wire_parts

WIDTH, HEIGHT, FRAMES = 64, 48, 8


@pytest.fixture(scope="module")
def frontend(tmp_path_factory) -> AgentFrontend:
    """A front-end that has run over a few frames of a small synthetic scene."""
    root = tmp_path_factory.mktemp("scene")
    synthesize(
        root,
        agents=2,
        seed=0,
        overlap=0.5,
        frames=FRAMES,
        preset="default",
        width=WIDTH,
        height=HEIGHT,
    )
    agent = open_agent(root / "agent_0")
    # the easy simulated prior: the realistic default makes a single keyframe here
    config = apply_overrides(Config(), [f"input.long_side={WIDTH}", "simulated_prior.model=easy"])
    prior = SimulatedPrior(config.simulated_prior, AgentFolderTruth({0: agent}, WIDTH))
    fe = AgentFrontend(prior, config, 0, prior.codebook())
    for i in range(0, agent.num_frames, config.input.subsample):
        frame = agent.load_frame(i)
        view = make_view(frame, 0, WIDTH)
        fe.process(view, frame.timestamp, _colors(view))
    assert len(fe.keyframes) >= 2
    return fe


def identical(a: Any, b: Any) -> bool:
    """Same types and structure, bit-identical arrays."""
    if type(a) is not type(b):
        return False
    if isinstance(a, torch.Tensor):
        return (
            a.dtype == b.dtype
            and a.shape == b.shape
            and (a.contiguous().numpy().tobytes() == b.numpy().tobytes())
        )
    if isinstance(a, np.ndarray):
        return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
    if is_dataclass(a):
        return all(identical(getattr(a, f.name), getattr(b, f.name)) for f in fields(a))
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(identical(x, y) for x, y in zip(a, b))
    return a == b


def _packet_message(fe: AgentFrontend, kf_id: int) -> messages.KeyframeMessage:
    previous = fe.keyframes[kf_id - 1].T_WC if kf_id > 0 else None
    return messages.KeyframeMessage(
        fe.export_keyframe(kf_id), applied_seq=0, T_WC_previous=previous
    )


# ---------------------------------------------------------------------- schema


#: messages past their first schema (AgentTask 2: live, 3: resume_after, 4: send_encoding,
#: 5: verify)
VERSIONS = {"AgentTask": 5, "FrameDone": 2, "AgentFinished": 2}


@pytest.mark.parametrize(
    "cls",
    [*messages.TO_AGENT, *messages.FROM_AGENT, messages.EdgeSummary],
    ids=lambda c: c.__name__,
)
def test_every_message_is_a_frozen_versioned_registered_dataclass(cls: type) -> None:
    assert dataclasses.is_dataclass(cls) and cls.__dataclass_params__.frozen
    version = {f.name: f.default for f in fields(cls)}["version"]
    assert codec_registry.REGISTRY[cls.__name__].version == version == VERSIONS.get(cls.__name__, 1)
    assert codec_registry.registered_types()[cls.__name__] is cls


def test_message_directions_are_disjoint() -> None:
    assert not set(messages.TO_AGENT) & set(messages.FROM_AGENT)


# ---------------------------------------------------------------------- real payloads


def test_real_keyframe_messages_round_trip_bit_exactly(frontend: AgentFrontend) -> None:
    for kf_id in range(len(frontend.keyframes)):
        message = _packet_message(frontend, kf_id)
        back = decode(encode(message), expected=messages.KeyframeMessage)
        assert identical(message, back)
        assert (back.packet.previous is None) == (kf_id == 0)


def test_decoded_encodings_decode_to_the_same_prediction(frontend: AgentFrontend) -> None:
    """What crosses the process boundary is as good as the original for the prior."""
    enc_a, enc_b = (frontend.keyframes[k].encoding for k in (0, 1))
    copy_a, copy_b = (
        decode(
            encode(messages.KeyframeMessage(frontend.export_keyframe(k), 0, None))
        ).packet.encoding
        for k in (0, 1)
    )
    original, copied = frontend.prior.decode(enc_a, enc_b), frontend.prior.decode(copy_a, copy_b)
    assert identical(original, copied)


def test_keyframe_message_is_compressed_below_its_raw_arrays(frontend: AgentFrontend) -> None:
    """Arrays travel losslessly compressed (codec: byte planes + Zstandard)."""
    message = _packet_message(frontend, 1)

    def raw_bytes(value: Any) -> int:
        if isinstance(value, torch.Tensor):
            return value.numel() * value.element_size()
        if isinstance(value, np.ndarray):
            return value.nbytes
        if is_dataclass(value):
            return sum(raw_bytes(getattr(value, f.name)) for f in fields(value))
        if isinstance(value, (list, tuple)):
            return sum(raw_bytes(v) for v in value)
        return 0

    raw = raw_bytes(message)
    assert len(encode(message)) < 0.9 * raw


def test_pose_update_message_applies_like_the_original(frontend: AgentFrontend) -> None:
    K = len(frontend.keyframes) - 1  # leave the newest to follow rigidly
    update = PoseUpdate(
        agent=0, kf_ids=torch.arange(K), T_WC=frontend.keyframes.poses()[:K] + 0.01, reason="gauge"
    )
    back = decode(encode(messages.PoseUpdateMessage(update, seq=1))).update
    assert identical(update, back)


def test_agent_task_carries_the_configuration(tmp_path) -> None:
    config = apply_overrides(
        Config(),
        [
            "input.long_side=96",
            "tracking.sigma_ray=0.002",
            "loop_closure=false",
            "depth.variant=pixel",
        ],
    )
    task = messages.AgentTask(
        agent=1,
        input_path=str(tmp_path),
        config=config_to_dict(config),
        prior={"name": "simulated", "weights": None, "device": "cpu"},
    )
    back = decode(encode(task), expected=messages.AgentTask)
    assert config_from_dict(Config, back.config) == config


# ---------------------------------------------------------------------- checks on decode


def _reject(message: Any, match: str) -> None:
    data = encode(message)  # the sender does not check; the receiver must
    with pytest.raises(MessageError, match=match):
        decode(data)


def test_malformed_pose_updates_are_rejected() -> None:
    good = PoseUpdate(agent=0, kf_ids=torch.arange(3), T_WC=torch.zeros(3, 8), reason="gauge")
    _reject(messages.PoseUpdateMessage(replace(good, T_WC=torch.zeros(3, 7)), 1), r"\(3, 8\)")
    _reject(messages.PoseUpdateMessage(replace(good, T_WC=torch.zeros(2, 8)), 1), r"\(3, 8\)")
    _reject(
        messages.PoseUpdateMessage(replace(good, kf_ids=torch.tensor([0, -1, 2])), 1),
        "non-negative",
    )
    _reject(messages.PoseUpdateMessage(replace(good, kf_ids=torch.zeros(3)), 1), "int64")
    _reject(
        messages.PoseUpdateMessage(replace(good, T_WC=torch.zeros(3, 8, dtype=torch.int64)), 1),
        "floating",
    )


def _with_words(fe: AgentFrontend, packet: KeyframePacket) -> KeyframePacket:
    """``packet`` with its keyframe's retrieval descriptors and their words (as a packet
    made by an agent without the coordinator's codebook would carry them)."""
    retrieval = fe.keyframes[packet.kf_id].retrieval
    words = fe.database.quantize(retrieval[0]).words.astype(np.int32)
    return replace(
        packet, retrieval=retrieval, retrieval_words=words, codebook_id=fe.database.codebook_id
    )


def test_retrieval_words_round_trip_bit_exactly(frontend: AgentFrontend) -> None:
    message = _packet_message(frontend, 1)
    message = replace(message, packet=_with_words(frontend, message.packet))
    assert identical(message, decode(encode(message), expected=messages.KeyframeMessage))


def test_an_agent_with_a_codebook_sends_its_retrieval_aggregated(frontend: AgentFrontend) -> None:
    """What the coordinator's ASMK reads of the descriptors, bit-exact on either wire, and
    smaller on the lossy one than the descriptors in 8 bits with their words."""
    message = _packet_message(frontend, 1)
    aggregated = message.packet.retrieval
    assert isinstance(aggregated, Aggregated) and message.packet.retrieval_words is None
    assert aggregated.codebook_id == frontend.database.codebook_id
    descriptors = frontend.keyframes[1].retrieval[0]
    assert identical(aggregated, frontend.database.aggregate(descriptors))
    for lossy in (False, True):
        back = decode(encode(message, lossy=lossy), expected=messages.KeyframeMessage)
        assert identical(back.packet.retrieval, aggregated)
    sizes = wire_parts(message, lossy=True)
    with_words = wire_parts(
        replace(message, packet=_with_words(frontend, message.packet)), lossy=True
    )
    assert sizes["retrieval_words"] == 1 and sizes["retrieval_descriptors"] > 0  # 1: nil
    assert sizes["retrieval_descriptors"] < (
        with_words["retrieval_descriptors"] + with_words["retrieval_words"]
    )


def test_malformed_keyframe_packets_are_rejected(frontend: AgentFrontend) -> None:
    message = _packet_message(frontend, 1)
    packet = message.packet
    with_words = _with_words(frontend, packet)
    words, retrieval = with_words.retrieval_words, with_words.retrieval
    aggregated = packet.retrieval
    for bad, match in [
        (replace(packet, T_WC=torch.zeros(7)), r"T_WC has shape"),
        (replace(packet, C_hat=packet.C_hat[1:]), r"C_hat has shape"),
        (replace(packet, X_hat=packet.X_hat[..., :2]), r"X_hat has shape"),
        (replace(packet, colors=packet.colors.astype(np.float32)), "uint8"),
        (replace(packet, colors=packet.colors[:, 1:]), "colors has shape"),
        (replace(packet, kf_id=-1), ">= 0"),
        (replace(packet, timestamp=float("nan")), "not finite"),
        (replace(packet, previous=replace(packet.previous, kf_id=5)), "kf_id - 1"),
        (
            replace(
                packet,
                sequential_ij=replace(packet.sequential_ij, idx=packet.sequential_ij.idx[1:]),
            ),
            "valid has",
        ),
        (replace(packet, retrieval=(retrieval[0], retrieval[1][1:])), "attention"),
        (
            replace(packet, retrieval=replace(aggregated, query_bits=aggregated.query_bits[1:])),
            "query_bits has shape",
        ),
        (
            replace(
                packet,
                retrieval=replace(aggregated, build_bits=aggregated.build_bits.astype(np.int64)),
            ),
            "build_bits must be uint32",
        ),
        (replace(packet, retrieval_words=words, codebook_id="c"), "need retrieval descriptors"),
        (replace(packet, K=torch.eye(3)[:2]), "K has shape"),
        (replace(packet, K=torch.eye(3, dtype=torch.int64)), "K must be floating"),
        (replace(with_words, codebook_id=None), "need retrieval descriptors and codebook_id"),
        (replace(with_words, retrieval_words=words[1:]), "retrieval_words has shape"),
        (replace(with_words, retrieval_words=words.astype(np.float32)), "must be integers"),
    ]:
        _reject(replace(message, packet=bad), match)
    _reject(replace(message, T_WC_previous=torch.zeros(3)), "T_WC_previous")


def test_malformed_frame_done_is_rejected() -> None:
    good = messages.FrameDone(
        agent=0, frame_index=2, timestamp=0.5, outcome="lost", seconds=1, keyframes_waiting=2
    )
    assert decode(encode(good)) == good
    _reject(replace(good, timestamp=float("inf")), "not finite")
    _reject(replace(good, frame_index=-2), ">= 0")


def test_inconsistent_agent_finished_is_rejected() -> None:
    good = messages.AgentFinished(
        agent=0,
        final=None,
        stats=FrontendStats(),
        seconds=0.0,
        applied_seq=0,
        frame_indices=np.arange(3),
        timestamps=np.zeros(3),
        anchors=np.array([0, 0, 1]),
        T_rel=torch.zeros(3, 8),
        keyframe_frames=np.array([0, 2]),
        keyframe_timestamps=np.zeros(2),
        keyframe_T_WC=torch.zeros(2, 8),
    )
    assert identical(good, decode(encode(good)))
    _reject(replace(good, anchors=np.array([0, 0, 2])), "anchors must be keyframe ids")
    _reject(replace(good, T_rel=torch.zeros(2, 8)), "T_rel has shape")
    _reject(replace(good, keyframe_T_WC=torch.zeros(3, 8)), "keyframe_T_WC has shape")
    _reject(replace(good, applied_seq=-1), "applied_seq")
