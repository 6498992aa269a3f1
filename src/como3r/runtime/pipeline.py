"""Running como3r on agent inputs, end to end, in one process.

``run`` opens and validates every agent input first (so bad input fails before any work),
builds the prior, feeds the agents' frames to their frame loops
(:class:`~como3r.runtime.agent_loop.AgentLoop`, an agent process's too) interleaved by
timestamp (as concurrent robots would deliver them; live inputs' frames as they arrive)
and, as a loop hands out an agent's new keyframe, gives it to the coordinator and applies
the pose updates it returns to the agents (C-Sec. 3.1, A.8). At the end it sends each
agent's last fused pointmap, runs the coordinator's terminal pose-depth alternation, writes
the output folder atomically and, where ground truth exists, evaluates the trajectories
(merged ATE only within gauge components). The coordinator's state is kept in the output
folder's session store as it changes (:mod:`como3r.store.writer`). A first Ctrl-C or
SIGTERM stops reading recorded inputs after the frame at hand and keeps ``OUT.partial`` for
``--resume`` (:mod:`.interrupts`); on live inputs it ends the streams and the outputs are
written.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import heapq
import logging
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from como3r.config import Config
from como3r.data.agent import open_agent
from como3r.data.agent_input import AgentInput
from como3r.data.preprocess import make_view, upsampling
from como3r.data.readers.camera import (
    CameraInput,
    CameraSource,
    camera_schedule,
    interrupt_ends_streams,
    open_camera,
)
from como3r.errors import InputError
from como3r.frontend.agent import AgentFrontend
from como3r.frontend.packets import KeyframePacket, PointmapRefresh, PoseUpdate
from como3r.io.output import atomic_output_dir
from como3r.live import LiveCallback
from como3r.prior.base import Prior, View
from como3r.progress import AgentProgress, PhaseCallback, ProgressCallback, tracking_state
from como3r.runtime.agent_loop import AgentLoop
from como3r.runtime.ingest import hold_the_coordinators, received
from como3r.runtime.interrupts import checkpoint, finishing, interrupts_are_checkpoints
from como3r.runtime.prefetch import prepared_frames

# the coordinator's side is imported where ``run`` uses it: an agent's process imports this
# module for its prior and frames only, and the back-end's imports cost it ~0.5 s CPU
if TYPE_CHECKING:
    from como3r.coordination.coordinator import Coordinator
    from como3r.runtime.live import CoordinatorLive
    from como3r.runtime.map_session import SavedMap
    from como3r.runtime.results import AgentResult
    from como3r.store.writer import SessionStore

logger = logging.getLogger(__name__)

PRIORS = ("simulated", "mast3r")


@dataclass(frozen=True)
class PriorSpec:
    """Which prior to build and from which files.

    Attributes:
        name: ``"mast3r"`` or ``"simulated"`` (no default: the stand-in is chosen explicitly).
        weights: MASt3R checkpoint (``mast3r`` only); None takes all three files from the
            weights cache (:func:`resolve_weights`).
        retrieval_weights: MASt3R retrieval checkpoint (``..._retrieval_trainingfree.pth``).
        codebook: ASMK codebook ``.pkl`` for the MASt3R retrieval.
        device: ``"cpu"`` or ``"cuda"``.
        precision: MASt3R compute precision ``auto|fp32|bf16|fp16`` (the simulated prior
            ignores it).
    """

    name: str
    weights: Path | None = None
    retrieval_weights: Path | None = None
    codebook: Path | None = None
    device: str = "cpu"
    precision: str = "auto"


@dataclass
class RunSummary:
    """What a run did, for the command line's final table."""

    out: Path
    agents: list[dict[str, object]] = field(default_factory=list)
    evaluation: object | None = None
    notes: list[str] = field(default_factory=list)


def resolve_weights(spec: PriorSpec) -> PriorSpec:
    """The spec with every MASt3R file not given taken from the weights cache
    (:mod:`como3r.prior.weights`).

    Without ``weights`` all three files come from the cache. With ``weights`` given, the
    retrieval files are only those given (the cached ones belong to the official
    checkpoint); without them retrieval is off. A codebook not given is the one beside the
    retrieval checkpoint, as in the official code, else the cached one.

    Raises:
        InputError: a file missing from the cache (one line naming ``como3r weights fetch``).
    """
    if spec.name != "mast3r":
        return spec
    from como3r.prior.mast3r.retrieval import codebook_path_for
    from como3r.prior.weights import cached_file

    weights, retrieval = spec.weights, spec.retrieval_weights
    if weights is None:
        weights = cached_file("checkpoint")
        retrieval = retrieval or cached_file("retrieval")
    codebook = spec.codebook
    if codebook is None and retrieval is not None:
        beside = codebook_path_for(retrieval)
        codebook = beside if beside.is_file() else cached_file("codebook")
    return dataclasses.replace(
        spec, weights=weights, retrieval_weights=retrieval, codebook=codebook
    )


def build_prior(
    spec: PriorSpec,
    config: Config,
    agents: Mapping[int, AgentInput] | None = None,
    quiet: bool = False,
) -> tuple[Prior, np.ndarray | None]:
    """The prior and its retrieval codebook (None when retrieval is unavailable); MASt3R
    files not in ``spec`` come from the weights cache (:func:`resolve_weights`).

    Args:
        spec: which prior.
        config: the run's configuration.
        agents: agent id -> input whose frames this prior encodes; the simulated prior reads
            its ground truth there (None: it only decodes, as a coordinator's does).
        quiet: do not warn that retrieval is off (an agent process: the coordinator's
            prior, built from the same spec, warns once for the run).
    """
    if spec.name == "simulated":
        from como3r.data.ground_truth import AgentFolderTruth
        from como3r.prior.simulated import SimulatedPrior

        truth = None if agents is None else AgentFolderTruth(agents, config.input.long_side)
        prior = SimulatedPrior(config.simulated_prior, truth)
        return prior, prior.codebook()
    if spec.name == "mast3r":
        from como3r.prior.mast3r import load_mast3r

        spec = resolve_weights(spec)
        prior = load_mast3r(spec.weights, device=spec.device, dtype=spec.precision)
        if spec.retrieval_weights is None:
            if not quiet:
                logger.warning("no --retrieval-weights: loop closure and retrieval are disabled")
            return prior, None
        from como3r.prior.mast3r.retrieval import load_retrieval_head
        from como3r.prior.retrieval import load_codebook

        prior.retrieval = load_retrieval_head(spec.retrieval_weights, device=spec.device)
        return prior, load_codebook(spec.codebook)
    raise InputError(f"unknown prior {spec.name!r}; choose one of {', '.join(PRIORS)}")


def open_agents(
    paths: Sequence[Path | CameraSource], config: Config, cameras: bool = False
) -> list[AgentInput] | list[CameraInput]:
    """Open and validate every agent input before any work starts; with ``cameras``, the
    live inputs of :mod:`como3r.data.readers.camera` too (they start reading).

    Raises:
        InputError: a bad input, live inputs mixed with recorded ones, or live inputs
            without ``cameras`` (they run in one process: ``--single-process``).
    """
    if not paths:
        raise InputError("no --agent given")
    live = [p for p in paths if isinstance(p, CameraSource)]
    if not live:
        return [
            open_agent(
                p,
                fps=config.input.frame_rate_hz,
                format=config.input.format,
                topic=config.input.topic,
            )
            for p in paths
        ]
    if not cameras:
        raise InputError(f"{live[0]}: live inputs run in one process (--single-process)")
    if len(live) < len(paths):
        raise InputError("a run takes recorded inputs (--agent) or live ones (--camera), not both")
    opened: list[CameraInput] = []
    try:
        for source in live:
            opened.append(open_camera(source, config.input.frame_rate_hz))
    except InputError:
        for camera in opened:
            camera.stop()
        raise
    return opened


def run_frames(source: AgentInput, stride: int, prior: str, start: int = 0) -> np.ndarray:
    """``(M,)`` int64 indices of the frames an agent's loop is fed: every ``stride``-th
    frame counted from frame 0, from ``start`` on; with the simulated prior, only those it
    can encode (:func:`como3r.data.ground_truth.encodable`). The frames keep their indices
    and timestamps."""
    frames = np.arange(0, source.num_frames, stride, dtype=np.int64)
    frames = frames[frames >= start]
    if prior == "simulated":
        from como3r.data.ground_truth import encodable

        frames = frames[encodable(source)[frames]]
    return frames


def warn_skipped_frames(agents: Sequence[AgentInput], prior: str) -> None:
    """One warning per input some of whose frames the simulated prior cannot encode and
    :func:`run_frames` skips, counting them."""
    if prior != "simulated":
        return
    from como3r.data.ground_truth import skipped_warning

    for agent in agents:
        line = skipped_warning(agent)
        if line is not None:
            logger.warning("%s", line)


def _frame_schedule(
    agents: Sequence[AgentInput], frames: Sequence[np.ndarray]
) -> Iterator[tuple[int, int]]:
    """``(agent, frame index)`` of every agent's ``frames`` (:func:`run_frames`), by
    timestamp."""
    heap = [
        (float(a.timestamps[f[0]]), k, 0) for k, (a, f) in enumerate(zip(agents, frames)) if len(f)
    ]
    heapq.heapify(heap)
    while heap:
        _, k, n = heapq.heappop(heap)
        yield k, int(frames[k][n])
        if n + 1 < len(frames[k]):
            heapq.heappush(heap, (float(agents[k].timestamps[frames[k][n + 1]]), k, n + 1))


def load_frame(
    source: AgentInput, agent: int, index: int, long_side: int, calibrated: bool
) -> tuple[View, float, np.ndarray]:
    """Frame ``index`` of agent ``agent``'s input pre-processed: ``(view, timestamp,
    colors)``; the folder's intrinsics go into the view only in a ``calibrated`` run."""
    frame = source.load_frame(index)
    view = make_view(frame, agent, long_side, source.calib if calibrated else None)
    return view, frame.timestamp, _colors(view)


def _colors(view: View) -> np.ndarray:
    """``(H, W, 3)`` uint8 image of a view at network resolution."""
    image = ((view.image.permute(1, 2, 0) + 1.0) * 127.5).round().clamp(0, 255)
    return image.to(torch.uint8).numpy()


def run(
    agent_paths: Sequence[Path],
    out: Path,
    config: Config,
    prior_spec: PriorSpec,
    overwrite: bool = False,
    progress: ProgressCallback | None = None,
    live: LiveCallback | None = None,
    resume: bool = False,
    saved_map: SavedMap | None = None,
) -> RunSummary:
    """Run all agents' front-ends and the coordinator, and write the output folder.

    Args:
        agent_paths: one agent input per agent, in agent order: paths, or live inputs
            (:class:`~como3r.data.readers.camera.CameraSource`; all of them), whose frames
            come as they arrive, the newest kept, until every stream ends.
        out: output folder (created atomically).
        config: effective configuration.
        prior_spec: which prior to use.
        overwrite: replace an existing non-empty output folder.
        progress: called with the agent's :class:`~como3r.progress.AgentProgress` after
            every frame and with a :class:`~como3r.progress.PhaseEvent` as each step of
            the terminal work starts.
        live: called with the live events of :mod:`como3r.live` (a viewer); they are only
            built when it is given.
        resume: continue the killed run in ``out.partial`` from its session store
            (:mod:`como3r.store.resume`; the agents start again from the beginning).
        saved_map: a finished run's map to start from (``--map``, :mod:`.map_session`): its
            agents keep their ids, the new ones are numbered after them, the outputs hold
            them all; without ground truth for the saved agents, nothing is evaluated.
    """
    from como3r.coordination.coordinator import Coordinator
    from como3r.runtime.disk_guard import DiskGuard
    from como3r.runtime.live import CoordinatorLive
    from como3r.runtime.map_session import hold_map, map_results, seed_map
    from como3r.store.reader import resumable
    from como3r.store.resume import open_store

    agents = open_agents(agent_paths, config, cameras=True)
    first = 0 if saved_map is None else saved_map.agents  # the id of the first new agent
    prior, codebook = build_prior(
        prior_spec, config, {first + k: agent for k, agent in enumerate(agents)}
    )
    frontends = [
        AgentFrontend(
            prior, config, first + k, codebook, upsampling(agent.image_size, config.input.long_side)
        )
        for k, agent in enumerate(agents)
    ]
    coordinator = Coordinator(prior, config, codebook, first + len(agents))
    saved = [] if saved_map is None else map_results(saved_map)
    if saved_map is not None and not resume:
        seed_map(coordinator, saved_map)
    results = [*saved, *frontends]  # by agent id
    coordinator_live = (
        None
        if live is None
        else CoordinatorLive(live, coordinator, config.visualization.map_min_confidence)
    )
    hand_over = functools.partial(_hand_over, results, coordinator, coordinator_live)
    loops = [AgentLoop(frontend, hand_over, live) for frontend in frontends]
    cameras = [a for a in agents if isinstance(a, CameraInput)]
    selected = (
        [] if cameras else [run_frames(a, config.input.subsample, prior_spec.name) for a in agents]
    )
    if not cameras:
        warn_skipped_frames(agents, prior_spec.name)
    totals = [a.source.max_frames for a in cameras] if cameras else [len(f) for f in selected]
    frames = prepared_frames(
        camera_schedule(cameras) if cameras else _frame_schedule(agents, selected),
        lambda k, i: load_frame(agents[k], first + k, i, config.input.long_side, config.calibrated),
        prior,
        config.input.prefetch_frames,
    )
    # recorded inputs: the first Ctrl-C or SIGTERM stops the run between two frames, and
    # OUT.partial is kept for --resume; a live run's store cannot be resumed
    checkpoints = contextlib.nullcontext() if cameras else interrupts_are_checkpoints()
    kept = None if cameras else resumable
    guard = DiskGuard(config.session.disk_reserve_mb, progress)
    with (
        checkpoints,
        atomic_output_dir(out, overwrite=overwrite, resume=resume, kept=kept) as staging,
        open_store(staging, config, coordinator, resume) as store,
        contextlib.closing(frames),
        contextlib.ExitStack() as streams,
    ):
        guard.watch(store)  # from here a disk filling up stops the run, resumably
        if saved_map is not None:
            hold_map(coordinator, saved_map)
            store.record_runtime(None, {r.agent: r.finished for r in saved if r.finished})
        for camera in cameras:  # the live streams end on an error too
            streams.callback(camera.stop)
        if cameras:  # the first Ctrl-C ends them, and the run goes on to its outputs
            streams.enter_context(interrupt_ends_streams())
        while True:  # until every input ends (a live stream's length is not known)
            checkpoint()  # the store holds every keyframe handed over so far
            start = time.perf_counter()
            frame = next(frames, None)
            if frame is None:
                break
            k = frame.agent
            step = loops[k].step(frame, start)
            stats = frontends[k].stats
            guard.progress(  # the disk guard counts the input left; it calls progress
                AgentProgress(
                    first + k,
                    stats.frames,
                    totals[k],
                    len(frontends[k].keyframes),
                    stats.lost,
                    stats.relocalized,
                    tracking_state(step.outcome),
                )
            )
        finishing()  # every frame was read: a first Ctrl-C now lets the outputs be written
        streams.close()  # the live streams end; Ctrl-C interrupts again
        notes = [camera.stop() for camera in cameras]  # frames read and dropped
        for loop in loops:
            loop.end()
        _finish(frontends, results, coordinator, progress)
        store.record_runtime(None, {loop.frontend.agent: loop.report(0) for loop in loops})
        if coordinator_live is not None:
            coordinator_live.finish(results)
        seconds = [r.finished.seconds if r.finished else 0.0 for r in saved] + [
            loop.seconds for loop in loops
        ]
        summary = _write(
            staging, results, coordinator, config, agents, seconds, prior, store, progress
        )
    summary.out = out
    summary.notes.extend(notes)
    return summary


def _hand_over(
    results: Sequence[AgentFrontend | AgentResult],
    coordinator: Coordinator,
    coordinator_live: CoordinatorLive | None,
    packet: KeyframePacket,
) -> None:
    """Give an agent's keyframe to the coordinator and the pose updates it returns to the
    agents (``results``: by agent id)."""
    updates = coordinator.add_keyframe(received(packet, coordinator))
    _apply(results, updates)
    if coordinator_live is not None:
        coordinator_live.keyframe_added(packet, updates)


def _apply(frontends: Sequence[AgentFrontend], updates: Sequence[PoseUpdate]) -> None:
    """Hand the coordinator's pose updates to their agents, in order."""
    for update in updates:
        frontends[update.agent].apply_pose_update(update)


def _finish(
    frontends: Sequence[AgentFrontend],
    results: Sequence[AgentFrontend | AgentResult],
    coordinator: Coordinator,
    progress: PhaseCallback | None = None,
) -> None:
    """Send every front-end's last fused pointmap, run the terminal alternation, apply the
    final poses and refined pointmaps to every agent's ``results`` (by agent id)."""
    final_poses = {}
    for fe in frontends:
        if len(fe.keyframes):
            last = fe.keyframes.last
            refresh = PointmapRefresh(last.kf_id, last.X_hat, last.C_hat, last.fused_frames, last.K)
            coordinator.refresh(fe.agent, received(refresh, coordinator))
            final_poses[fe.agent] = fe.keyframes.poses()
    cleanup = coordinator.finish(final_poses, progress)
    _apply(results, cleanup.updates)
    for update in cleanup.pointmaps:
        results[update.agent].apply_pointmap_update(update)
    hold_the_coordinators(frontends, coordinator)


def _write(
    staging: Path,
    results: list[AgentFrontend | AgentResult],
    coordinator: Coordinator,
    config: Config,
    agents: list[AgentInput],
    seconds: list[float],
    prior: Prior,
    store: SessionStore,
    progress: PhaseCallback | None = None,
) -> RunSummary:
    """The output folder; ``agents`` are the inputs of the last ``len(agents)`` results
    (the others came with a saved map: then nothing is evaluated); ``store``: the run's
    session store (``metrics.json``: the bytes written to it)."""
    from como3r.runtime import outputs
    from como3r.runtime.disk_guard import store_metrics

    metrics, components = outputs.write_run_files(
        staging, results, coordinator, config, prior.describe(), seconds, progress
    )
    metrics["store"] = store_metrics(store)
    first = len(results) - len(agents)
    for entry, agent in zip(metrics["agents"][first:], agents):
        if isinstance(agent, CameraInput):  # its stream has ended: the count is final
            entry["frames_dropped"] = agent.dropped
    summary = RunSummary(out=staging)
    summary.agents.extend(outputs.agent_row(r, s) for r, s in zip(results, seconds))
    outputs.evaluate_and_finish(
        staging,
        summary,
        metrics,
        [] if first else agents,
        components,
        results,
        coordinator,
        config,
        progress,
    )
    return summary
