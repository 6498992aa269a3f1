"""The coordinator's counters and timings (``metrics.json``'s ``coordinator`` section, kept
in the session store): :class:`CoordinatorStats`, one part of
:class:`~como3r.coordination.coordinator.Coordinator`'s state."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class CoordinatorStats:
    """Counters and timings reported in metrics.json."""

    keyframes: int = 0
    retrieval_queries: int = 0
    edges_tried: int = 0
    edges_verified: int = 0
    edges_accepted: int = 0
    edges_inconsistent: int = 0
    # of those, edges whose own similarity would rescale the map (gauge.scale_alarm_log)
    edges_scale_inconsistent: int = 0
    # edges a merge did not count as support: their T* scale disagreed with the joint one
    gauge_scale_held: int = 0
    gauge_syncs: int = 0
    focal_refinements: int = 0
    ba_runs: int = 0
    ba_iterations: int = 0
    ba_seconds: float = 0.0
    ba_restored: int = 0
    cleanup_passes: int = 0
    cleanup_iterations: int = 0
    cleanup_seconds: float = 0.0
    pose_updates: int = 0
    # keyframes are taken in batches (Coordinator.add_keyframes): how many batches had a new
    # keyframe, and the most new keyframes one had (1: the coordinator never fell behind)
    batches: int = 0
    largest_batch: int = 0
    # ordered pairs the prior decoded for the coordinator (verification): the prior's work
    # its keyframes caused, as the agents' decodes are theirs (benchmarks/report.py)
    prior_decodes: int = 0
    # keyframes of a batch whose verification verification.max_decodes_per_batch deferred,
    # those of them verified later (.deferral; equal once the cleanup ran), and of these
    # the ones verified only when the input ended, before the terminal cleanup
    verification_skipped: int = 0
    verification_deferred: int = 0
    verification_deferred_at_finish: int = 0
    # keyframes whose encoding was made again from their colours (.encodings); their
    # seconds are stage_seconds["reencode"]
    reencodes: int = 0
    # relocalized keyframes (no sequential edge) tied to their agent's chain by the
    # coordinator (linking.InterAgentLinking._relink)
    chain_relinks: int = 0
    # keyframes of a keyframe's own agent verified as its loop candidates, and the loop
    # links that entered the global graph (verification.max_loop_candidates)
    loops_tried: int = 0
    loop_links: int = 0
    # verification on threads (verification.workers, .decode_pool), in thread CPU seconds:
    # the coordinator's own thread's in _verify (in line: what the pool did not run ahead,
    # or everything without one), the workers' by stage (reencode, prior_decode and the
    # rest of verification, the matching; wasted work included), so that
    # benchmarks/team_scale.py can spread the verification over cores
    verification_cpu: float = 0.0
    pool_seconds: dict[str, float] = field(default_factory=dict)
    # verifications the pool ran for a predicted selection the coordinator then did not
    # make (a merge came between), and their decodes (not in prior_decodes)
    pool_wasted: int = 0
    pool_wasted_decodes: int = 0
    # verification on the agents (verification.on_agents, .remote): jobs the agents answered,
    # their decodes (in prior_decodes too), the agents' thread CPU seconds by stage, and the
    # jobs taken back to be verified here (their agent gone)
    remote_verifications: int = 0
    remote_decodes: int = 0
    remote_seconds: dict[str, float] = field(default_factory=dict)
    remote_taken_back: int = 0
    stage_seconds: dict[str, float] = field(default_factory=dict)

    def add_time(self, stage: str, seconds: float) -> None:
        """Accumulate wall-clock seconds of a stage."""
        self.stage_seconds[stage] = self.stage_seconds.get(stage, 0.0) + seconds
