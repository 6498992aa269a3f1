"""Two finished sessions merged into one map (issue 14: ``como3r merge A B --out C``).

The first session's map starts the coordinator as ``run --map`` does (:mod:`.map_session`):
its agents keep their ids ``0 .. M-1``. The second session's keyframes then arrive as if
its agents (now ``M, M+1, ...``) were streaming them again, in the order its coordinator
received them: each with its sequential edge's matches, its encoding, retrieval features
and pointmap, and its pose in the frame its agent is in at that moment (the second session's
frame until a gauge merge moves the agent, the merged frame after, as an agent applies the
coordinator's updates). So the association is the one of every run: retrieval against the
database (which holds both sessions' keyframes), dense verification, the consistency tests,
the gauge merge, global BA. The second session's own cross-agent edges are not copied: its
agents find each other again the same way.

If no agent of one session ends in a gauge component with an agent of the other, the
sessions share no place that was recognized: that is an error, and nothing is written.
Otherwise the terminal refinement runs on every component that gained agents, and the
output folder holds every agent of both, in one frame per component (the first session's
where it is one of them).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

from como3r.coordination.coordinator import Coordinator
from como3r.errors import InputError
from como3r.frontend.keyframes import Keyframe
from como3r.frontend.packets import KeyframePacket, PointmapRefresh
from como3r.io.output import atomic_output_dir
from como3r.progress import PhaseCallback, report_phase
from como3r.runtime import outputs
from como3r.runtime.map_session import SavedMap, map_results, open_map, seed_map
from como3r.runtime.pipeline import PriorSpec, RunSummary, build_prior
from como3r.runtime.results import AgentResult
from como3r.store.schema import STORE_NAME
from como3r.store.writer import SessionStore

logger = logging.getLogger(__name__)


def merge_runs(
    first: Path,
    second: Path,
    out: Path,
    prior_spec: PriorSpec,
    overwrite: bool = False,
    progress: PhaseCallback | None = None,
) -> RunSummary:
    """Merge the maps of two finished runs into the output folder ``out``.

    Args:
        first: the run folder whose agents keep their ids and whose frame is kept.
        second: the run folder whose agents follow, moved into the first one's frame.
        out: output folder (created atomically).
        prior_spec: the prior that verifies candidate pairs (the sessions' own).
        overwrite: replace an existing non-empty output folder.
        progress: called as each keyframe of ``second`` and each step of the terminal
            work starts.

    Raises:
        InputError: a folder without a finished session, sessions of different
            configurations, or sessions that share no place (nothing is written).
        StoreError: a store that cannot be read.
    """
    kept = open_map(first, None, option="merge")
    moved = open_map(second, kept.session.config, option="merge")
    config = kept.session.config
    prior, codebook = build_prior(prior_spec, config)
    coordinator = Coordinator(prior, config, codebook, kept.agents + moved.agents)
    seed_map(coordinator, kept)
    coordinator.refined += [
        {kept.agents + a for a in members} for members in moved.session.gauges.components()
    ]
    results = map_results(kept) + map_results(moved, kept.agents, coordinator.graph)
    with atomic_output_dir(out, overwrite=overwrite) as staging:
        with SessionStore.create(staging / STORE_NAME, config, coordinator) as store:
            store.record_runtime(None, {r.agent: r.finished for r in results if r.finished})
            _replay(moved, kept.agents, coordinator, results, progress)
            _check_meeting(first, second, coordinator, kept.agents)
            cleanup = coordinator.finish(None, progress)
            for update in cleanup.updates:
                results[update.agent].apply_pose_update(update)
            summary = _write(staging, results, coordinator, prior.describe(), progress)
    summary.out = out
    return summary


def _replay(
    moved: SavedMap,
    offset: int,
    coordinator: Coordinator,
    results: Sequence[AgentResult],
    progress: PhaseCallback | None,
) -> None:
    """Hand the moved session's keyframes to the coordinator in their stored order, each in
    its agent's current frame (its pose in ``results``; the coordinator takes its pointmap
    onto the agent's focal length in the merged map); apply the coordinator's updates to
    the results."""
    graph = moved.session.graph
    # a relocalized keyframe's chain edge may join it to an earlier keyframe than its
    # predecessor (linking.InterAgentLinking._relink): it is not a packet's sequential edge,
    # and the coordinator here links that keyframe again itself, as it finds an agent's
    # "loop" links again (linking.InterAgentLinking._add_loop)
    sequential = {
        link.j: link.link
        for link in graph.links
        if link.kind == "sequential"
        and graph.keyframes[link.i].kf_id + 1 == graph.keyframes[link.j].kf_id
    }
    for g, kf in enumerate(graph.keyframes):
        report_phase(progress, "merging", f"keyframe {g + 1} of {len(graph)}", g, len(graph))
        agent = offset + graph.agent_of[g]
        link = sequential.get(g)
        previous = (
            None
            if kf.kf_id == 0
            else _refresh(graph.keyframes[graph.global_index(graph.agent_of[g], kf.kf_id - 1)])
        )
        packet = KeyframePacket(
            agent=agent,
            kf_id=kf.kf_id,
            frame_index=kf.frame_index,
            timestamp=kf.timestamp,
            T_WC=results[agent].keyframes[kf.kf_id].T_WC.clone(),
            X_hat=kf.X_hat,
            C_hat=kf.C_hat,
            colors=kf.colors,
            encoding=kf.encoding,
            retrieval=kf.retrieval,
            sequential_ij=None if link is None else link.ij,
            sequential_ji=None if link is None else link.ji,
            previous=previous,
            K=kf.K,
        )
        for update in coordinator.add_keyframe(packet):
            results[update.agent].apply_pose_update(update)
    for agent in range(moved.agents):  # as an agent's last keyframe comes with its report
        own = graph.agent_keyframes(agent)
        if own:
            coordinator.refresh(offset + agent, _refresh(graph.keyframes[own[-1]]))


def _refresh(kf: Keyframe) -> PointmapRefresh:
    """A stored keyframe's fused pointmap as its agent would send it (with the keyframe
    after it, or at its end)."""
    return PointmapRefresh(kf.kf_id, kf.X_hat, kf.C_hat, kf.fused_frames, kf.K)


def _check_meeting(first: Path, second: Path, coordinator: Coordinator, split: int) -> None:
    """Some agent of each session ends in one gauge component with the other's.

    Raises:
        InputError: they share no place.
    """
    mapped = [c for c in coordinator.components() if coordinator.graph.agent_keyframes(c[0])]
    if not any(min(c) < split <= max(c) for c in mapped):
        raise InputError(
            f"merge: {first} and {second} share no place (no keyframe of one was "
            f"verified against the other's); nothing written"
        )


def _write(
    staging: Path,
    results: Sequence[AgentResult],
    coordinator: Coordinator,
    prior: dict,
    progress: PhaseCallback | None,
) -> RunSummary:
    """The output folder of a run, from the merged results (no evaluation: the sessions'
    ground truth is not known here; ``como3r eval`` takes it)."""
    seconds = [r.finished.seconds if r.finished else 0.0 for r in results]
    metrics, components = outputs.write_run_files(
        staging, results, coordinator, coordinator.config, prior, seconds, progress
    )
    summary = RunSummary(out=staging)
    summary.agents.extend(outputs.agent_row(r, s) for r, s in zip(results, seconds))
    outputs.evaluate_and_finish(
        staging,
        summary,
        metrics,
        [],
        components,
        results,
        coordinator,
        coordinator.config,
        progress,
    )
    return summary
