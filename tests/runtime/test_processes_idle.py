"""The multi-process coordinator's loop (runtime/processes.py) verifies the keyframes a
batch budget deferred (coordination/deferral.py) while it is idle: one per turn of its
loop in which no keyframe waits for its turn, the updates sent to the agents and applied
to their results; never while a keyframe waits."""

from __future__ import annotations

from types import SimpleNamespace

import torch

from como3r.config import Config, apply_overrides
from como3r.frontend.packets import PoseUpdate
from como3r.runtime.agent_events import RuntimeOptions
from como3r.runtime.pipeline import PriorSpec
from como3r.transport.links import Left, Received
from como3r.transport.messages import (
    AgentStarted,
    FrameDone,
    KeyframeMessage,
    PoseUpdateMessage,
)

IDENTITY = torch.tensor([0.0, 0, 0, 0, 0, 0, 1, 1])
MOVED = torch.tensor([[1.0, 0, 0, 0, 0, 0, 1, 1]])  # one metre along x


def test_an_idle_runtime_verifies_deferred_keyframes_and_sends_their_updates(
    scripted_hub,
) -> None:
    """Agent 0's keyframe waits until agent 1 reports a later frame; only then, with no
    keyframe waiting, does the loop ask the coordinator for a deferred verification, whose
    update goes to agent 0 and moves its result's keyframe. The agents then leave and the
    run ends (the coordinator's batches and cleanup are stand-ins: the loop is tested)."""
    from como3r.runtime.processes import _Runtime

    hub = scripted_hub
    config = apply_overrides(Config(), ["input.long_side=64"])
    runtime = _Runtime(hub, [0, 0], config, PriorSpec("simulated"), RuntimeOptions(), None)
    runtime.start([None, None], PriorSpec("simulated"))
    packet = SimpleNamespace(agent=0, kf_id=0, timestamp=1.0, frame_index=30, T_WC=IDENTITY)
    turns = [  # what the transport brings at each turn of the loop
        [
            Received(0, AgentStarted(agent=0, pid=1, frames=4)),
            Received(1, AgentStarted(agent=1, pid=2, frames=4)),
            Received(0, KeyframeMessage(packet, 0, None)),  # waits for agent 1's clock
        ],
        [],  # it still waits
        [Received(1, FrameDone(1, 3, 1.5, "tracked", 0.0, 0))],  # its turn: taken
        [],
        [Left(0, "stopped", may_return=False), Left(1, "stopped", may_return=False)],
    ]
    turn = 0

    def events(timeout: float) -> list:
        nonlocal turn
        turn += 1
        return turns[turn - 1] if turn <= len(turns) else []

    hub.events = events
    taken: list[tuple[int, int]] = []

    def add_keyframes(batch, solve=True) -> None:  # the batch's coordinator work, a stand-in
        for waiting in batch:
            message, _ = waiting.message()
            taken.append((turn, message.packet.kf_id))
            view = SimpleNamespace(T_WC=message.packet.T_WC.clone())
            waiting.segment.result.keyframes.append(view)

    asked: list[tuple[int, int]] = []  # (turn, keyframes waiting) at each ask
    deferred = [PoseUpdate(agent=0, kf_ids=torch.tensor([0]), T_WC=MOVED, reason="global_ba")]

    def verify_deferred_one() -> list[PoseUpdate]:
        asked.append((turn, len(runtime.pending)))
        return [deferred.pop()] if deferred else []

    runtime._add_keyframes = add_keyframes
    runtime.coordinator.verify_deferred_one = verify_deferred_one
    runtime.coordinator.finish = lambda final_poses, progress: SimpleNamespace(updates=[])
    runtime.run(torch.get_num_threads())

    assert taken == [(3, 0)]
    assert asked and all(waiting == 0 and at >= 3 for at, waiting in asked)
    assert asked[0][0] == 3  # the turn that emptied the queue
    [(agent, message)] = hub.sent
    assert agent == 0 and isinstance(message, PoseUpdateMessage) and message.seq == 1
    assert torch.equal(message.update.T_WC, MOVED)
    segment = runtime.segments[0]
    assert segment.sent_seq == 1 and len(segment.updates) == 1
    assert torch.equal(segment.result.keyframes[0].T_WC, MOVED[0])
