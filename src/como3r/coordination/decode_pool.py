"""The coordinator's verification work on a pool of threads (issue 41, "Teams of sixteen").

A centralized coordinator falls further behind as its team grows (``benchmarks/
team_scale.py``: at 16 agents its one core is about 11x short); of its in-stream work the
prior decodes of verification, the re-encodes of keyframes that came without their
encodings and the matching of the decoded pairs (about 70 %) depend on nothing but the
pair's two encodings. :class:`VerificationPool` runs them ahead on
``verification.workers`` threads while the coordinator's own thread keeps every decision:
which hits a keyframe verifies (its budget, which depends on the gauge merges before it),
whether a batch budget skips it, what is admitted and merged, all in the order they were
made with no pool. Torch releases the interpreter lock inside its kernels (the
precedent: :mod:`como3r.runtime.prefetch`), so the threads use several cores.

How (:mod:`.linking` drives it):

1. When the coordinator starts verifying a keyframe of a batch, it predicts, with the gauge
   components as they are then, the candidates of the next ``2 * workers`` keyframes and
   submits their verifications (:func:`~.association.verify_candidates`, the very call the
   coordinator would make), and those of the current keyframe but its first chunk, which
   it verifies itself meanwhile. A chunk is one candidate pair where the prior decodes pair
   by pair (the base class's :meth:`~como3r.prior.base.Prior.decode_pairs`: the simulated
   prior), so a keyframe's candidates are verified side by side even in a batch of one;
   where the prior batches its decodes (MASt3R: one decoder call per image size, whose
   floats may depend on the batch) it is the keyframe's whole candidate list, so that every
   decode is the one the coordinator would have made.
2. The coordinator then takes a chunk's result (waiting for it, or re-raising what the
   worker raised) when its own selection is the predicted one, and verifies in line what
   was not predicted. A merge between prediction and use changes a keyframe's selection:
   the work done for the prediction is wasted, counted in ``pool_wasted`` and
   ``pool_wasted_decodes`` of the statistics (cancelled before it started, it costs nothing).
3. A keyframe's encoding made again from its colours (:mod:`.encodings`) is made once per
   batch by whichever thread needs it first (:meth:`VerificationPool.encoding`) and handed
   to the coordinator's cache in the order it asks for it, so the cache, its counts and
   every output are those of a run with no pool.

Outputs are bit for bit those of ``workers = 0`` (tests/coordination/test_decode_pool.py).
Work is accounted in thread CPU time: each job's re-encodes, decodes and the rest of its
verification (matching) go to ``pool_seconds`` by stage; what the coordinator's thread
verifies itself to ``verification_cpu``; the pool's waits are no one's CPU. The prior's
caches are filled on first use with values that depend on their key alone (the simulated
prior's texture embeddings, MASt3R's rotary tables): a race computes one twice, the same;
MASt3R enters its no-grad and autocast modes, which are per thread, inside its own calls.
"""

from __future__ import annotations

import concurrent.futures as futures
import logging
import threading
import time
from collections import Counter
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass, field
from typing import Any

from como3r.config import MatchingConfig, VerificationConfig
from como3r.coordination.association import Verification, verify_candidates
from como3r.prior.base import Encoding, PairPrediction, Prior
from como3r.prior.retrieval import Hit

logger = logging.getLogger(__name__)

#: an encoding the coordinator holds, or ``(global index, how to make it again)``
Source = Encoding | tuple[int, Callable[[], Encoding]]


@dataclass
class Done:
    """A chunk verified on the pool.

    Attributes:
        verifications: one per candidate of the chunk, in its order.
        decodes: ordered pairs the prior decoded for it.
        seconds: the worker's thread CPU seconds by stage (``reencode``, ``prior_decode``,
            ``verification``: the rest, the matching).
    """

    verifications: list[Verification]
    decodes: int
    seconds: dict[str, float] = field(default_factory=dict)


class _Made:
    """One keyframe's encoding, made once by the first thread that needs it."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.encoding: Encoding | None = None


class _Worker(threading.local):
    """The current job's thread CPU seconds of re-encodes (per thread)."""

    reencode = 0.0


class CountingPrior:
    """The prior as a job calls it: its decodes counted and timed in thread CPU seconds
    (the coordinator's :class:`~como3r.frontend.timing.TimedPrior` keeps one stage stack,
    which two threads must not share). Every other attribute is the prior's."""

    def __init__(self, prior: Prior) -> None:
        self._prior = prior
        self.decodes = 0
        self.seconds = 0.0

    def __getattr__(self, name: str) -> Any:
        return getattr(self._prior, name)

    def decode_pairs(self, pairs: Sequence[tuple[Encoding, Encoding]]) -> list[PairPrediction]:
        self.decodes += len(pairs)
        start = time.thread_time()
        try:
            return self._prior.decode_pairs(pairs)
        finally:
            self.seconds += time.thread_time() - start


class VerificationPool:
    """Verifications run ahead on ``workers`` threads for one batch at a time.

    The threads serve every batch: started with the first batch that submits work and ended
    by :meth:`shutdown` (the coordinator's :meth:`~.coordinator.Coordinator.finish`), or
    when the pool is collected; a batch after :meth:`shutdown` starts them again. (An
    executor per batch started and joined its threads each time: 0.23-0.43 ms of process
    CPU and 0.7-1.9 ms of wall time more per batch at 2 to 4 workers, with empty jobs;
    small beside a batch's verifications, but paid on the coordinator's thread.)

    Args:
        prior: the coordinator's prior (unwrapped: its decodes are timed per job); None for
            a coordinator that decodes nothing (no threads).
        workers: threads; 0 verifies everything in line and starts none.

    Attributes:
        pairwise: chunks are single candidate pairs (the prior decodes pair by pair).
    """

    def __init__(self, prior: Prior | None, workers: int) -> None:
        self.prior = prior
        self.workers = workers if prior is not None else 0
        self.pairwise = getattr(type(prior), "decode_pairs", None) is Prior.decode_pairs
        self._executor: futures.ThreadPoolExecutor | None = None
        self._open = False  # a batch is open on the threads
        self._jobs: dict[Hashable, tuple[futures.Future[Done], list[int]]] = {}
        self._needs: Counter[int] = Counter()
        self._made: dict[int, _Made] = {}
        self._lock = threading.Lock()
        self._local = _Worker()
        self._plan: list[Any] = []
        self._position: dict[Hashable, int] = {}
        self._submitted = 0

    @property
    def active(self) -> bool:
        """Whether a batch is open on threads."""
        return self._open

    def open(self, plan: Sequence[tuple[Hashable, Any]]) -> None:
        """Start a batch: ``plan`` is its keyframes in the order they will be verified, each
        ``(key, item)`` (the item is what :meth:`due` hands back)."""
        self.close()
        if self.workers <= 0 or not plan:
            return
        self._plan = [item for _, item in plan]
        self._position = {key: n for n, (key, _) in enumerate(plan)}
        self._submitted = 0
        self._open = True

    def due(self, key: Hashable) -> list[tuple[bool, Any]]:
        """The plan's items to submit now that keyframe ``key`` is being verified: itself
        (``True``: the current one) and those up to ``2 * workers`` after it not yet
        submitted, in order. Nothing when no batch is open or ``key`` is not in it."""
        if not self.active or key not in self._position:
            return []
        here = self._position[key]
        start, stop = max(here, self._submitted), min(len(self._plan), here + 1 + 2 * self.workers)
        self._submitted = max(self._submitted, stop)
        return [(n == here, self._plan[n]) for n in range(start, stop)]

    def submit(
        self,
        query: tuple[int, int],
        query_source: Source,
        candidates: Sequence[tuple[Hit, Source]],
        matching: MatchingConfig,
        q_min: float,
        verification: VerificationConfig,
    ) -> None:
        """Verify ``candidates`` with keyframe ``query`` on a worker (the arguments of
        :func:`~.association.verify_candidates`, encodings perhaps still to make)."""
        key = (query, tuple(hit for hit, _ in candidates))
        if not self._open or key in self._jobs:
            return
        if self._executor is None:
            self._executor = futures.ThreadPoolExecutor(self.workers, "como3r-verify")
        needs = [s[0] for _, s in candidates if isinstance(s, tuple)]
        if isinstance(query_source, tuple):
            needs.append(query_source[0])
        with self._lock:
            for g in needs:
                self._made.setdefault(g, _Made())
        self._needs.update(needs)

        def job() -> Done:
            start = time.thread_time()
            self._local.reencode = 0.0
            prior = CountingPrior(self.prior)  # type: ignore[arg-type]
            verifications = verify_candidates(
                prior,  # type: ignore[arg-type]
                query,
                self._resolve(query_source),
                [(hit, self._resolve(source)) for hit, source in candidates],
                matching,
                q_min,
                verification,
            )
            total, reencode = time.thread_time() - start, self._local.reencode
            seconds = {
                "reencode": reencode,
                "prior_decode": prior.seconds,
                "verification": max(0.0, total - reencode - prior.seconds),
            }
            return Done(verifications, prior.decodes, seconds)

        self._jobs[key] = (self._executor.submit(job), needs)

    def take(self, query: tuple[int, int], hits: Sequence[Hit]) -> Done | None:
        """The pool's verification of ``hits`` with ``query`` (waiting for it; what its
        worker raised is raised here), or None where none was submitted."""
        entry = self._jobs.pop((query, tuple(hits)), None)
        if entry is None:
            return None
        job, needs = entry
        self._needs.subtract(needs)
        return job.result()

    def encoding(self, g: int, make: Callable[[], Encoding]) -> Encoding:
        """Global keyframe ``g``'s encoding made again: shared with the batch's other
        threads (made once, by whichever asks first; the others wait for it)."""
        with self._lock:
            made = self._made.setdefault(g, _Made()) if self.active else None
        if made is None:
            return make()
        with made.lock:
            if made.encoding is None:
                start = time.thread_time()
                made.encoding = make()
                self._local.reencode += time.thread_time() - start
            return made.encoding

    def prune(self) -> None:
        """Let go of the made encodings no job still waiting to be taken needs (the
        coordinator's own cache keeps those it keeps)."""
        with self._lock:
            for g in [g for g in self._made if self._needs[g] <= 0]:
                del self._made[g]
        self._needs = +self._needs

    def close(self) -> list[Done]:
        """End the batch: cancel the jobs not started and wait for the running ones;
        returns those that ran and were not taken (wasted; one that failed is logged)."""
        if not self._open:
            return []
        self._open = False
        for job, _ in self._jobs.values():
            job.cancel()
        futures.wait([job for job, _ in self._jobs.values()])  # every job taken is done
        wasted = []
        for job, _ in self._jobs.values():
            if job.cancelled():
                continue
            error = job.exception()
            if error is None:
                wasted.append(job.result())
            else:
                logger.debug("coordinator: a verification run ahead failed: %s", error)
        self._jobs.clear()
        self._needs.clear()
        self._made.clear()
        self._plan, self._position = [], {}
        return wasted

    def shutdown(self) -> None:
        """End the batch (:meth:`close`) and the threads; a later batch starts new ones."""
        self.close()
        executor, self._executor = self._executor, None
        if executor is not None:
            executor.shutdown(wait=True)

    def _resolve(self, source: Source) -> Encoding:
        if isinstance(source, tuple):
            return self.encoding(*source)
        return source
