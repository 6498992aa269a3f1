"""Verification on the agents (``verification.on_agents``, coordination/remote.py and
runtime/remote_verification.py): the jobs a coordinator leaves to agents, served and
answered, give the outputs of verifying in line; jobs no agent answers are verified by the
coordinator itself."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch

from como3r.config import Config, apply_overrides
from como3r.coordination.coordinator import Coordinator
from como3r.coordination.remote import Verified
from como3r.errors import MessageError
from como3r.frontend.packets import KeyframePacket
from como3r.prior.simulated import SimulatedPrior
from como3r.runtime.remote_verification import request_message, verified
from como3r.runtime.verification_service import serve
from como3r.transport import codec
from como3r.transport.messages import FROM_AGENT, TO_AGENT

from .ring_keyframes import AGENTS, HEIGHT, SHORT_RUN, WIDTH, ring_keyframes

#: keyframes one at a time: a job's selection is then made after the edges of every
#: keyframe before it came back, as in line (in a batch, a keyframe's selection does not
#: see the merges of the batch's earlier keyframes: their jobs are still out)
BATCH = 1


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> tuple[SimulatedPrior, list[KeyframePacket]]:
    """The ring of test_decode_pool: agents 1 and 2 send encoding records, agent 0 its
    encodings (a request then carries the record, or the encoding itself)."""
    config = apply_overrides(Config(), SHORT_RUN)
    return ring_keyframes(
        tmp_path_factory.mktemp("remote"), config, AGENTS, WIDTH, HEIGHT, portable_from=1
    )


def _wire(message: object, expected: tuple, lossy: bool) -> object:
    return codec.decode(codec.encode(message, lossy=lossy), expected=expected)


def _answered(coordinator: Coordinator, prior: SimulatedPrior, wire: bool) -> list[Verified]:
    """Every job the coordinator made, served as an agent would (through the codec, as on
    the pipes, where ``wire``)."""
    replies = []
    for job in coordinator.take_jobs():
        request = request_message(coordinator, job)
        if wire:
            request = _wire(request, TO_AGENT, lossy=False)
        reply = serve(request.query[0], prior, coordinator.config, request)
        if wire:
            reply = _wire(reply, FROM_AGENT, lossy=True)
        made = verified(job, reply)
        assert made is not None
        replies.append(made)
    return replies


def _run(prior, order, delegate: bool, wire: bool = False) -> Coordinator:
    coordinator = Coordinator(prior, apply_overrides(Config(), SHORT_RUN), prior.codebook(), AGENTS)
    coordinator.delegate = delegate
    for start in range(0, len(order), BATCH):
        coordinator.add_keyframes(order[start : start + BATCH])
        if delegate:
            coordinator.add_verified(_answered(coordinator, prior, wire))
    coordinator.finish()
    return coordinator


def _outcome(coordinator: Coordinator) -> dict:
    """What a run writes of the coordinator but its timings and where it verified."""
    skipped = {"stage_seconds", "ba_seconds", "cleanup_seconds", "verification_cpu", "reencodes"}
    stats = {
        k: v
        for k, v in dataclasses.asdict(coordinator.stats).items()
        if k not in skipped and not k.startswith(("pool_", "remote_"))
    }
    graph = coordinator.graph_document()
    return {"stats": stats, "graph": json.dumps(graph, sort_keys=True, default=str)}


def test_jobs_answered_at_once_give_the_outputs_of_verifying_in_line(scene) -> None:
    """Each batch's jobs served and handed back before the next batch: poses, graph and
    counters as in line; the coordinator itself encoded and decoded nothing."""
    prior, order = scene
    inline = _run(prior, order, delegate=False)
    remote = _run(prior, order, delegate=True)
    n = len(order)
    assert inline.stats.edges_accepted > 0 and inline.stats.reencodes > 0
    assert torch.equal(inline.graph.poses(range(n)), remote.graph.poses(range(n)))
    assert _outcome(inline) == _outcome(remote)
    stats = remote.stats
    assert stats.remote_verifications > 0 and stats.remote_taken_back == 0
    assert stats.remote_decodes == stats.prior_decodes == inline.stats.prior_decodes
    assert stats.reencodes == 0 and stats.verification_cpu == 0.0
    assert stats.remote_seconds["prior_decode"] > 0 and remote.jobs_out == 0


def test_through_the_wire_the_same_edges_and_nearly_the_same_poses(scene) -> None:
    """The matches travel in the session store's coding of inter-agent edges (their
    confidences quantised): the same edges are accepted, the poses move by little."""
    prior, order = scene
    inline = _run(prior, order, delegate=False)
    remote = _run(prior, order, delegate=True, wire=True)
    n = len(order)
    for name in ("edges_tried", "edges_verified", "edges_accepted", "gauge_syncs", "loop_links"):
        assert getattr(remote.stats, name) == getattr(inline.stats, name), name
    positions = inline.graph.poses(range(n))[:, :3], remote.graph.poses(range(n))[:, :3]
    extent = float((positions[0] - positions[0].mean(0)).norm(dim=1).max())
    # measured 3.7e-4 of the scene's extent
    assert float((positions[0] - positions[1]).norm(dim=1).max()) < 1e-3 * extent


def test_jobs_no_agent_answers_are_kept_and_verified_here(scene) -> None:
    """Jobs still out are stored as deferred keyframes (a resumed run verifies them); taken
    back (their agent gone) or at the end, the coordinator verifies them itself."""
    prior, order = scene
    inline = _run(prior, order, delegate=False)
    coordinator = Coordinator(prior, apply_overrides(Config(), SHORT_RUN), prior.codebook(), AGENTS)
    coordinator.delegate = True
    half = len(order) // 2
    coordinator.add_keyframes(order[:half])
    jobs = coordinator.take_jobs()
    assert jobs and coordinator.jobs_out == len(jobs)
    stored = coordinator.deferred_keyframes()
    assert [(a, k) for a, k, _ in stored] == [job.query for job in jobs]
    coordinator.take_back(jobs[0].request)
    assert coordinator.jobs_out == len(jobs) - 1
    coordinator.add_keyframes(order[half:])  # these jobs too stay out until the end
    coordinator.finish()
    stats = coordinator.stats
    assert stats.remote_verifications == 0 and coordinator.jobs_out == 0
    assert stats.remote_taken_back == stats.verification_deferred_at_finish > len(jobs)
    assert stats.edges_accepted > 0
    assert len(coordinator.components()) == len(inline.components())


def test_a_reply_for_another_request_is_ignored(scene, caplog) -> None:
    prior, order = scene
    coordinator = Coordinator(prior, apply_overrides(Config(), SHORT_RUN), prior.codebook(), AGENTS)
    coordinator.delegate = True
    assert coordinator.add_verified([Verified(7, [], 0)]) == []
    assert "request 7 that is not out" in caplog.text


def test_a_request_without_an_image_of_its_keyframes_is_refused(scene) -> None:
    prior, order = scene
    coordinator = Coordinator(prior, apply_overrides(Config(), SHORT_RUN), prior.codebook(), AGENTS)
    coordinator.delegate = True
    for start in range(0, len(order), BATCH):
        coordinator.add_keyframes(order[start : start + BATCH])
        jobs = coordinator.take_jobs()
        if jobs:
            break
    request = request_message(coordinator, jobs[0])
    broken = dataclasses.replace(request, images=request.images[1:])
    with pytest.raises(MessageError, match="needs its image"):
        _wire(broken, TO_AGENT, lossy=False)
