"""Verification on the agents' processes (``verification.on_agents``;
runtime/remote_verification.py): a team run where the agents verify for the coordinator, and
the coordinator's side of it on a scripted hub (replies from the wrong agent, an agent that
leaves with jobs out)."""

from __future__ import annotations

import dataclasses
import json
import logging
import multiprocessing

import pytest

from como3r.config import Config, apply_overrides
from como3r.coordination.coordinator import Coordinator
from como3r.prior.simulated import SimulatedPrior
from como3r.runtime.backlog import Backlog
from como3r.runtime.multiprocess import run_multiprocess
from como3r.runtime.pipeline import PriorSpec
from como3r.runtime.remote_verification import AgentVerifiers
from como3r.runtime.verification_service import serve
from como3r.transport.verification_messages import VerificationDone, VerificationRequest

from ..coordination.ring_keyframes import AGENTS, HEIGHT, SHORT_RUN, WIDTH, ring_keyframes

ON_AGENTS = ["verification.on_agents=true"]


def test_a_team_whose_agents_verify_ends_in_one_map(tiny_scene, tmp_path) -> None:
    """Three agents on a ring verify every candidate the coordinator selects: it encodes
    and decodes nothing itself; each agent served requests, between its frames and after
    its stream; every process ends."""
    scene = tiny_scene(16, 0, 0.5, agents=3)
    config = apply_overrides(Config(), [*SHORT_RUN, *ON_AGENTS])
    out = tmp_path / "out"
    run_multiprocess([scene / f"agent_{a}" for a in range(3)], out, config, PriorSpec("simulated"))
    metrics = json.loads((out / "metrics.json").read_text())
    coordinator, runtime = metrics["coordinator"], metrics["runtime"]
    assert runtime["verification_on_agents"] is True
    served = [a["verification"] for a in runtime["agents"]]
    assert sum(s["requests"] for s in served) == coordinator["remote_verifications"] > 0
    assert all(s["cpu_seconds"] >= s["cpu_seconds_after_stream"] >= 0.0 for s in served)
    assert coordinator["remote_taken_back"] == 0
    assert coordinator["reencodes"] == 0 and coordinator["verification_cpu"] == 0.0
    assert coordinator["remote_decodes"] == coordinator["prior_decodes"] > 0
    assert coordinator["edges_accepted"] > 0 and len(metrics["components"]) == 1
    assert [a["status"] for a in runtime["agents"]] == ["finished"] * 3
    assert [a["exitcode"] for a in runtime["agents"]] == [0] * 3
    assert runtime["bytes_by_type"]["VerificationRequest"] > 0
    assert runtime["bytes_by_type"]["VerificationReply"] > 0
    assert not multiprocessing.active_children()


def test_agents_across_machines_verify_for_their_coordinator(tiny_scene, new_team) -> None:
    """``como3r coordinator`` and two ``como3r agent`` processes over loopback TCP: the
    agents serve the coordinator's requests and end once it releases them."""
    scene = tiny_scene(frames=12, seed=0, overlap=0.5)
    team = new_team("on_agents")
    out = team.tmp / "out"
    team.coordinator(out, 2, "--set", "verification.on_agents=true")
    for agent in range(2):
        team.agent(agent, scene / f"agent_{agent}")
    for name in ("coordinator", "agent0", "agent1"):
        team.wait(name)
    metrics = json.loads((out / "metrics.json").read_text())
    coordinator, runtime = metrics["coordinator"], metrics["runtime"]
    assert runtime["transport"] == "zenoh" and runtime["verification_on_agents"] is True
    served = [a["verification"]["requests"] for a in runtime["agents"]]
    assert sum(served) == coordinator["remote_verifications"] > 0
    assert coordinator["remote_taken_back"] == 0 and coordinator["reencodes"] == 0
    assert len(metrics["components"]) == 1


@pytest.fixture
def delegating(tmp_path, scripted_hub) -> tuple[Coordinator, AgentVerifiers, SimulatedPrior]:
    """A coordinator that left its first jobs to agents 0 and 1 (scripted: nothing runs)."""
    config = apply_overrides(Config(), SHORT_RUN)
    prior, order = ring_keyframes(tmp_path, config, AGENTS, WIDTH, HEIGHT, portable_from=1)
    coordinator = Coordinator(prior, config, prior.codebook(), AGENTS)
    verifiers = AgentVerifiers(coordinator, scripted_hub)
    verifiers.join(0)
    verifiers.join(1)
    for packet in order:
        coordinator.add_keyframes([packet])
        verifiers.dispatch({0: 0, 1: 1, 2: 2})  # agent 2 serves nothing: 0 or 1 does
        if verifiers.out >= 3:
            break
    return coordinator, verifiers, prior


def test_jobs_go_to_their_agent_or_to_one_that_serves(delegating, scripted_hub) -> None:
    coordinator, verifiers, _ = delegating
    requests = [(agent, m) for agent, m in scripted_hub.sent if isinstance(m, VerificationRequest)]
    assert len(requests) == verifiers.out == coordinator.jobs_out >= 3
    for agent, request in requests:
        assert agent == request.query[0] or (request.query[0] == 2 and agent in (0, 1))
    # silent since they were sent their jobs: overdue past a timeout, not before
    assert verifiers.overdue(3600.0) == []
    assert verifiers.overdue(0.0) == sorted({agent for agent, _ in requests})


def test_replies_are_taken_from_the_agent_sent_to_and_handed_over_together(
    delegating, scripted_hub, caplog
) -> None:
    coordinator, verifiers, prior = delegating
    requests = [(agent, m) for agent, m in scripted_hub.sent if isinstance(m, VerificationRequest)]
    agent, request = requests[0]
    reply = serve(agent, prior, coordinator.config, request)
    caplog.set_level(logging.INFO, "como3r.runtime.remote_verification")
    verifiers.received(1 - agent, reply)  # not the agent it was sent to
    assert "it was not sent; dropped" in caplog.text and verifiers.out == len(requests)
    # the same number for another keyframe: a request made before the coordinator resumed
    other = dataclasses.replace(reply, query=(reply.query[0], reply.query[1] + 100))
    verifiers.received(agent, other)
    assert "a request not out" in caplog.text and verifiers.out == len(requests)
    verifiers.received(agent, reply)
    assert verifiers.out == len(requests) - 1 and verifiers.served[agent] == 1
    tried = coordinator.stats.edges_tried
    verifiers.hand_over()
    assert coordinator.stats.remote_verifications == 1
    assert coordinator.stats.edges_tried == tried + len(request.candidates)
    assert verifiers.hand_over() == []  # nothing new


def test_an_agent_that_leaves_has_its_jobs_verified_by_the_coordinator(
    delegating, scripted_hub
) -> None:
    coordinator, verifiers, _ = delegating
    mine = [m for a, m in scripted_hub.sent if a == 0 and isinstance(m, VerificationRequest)]
    assert mine
    verifiers.left(0)
    assert coordinator.stats.remote_taken_back == len(mine)
    assert 0 not in verifiers.serving
    # its next jobs go to agent 1; with no agent serving, they are taken back too
    verifiers.left(1)
    assert verifiers.out == 0 and coordinator.jobs_out == 0
    coordinator.finish()  # the taken-back keyframes verified here
    assert coordinator.stats.verification_deferred_at_finish == coordinator.stats.remote_taken_back
    verifiers.release([0, 1])
    assert not [m for _, m in scripted_hub.sent if isinstance(m, VerificationDone)]  # none serves


def test_a_coordinator_that_trailed_its_team_says_the_agents_can_verify() -> None:
    """More keyframes waiting than one per agent when the input ended: a note names
    ``verification.on_agents``; those of the last moment only, or one agent: none."""
    backlog = Backlog()
    backlog.sample([1.0, 1.1, 1.2], input_ended=True)
    assert backlog.advice(2) is not None and "verification.on_agents=true" in backlog.advice(2)
    assert backlog.advice(3) is None and backlog.advice(1) is None
    assert Backlog().advice(16) is None  # the input has not ended


def test_released_agents_are_told_no_more_requests_come(delegating, scripted_hub) -> None:
    _, verifiers, _ = delegating
    verifiers.release([1, 2])
    stops = [a for a, m in scripted_hub.sent if isinstance(m, VerificationDone)]
    assert stops == [1] and verifiers.serving == {0}
