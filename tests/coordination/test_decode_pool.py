"""Verification on a pool of threads (``verification.workers``, coordination/decode_pool.py):
the coordinator's results are those of verifying in line, bit for bit; a worker's error is
raised in the coordinator's thread."""

from __future__ import annotations

import dataclasses
import json
import threading
from collections.abc import Callable

import pytest
import torch

from como3r.config import Config, apply_overrides
from como3r.coordination.coordinator import Coordinator
from como3r.coordination.decode_pool import VerificationPool
from como3r.errors import ConfigError, PriorError
from como3r.frontend.packets import KeyframePacket
from como3r.prior.simulated import SimulatedPrior

from .ring_keyframes import AGENTS, HEIGHT, SHORT_RUN, WIDTH, ring_keyframes

OVERRIDES = [*SHORT_RUN, "session.encoding_cache=2"]


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> tuple[SimulatedPrior, list[KeyframePacket]]:
    """Three agents on a ring, every second frame a keyframe, interleaved in time; agents 1
    and 2 send encoding records, as a multi-process run does (the coordinator encodes their
    keyframes again, with a cache of 2: re-encodes and evictions)."""
    config = apply_overrides(Config(), OVERRIDES)
    return ring_keyframes(
        tmp_path_factory.mktemp("pool"), config, AGENTS, WIDTH, HEIGHT, portable_from=1
    )


def _run(prior, order: list[KeyframePacket], workers: int, batch: int) -> Coordinator:
    config = apply_overrides(Config(), [*OVERRIDES, f"verification.workers={workers}"])
    coordinator = Coordinator(prior, config, prior.codebook(), AGENTS)
    for start in range(0, len(order), batch):
        coordinator.add_keyframes(order[start : start + batch])
    coordinator.finish()
    return coordinator


def _outcome(coordinator: Coordinator) -> dict:
    """Everything a run writes of the coordinator but its timings and the pool's counts."""
    skipped = {"stage_seconds", "ba_seconds", "cleanup_seconds", "verification_cpu"}
    stats = {
        k: v
        for k, v in dataclasses.asdict(coordinator.stats).items()
        if k not in skipped and not k.startswith("pool_")
    }
    graph = coordinator.graph_document()
    return {"stats": stats, "graph": json.dumps(graph, sort_keys=True, default=str)}


class _Batching(SimulatedPrior):
    """Decodes as a batching prior does (MASt3R: one call for many pairs): the pool then
    verifies a keyframe's candidates in one job, the call the coordinator would make."""

    def decode_pairs(self, pairs):
        return [self.decode(a, b) for a, b in pairs]


@pytest.mark.parametrize(("batch", "batching"), [(1, False), (6, False), (6, True)])
def test_two_workers_give_the_outputs_of_verifying_in_line(
    scene, batch, batching, verifiers
) -> None:
    """Batches of one (a keyframe's pairs side by side) and of six (keyframes ahead, merges
    in between), pair by pair or one job per keyframe: poses, graph document and every
    counter equal; the workers did work."""
    prior, order = scene
    if batching:
        prior = _Batching(prior.config, prior.truth)
    inline = _run(prior, order, 0, batch)
    pooled = _run(prior, order, 2, batch)
    assert pooled.pool.pairwise is not batching
    assert inline.stats.reencodes > 0 and inline.stats.edges_tried > 0
    n = len(order)
    assert torch.equal(inline.graph.poses(range(n)), pooled.graph.poses(range(n)))
    assert _outcome(inline) == _outcome(pooled)
    assert inline.stats.pool_seconds == {} and inline.stats.pool_wasted == 0
    assert pooled.stats.pool_seconds.get("prior_decode", 0.0) > 0
    assert not verifiers()


class _FailingOnThreads(SimulatedPrior):
    """Decodes in the coordinator's thread only; on any other it raises."""

    def decode(self, enc_i, enc_j):
        if threading.current_thread() is not threading.main_thread():
            raise PriorError("decoded on a worker")
        return super().decode(enc_i, enc_j)


def test_a_workers_error_is_raised_in_the_coordinators_thread(scene, verifiers) -> None:
    prior, order = scene
    failing = _FailingOnThreads(prior.config, prior.truth)
    config = apply_overrides(Config(), [*OVERRIDES, "verification.workers=2"])
    coordinator = Coordinator(failing, config, prior.codebook(), AGENTS)
    with pytest.raises(PriorError, match="decoded on a worker"):
        for start in range(0, len(order), 6):
            coordinator.add_keyframes(order[start : start + 6])
    assert not coordinator.pool.active
    coordinator.pool.shutdown()
    assert verifiers() == []


def _all_verifiers() -> set[threading.Thread]:
    return {t for t in threading.enumerate() if t.name.startswith("como3r-verify")}


@pytest.fixture
def verifiers() -> Callable[[], list[threading.Thread]]:
    """The verification threads started during the test: the idle ones of a coordinator
    an earlier test in this process left behind (``benchmarks/coordinator_replay``'s,
    ``test_coordinator``'s) do not count."""
    before = _all_verifiers()
    return lambda: sorted(_all_verifiers() - before, key=lambda t: t.ident or 0)


def test_one_thread_serves_every_batch_until_shutdown(scene, verifiers) -> None:
    """Batches reuse the pool's threads (none is started per batch); shutdown ends them,
    and a batch after it starts them again."""
    prior, _ = scene
    pool = VerificationPool(prior, workers=1)
    config = Config()
    seen = []
    for batch in range(3):
        if batch == 2:
            pool.shutdown()
            assert verifiers() == []
        pool.open([((0, 0), None)])
        pool.submit((0, batch), prior, [], config.matching, 0.5, config.verification)
        done = pool.take((0, batch), [])
        assert done is not None and (done.verifications, done.decodes) == ([], 0)
        assert pool.close() == []
        seen.append(verifiers())
    assert len(seen[0]) == 1 and seen[1] == seen[0] and seen[2] != seen[0]
    pool.shutdown()
    assert verifiers() == []


def test_workers_must_not_be_negative() -> None:
    with pytest.raises(ConfigError, match="verification.workers must be >= 0, got -1"):
        apply_overrides(Config(), ["verification.workers=-1"])
    assert apply_overrides(Config(), ["verification.workers=0"]).verification.workers == 0
