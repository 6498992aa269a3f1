"""Keyframe encodings the agents do not send: the coordinator encodes the colours again
(coordination/encodings.py), the messages and the session store go without them.

Everything runs MASt3R's own code on its smallest test configuration (TINY_MODEL_STRING,
seeded random weights) at 64x48 on CPU.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from types import SimpleNamespace

import msgpack
import numpy as np
import pytest
import torch

from como3r.config import Config, apply_overrides
from como3r.coordination.coordinator import Coordinator
from como3r.coordination.encodings import KeyframeEncodings
from como3r.data.agent import open_agent
from como3r.data.ground_truth import AgentFolderTruth
from como3r.data.preprocess import upsampling
from como3r.data.synth import synthesize
from como3r.errors import InputError, MessageError
from como3r.frontend.agent import AgentFrontend
from como3r.frontend.keyframes import Keyframe
from como3r.frontend.packets import KeyframePacket
from como3r.prior.base import Encoding, Prior, View, view_from_colors
from como3r.prior.mast3r.prior import MASt3RPrior
from como3r.prior.mast3r.testing import tiny_network
from como3r.prior.retrieval import Hit
from como3r.prior.simulated import SimulatedPrior
from como3r.prior.simulated_record import SimulatedTruthRecord
from como3r.runtime.pipeline import load_frame
from como3r.store.reader import read_session
from como3r.store.writer import SessionStore
from como3r.transport.codec import decode, encode
from como3r.transport.messages import KeyframeMessage

LONG_SIDE = 64


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("encodings_scene")
    synthesize(
        root,
        agents=2,
        seed=0,
        overlap=0.8,
        frames=5,
        preset="default",
        width=64,
        height=48,
        progress=None,
    )
    return root


@pytest.fixture(scope="module")
def config() -> Config:
    return apply_overrides(Config(), [f"input.long_side={LONG_SIDE}"])


@pytest.fixture(scope="module")
def prior() -> MASt3RPrior:
    return MASt3RPrior(tiny_network(seed=0))


@pytest.fixture(scope="module")
def packets(scene: Path, config: Config, prior: MASt3RPrior) -> list[KeyframePacket]:
    """Both agents' keyframe packets from MASt3R front-ends."""
    return _packets(scene, config, prior)


def _packets(scene: Path, config: Config, prior: Prior) -> list[KeyframePacket]:
    """Both agents' keyframe packets from front-ends with ``prior``, interleaved by frame,
    with placeholder retrieval features (the stub retrieval below ignores them)."""
    agents = [open_agent(scene / f"agent_{a}") for a in (0, 1)]
    frontends = [
        AgentFrontend(prior, config, a, None, upsampling(agent.image_size, LONG_SIDE))
        for a, agent in enumerate(agents)
    ]
    out = []
    for index in range(5):
        for a, (agent, frontend) in enumerate(zip(agents, frontends)):
            view, timestamp, colors = load_frame(agent, a, index, LONG_SIDE, False)
            frontend.process(view, timestamp, colors)
            features = (torch.zeros(1, 4), torch.ones(1))
            out += [
                dataclasses.replace(p, retrieval=features) for p in frontend.drain_new_keyframes()
            ]
    for frontend in frontends:  # a short stream's camera settles on the keyframes it has
        frontend.settle_camera()
        out += [
            dataclasses.replace(p, retrieval=(torch.zeros(1, 4), torch.ones(1)))
            for p in frontend.drain_new_keyframes()
        ]
    assert {p.agent for p in out} == {0, 1}
    return out


@pytest.mark.slow  # the MASt3R front-ends' packets: 5-15 s on 2 shared cores
def test_the_colours_give_the_image_and_the_tokens_again_bit_for_bit(
    scene: Path, prior: MASt3RPrior
) -> None:
    agent = open_agent(scene / "agent_1")
    view, _, colors = load_frame(agent, 1, 2, LONG_SIDE, False)
    again = view_from_colors(colors, 1, 2)
    assert torch.equal(again.image, view.image)  # the very image the agent encoded
    first, second = prior.encode(view), prior.encode(again)
    assert torch.equal(first.tokens, second.tokens)
    other = prior.encode(load_frame(agent, 1, 4, LONG_SIDE, False)[0])
    a, b = prior.decode(first, other), prior.decode(second, other)
    for name in ("X_ii", "X_ji", "C_ii", "C_ji", "D_ii", "D_ji", "Q_ii", "Q_ji"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert prior.can_reencode(7)


class _CountingPrior:
    """Encodes a view as its mean colour, counting the calls."""

    def __init__(self, can: bool = True) -> None:
        self.calls, self.can = 0, can

    def can_reencode(self, agent: int) -> bool:
        return self.can

    def encode(self, view: View) -> Encoding:
        self.calls += 1
        return SimpleNamespace(mean=float(view.image.mean()), index=view.index)

    encode_again = Prior.encode_again  # the prior's own: colours to a view to encode


def _keyframe(kf_id: int, encoding: Encoding | None = None, colors=None) -> Keyframe:
    pointmap = torch.ones(4, 6, 3)
    return Keyframe(
        kf_id=kf_id,
        frame_index=10 + kf_id,
        timestamp=0.0,
        encoding=encoding,
        T_WC=torch.zeros(8),
        X_hat=pointmap,
        C_hat=torch.ones(4, 6),
        X_init=pointmap,
        C_init=torch.ones(4, 6),
        colors=np.full((4, 6, 3), kf_id, np.uint8) if colors is None else colors,
    )


def test_the_cache_keeps_the_least_recently_used_re_encodings() -> None:
    prior = _CountingPrior()
    encodings = KeyframeEncodings(prior, capacity=2)
    frames = [_keyframe(k) for k in range(3)]
    first = encodings.get(0, frames[0], 0)
    assert first.index == 10 and encodings.get(0, frames[0], 0) is first
    encodings.get(1, frames[1], 0)
    encodings.get(0, frames[0], 0)  # 0 is now the most recently used
    encodings.get(2, frames[2], 0)  # 1 goes
    assert encodings.cached() == [0, 2] and prior.calls == 3 == encodings.reencodes
    encodings.get(1, frames[1], 0)
    assert prior.calls == 4 and encodings.cached() == [2, 1]
    held = SimpleNamespace()
    assert encodings.get(5, _keyframe(5, encoding=held), 0) is held  # sent: not remade
    assert prior.calls == 4 and encodings.seconds >= 0.0


class _TokenPrior(_CountingPrior):
    """Encodes a view as 256 float32 tokens (1024 bytes)."""

    def encode(self, view: View) -> Encoding:
        self.calls += 1
        return SimpleNamespace(tokens=torch.zeros(256), index=view.index)


def test_the_cache_keeps_its_encodings_within_its_bytes() -> None:
    """``session.encoding_cache_mb``: a heavy prior's encodings fill the byte bound before
    the count; least recently used first out, as under the count."""
    prior = _TokenPrior()
    encodings = KeyframeEncodings(prior, capacity=8, max_bytes=2500)
    frames = [_keyframe(k) for k in range(4)]
    for g in (0, 1, 0, 2):
        encodings.get(g, frames[g], 0)
    assert encodings.cached() == [0, 2] and encodings.held_bytes == 2048 and prior.calls == 3
    encodings.retain({2})
    assert encodings.cached() == [2] and encodings.held_bytes == 1024
    too_small = KeyframeEncodings(prior, capacity=8, max_bytes=1000)
    assert too_small.get(3, frames[3], 0).tokens.numel() == 256
    assert too_small.cached() == [] and too_small.held_bytes == 0
    unbounded = KeyframeEncodings(prior, capacity=8)
    for g in range(4):
        unbounded.get(g, frames[g], 0)
    assert unbounded.cached() == [0, 1, 2, 3] and unbounded.held_bytes == 4096


def test_a_keyframe_that_cannot_be_encoded_again_is_a_clear_error() -> None:
    with pytest.raises(InputError, match="cannot encode it again"):
        KeyframeEncodings(_CountingPrior(can=False), 4).get(0, _keyframe(0), 3)
    small = _keyframe(0, colors=np.zeros((2, 3, 3), np.uint8))
    with pytest.raises(InputError, match="colours of"):
        KeyframeEncodings(_CountingPrior(), 4).get(0, small, 3)
    with pytest.raises(InputError, match="encoding_cache"):
        KeyframeEncodings(_CountingPrior(), -1)
    with pytest.raises(InputError, match="encoding_cache_mb"):
        KeyframeEncodings(_CountingPrior(), 4, -1)


class _AllOthers:
    """Retrieval that offers every keyframe of the other agents (so every new keyframe is
    verified against all of them)."""

    database = SimpleNamespace(codebook_id=None)

    def __init__(self) -> None:
        self.seen: list[tuple[int, int]] = []

    def query_and_add(
        self, agent: int, kf_id: int, features, loops: int = 0, skipped: int = 1
    ) -> list[Hit]:
        hits = [Hit(a, k, 1.0) for a, k in self.seen if a != agent]
        self.seen.append((agent, kf_id))
        return hits


def _coordinate(prior, config, packets) -> Coordinator:
    coordinator = Coordinator(prior, config, None, 2)
    coordinator.retrieval = _AllOthers()
    for packet in packets:
        coordinator.add_keyframe(packet)
    return coordinator


@pytest.mark.slow  # the MASt3R front-ends' packets: 5-15 s on 2 shared cores
def test_a_coordinator_without_tokens_on_the_wire_verifies_and_solves_the_same(
    prior: MASt3RPrior, config: Config, packets: list[KeyframePacket]
) -> None:
    sent = _coordinate(prior, config, packets)
    # as they arrive from agents told not to send encodings, across machines
    received = [
        decode(encode(KeyframeMessage(dataclasses.replace(p, encoding=None), 0, None), lossy=True))
        for p in packets
    ]
    assert all(m.packet.encoding is None for m in received)
    remade = _coordinate(prior, config, [m.packet for m in received])
    assert sent.stats.edges_tried > 0 and sent.stats.reencodes == 0
    assert remade.stats.reencodes > 0 and remade.stats.stage_seconds["reencode"] > 0
    assert remade.stats.reencodes <= len(packets)  # the cache spares repeats
    assert remade.stats.edges_tried == sent.stats.edges_tried
    for a, b in zip(sent.candidates, remade.candidates, strict=True):
        assert (a.i, a.j, a.status) == (b.i, b.j, b.status)
        va, vb = a.verification, b.verification
        assert (va.nu_i, va.nu_j, va.covisible_ratio) == (vb.nu_i, vb.nu_j, vb.covisible_ratio)
    assert torch.equal(
        sent.graph.poses(range(len(sent.graph))), remade.graph.poses(range(len(remade.graph)))
    )


@pytest.mark.slow  # the MASt3R front-ends' packets: 5-15 s on 2 shared cores
def test_an_old_keyframe_message_is_refused_by_its_version(packets) -> None:
    tree = msgpack.unpackb(encode(KeyframeMessage(packets[0], 0, None)), raw=False)
    tree["fields"]["packet"]["version"] = 2
    with pytest.raises(MessageError, match="KeyframePacket version 2 is not the supported"):
        decode(msgpack.packb(tree, use_bin_type=True))


@pytest.mark.slow  # the MASt3R front-ends' packets: 5-15 s on 2 shared cores
def test_the_store_keeps_no_encoding_the_coordinator_can_make_again(
    tmp_path: Path, prior: MASt3RPrior, config: Config, packets: list[KeyframePacket]
) -> None:
    coordinator = Coordinator(prior, config, None, 2)
    with SessionStore.create(tmp_path / "session.db", config, coordinator) as store:
        for packet in packets:
            store.record(coordinator, coordinator.add_keyframe(packet))
        assert store.written["encoding"] == 0
        assert store.load_keyframe(0, "encoding") == {"encoding": None}
    session = read_session(tmp_path / "session.db")
    assert all(kf.encoding is None for kf in session.graph.keyframes)
    for g, kf in enumerate(session.graph.keyframes):  # the colours give the tokens again
        remade = KeyframeEncodings(prior, 0).get(g, kf, session.graph.agent_of[g])
        assert torch.equal(remade.tokens, coordinator.graph.keyframes[g].encoding.tokens)


@pytest.mark.slow  # the MASt3R front-ends' packets: 5-15 s on 2 shared cores
def test_the_store_keeps_an_encoding_the_coordinator_cannot_make(
    tmp_path: Path, prior: MASt3RPrior, config: Config, packets: list[KeyframePacket], monkeypatch
) -> None:
    monkeypatch.setattr(MASt3RPrior, "can_reencode", lambda self, agent: False)
    coordinator = Coordinator(prior, config, None, 2)
    with SessionStore.create(tmp_path / "session.db", config, coordinator) as store:
        store.record(coordinator, coordinator.add_keyframe(packets[0]))
        assert store.written["encoding"] > 0
    (kf,) = read_session(tmp_path / "session.db").graph.keyframes
    assert torch.equal(kf.encoding.tokens, packets[0].encoding.tokens)


def test_the_simulated_priors_record_travels_and_is_stored_in_place_of_its_encoding(
    tmp_path: Path, scene: Path, config: Config
) -> None:
    """Its encoding needs the frame's ground truth, which only the agents have: the record
    of it goes (prior/simulated_record.py), and the coordinator makes the encoding from the
    colours and the record, bit for bit, on the wire and from the store."""
    agents = {a: open_agent(scene / f"agent_{a}") for a in (0, 1)}
    agents_prior = SimulatedPrior(config.simulated_prior, AgentFolderTruth(agents, LONG_SIDE))
    packets = _packets(scene, config, agents_prior)
    sent = _coordinate(agents_prior, config, packets)  # one process: the encodings themselves
    received = [
        decode(encode(KeyframeMessage(replace_encoding(p), 0, None), lossy=True)).packet
        for p in packets
    ]
    assert all(isinstance(p.encoding, SimulatedTruthRecord) for p in received)
    coordinators_prior = SimulatedPrior(config.simulated_prior, None)  # no ground truth
    remade = _coordinate(coordinators_prior, config, received)
    assert sent.stats.edges_tried > 0 and sent.stats.reencodes == 0 < remade.stats.reencodes
    for a, b in zip(sent.candidates, remade.candidates, strict=True):
        assert (a.i, a.j, a.status) == (b.i, b.j, b.status)
    assert torch.equal(
        sent.graph.poses(range(len(sent.graph))), remade.graph.poses(range(len(remade.graph)))
    )
    single = Coordinator(agents_prior, config, None, 2)
    with SessionStore.create(tmp_path / "session.db", config, single) as store:
        for packet in packets:
            store.record(single, single.add_keyframe(packet))
        # the record, not the encoding (at 64x48 a tenth of it at most; 512x384: 1/17)
        full = sum(len(encode(p.encoding)) for p in packets)
        assert 0 < store.written["encoding"] * 10 < full
    session = read_session(tmp_path / "session.db")
    for g, kf in enumerate(session.graph.keyframes):
        assert isinstance(kf.encoding, SimulatedTruthRecord)
        again = KeyframeEncodings(coordinators_prior, 0).get(g, kf, session.graph.agent_of[g])
        held = single.graph.keyframes[g].encoding
        assert torch.equal(again.ranges, held.ranges) and torch.equal(
            again.key_coords, held.key_coords
        )


def replace_encoding(packet: KeyframePacket) -> KeyframePacket:
    """The packet as an agent process sends it (runtime/agent_worker.py)."""
    return dataclasses.replace(packet, encoding=packet.encoding.portable())


def test_a_record_is_encoded_as_its_own_view_whatever_the_agent_is_called_now(
    scene: Path,
) -> None:
    """A merge renumbers the moved session's agents; its encodings keep their own identity
    (the simulated prior seeds an image's draws by it)."""
    agents = {1: open_agent(scene / "agent_1")}
    prior = SimulatedPrior(Config().simulated_prior, AgentFolderTruth(agents, LONG_SIDE))
    view, _, colors = load_frame(agents[1], 1, 2, LONG_SIDE, False)
    made = prior.encode(view)
    pointmap = torch.ones(*view.shape, 3)
    kf = Keyframe(
        kf_id=0,
        frame_index=2,
        timestamp=0.0,
        encoding=made.portable(),
        T_WC=torch.zeros(8),
        X_hat=pointmap,
        C_hat=torch.ones(view.shape),
        X_init=pointmap,
        C_init=torch.ones(view.shape),
        colors=colors,
    )
    again = KeyframeEncodings(SimulatedPrior(Config().simulated_prior), 1).get(0, kf, agent=5)
    assert (again.agent, again.index) == (1, 2)
    assert torch.equal(again.ranges, made.ranges) and torch.equal(
        again.descriptors, made.descriptors
    )
