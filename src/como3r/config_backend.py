"""Configuration sections of the coordinator's back-end: cross-agent retrieval and
verification, gauge synchronization, global bundle adjustment and depth refinement
(C-Tab. 3's back-end rows). Sections of :class:`como3r.config.Config`, imported from
:mod:`como3r.config`, whose docstring says where the defaults come from.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


@dataclass(frozen=True)
class RetrievalConfig:
    """Cross-agent retrieval with binary ASMK (C-Tab. 3, C-Sec. B.3)."""

    codebook_size: int = 65536
    binary: bool = True
    use_idf: bool = False
    alpha: float = 3.0
    similarity_threshold_asmk: float = 0.0
    multiple_assignment_build: int = 1
    multiple_assignment_query: int = 5
    k_nn: int = 3
    min_similarity: float = 5e-3


@dataclass(frozen=True)
class VerificationConfig:
    """Inter-agent geometric verification, C-Eq. 12.

    The fields after ``tau_inter`` are not in the paper (como3r additions, see
    :mod:`como3r.coordination.association`):

    * ``min_covisible_ratio``: of the pixels of one view that the pair's own predicted
      geometry places inside the other view, onto a pixel whose confidence is at least
      ``covisible_min_confidence``, at least this share must be validly matched, in both
      directions. A prior that hallucinates a pose from repeated façades predicts overlap
      it cannot match. 0 restores the paper's single test. Measured on the aliasing
      façades (tests/coordination/test_association.py, occlusion_ratio 0.1): true pairs
      0.87-0.97, hallucinated ones 0.15-0.55; 0.7 sits between them. Measured again
      (issue 41) where baselines are wider and the prior harder: on the 16-agent ring of
      benchmarks/team_scale.py (160x120 -> 512, realistic prior, one process, seed 0)
      every verified cross-agent candidate truly overlaps (ground-truth depth: 0.10-0.86 of
      a view seen by the other); the admitted ones sit at 0.70-0.89, and 13 were refused by
      this ratio alone at 0.24-0.69 (9 at 0.6-0.7). At 0.6 that run admits 63 edges instead
      of 48, merged ATE 17.2 -> 15.6 mm. But among the test's façades with prior ``v2`` (every
      cross pair of every second frame verified, seed 1) the pairs that share no surface
      and pass ``tau_inter`` reach 0.78: at 160x120 (long side 160) 65 such pairs, 7 at
      0.72-0.78 and 8 at 0.6-0.7, against 28 true pairs, 19 above 0.7 and 4 at 0.6-0.7 (96x72: 64 false, 7
      at 0.71-0.82, 11 at 0.6-0.7). Under ``v2`` the ratio does not separate the two; a lower
      bar admits about two false pairs for each true one it gains, so 0.7 stays.
    * ``max_residual_ratio``: an edge between agents that already share a gauge must
      agree with their poses: the median distance of its matched points lifted into the
      shared world at most this fraction of their median range (about the relative
      rotation error in radians). ``inf`` admits every such edge, as the paper does.
      A decode of a true place whose relative translation is 1.6-3x too long or short (the
      wrong-scale edges of benchmarks/wrong_loops_centralized.py) passes it when the
      pair's baseline is short against the range, and no test on the edge's own geometry
      tells it from a true edge: measured (prior v2, 160x120, 3 agents, 3 seeds, 50 %
      wrong edges, every edge tested inside a gauge), the 27 true edges have residual
      ratios 0.031-0.090, the 9 wrong-scale edges that passed 0.036-0.072; the similarity
      fitted to the edge's lifted points moves keyframe j's camera centre by 0.4-6.8 % of
      the range (true) and 1.2-6.4 % (wrong), rescales by |log s| <= 0.067 and <= 0.084,
      and along the baseline by -0.35 to 6.4 baselines (true; above 0.5 only where the
      baseline is under 2.5 % of the range, the prior's noise over a short baseline) and
      -0.56 to 1.31 (wrong). A bar of half a baseline where the baseline is at least 4 % of
      the range would refuse 2 of the 9 and none of the 14 true edges there, a margin too
      thin on 14 edges to make a default of; not built. Those edges' matches were moved
      as the wrong geometry places them; a wrong decode matched by the coordinator's own
      matcher (the benchmark's default ``decode`` model since session 26) keeps matches
      the descriptors pull back, or fails C-Eq. 12: 20 % wrong, 1.03x the clean ATE.
    * ``max_decodes_per_keyframe``: the prior decodes one keyframe's verification may
      cost, over ALL other agents: the retrieval hits (``retrieval.k_nn`` over all other
      agents' keyframes, best first) are verified while their worst case (two decodes
      each, C-Eq. 12 is symmetric) fits, so the coordinator's work per keyframe does not
      grow with the team (the paper verifies every hit: with its ``k_NN = 3`` that is at
      most 6, the default, which so leaves the paper's behaviour unchanged).
    * ``max_within_component``: of those hits, at most this many whose agent already
      shares the keyframe's gauge component are verified (best first). Such an edge no
      longer synchronises a gauge (C-Sec. A.4: only the first edge between two
      components transports one); it only adds a loop constraint to the global BA, and
      one per keyframe keeps every meeting keyframe tied to the others, while the
      verifications that decide a merge are not spent on agents already merged. Measured
      on a 4-agent synthetic scene (320x240, 16 frames each, overlap 0.5, simulated
      prior, seed 0): the coordinator's decodes per keyframe 2.95 -> 1.58 (56 -> 30),
      admitted inter-agent edges 23 -> 12, the same three gauge merges, merged ATE
      10.5 -> 8.4 mm; 3 agents: 2.56 -> 1.39 (46 -> 25), merged ATE 9.6 -> 6.3 mm;
      8 agents: 3.93 -> 2.78 (106 -> 75), edges 30 -> 20, merged ATE 12.1 -> 15.2 mm
      (fewer loop constraints cost accuracy there). One seed each, and a loss at 8 agents:
      the default is 3 (``retrieval.k_nn``'s default), the paper's behaviour, until it is
      measured over seeds and team sizes; ``k_nn`` or more is the paper.
    * ``link_spacing``: a hit whose agent already shares the keyframe's gauge component is
      not verified when an admitted inter-agent link already joins the two agents within
      this many keyframes (along each agent's chain) of both the keyframe and the hit: it
      would add a loop constraint beside one the global BA holds, for one or two decodes.
      Agents that keep meeting (neighbours along a shared stretch) otherwise verify every
      keyframe against the same stretch again. The budget it frees goes to the next hits. 0
      (default): every hit within the budgets, the paper. Measured, 1 against 0 (prior v2,
      benchmarks/robustness.py --set, 160x120, long side 160, 80 frames, seeds 0 / 1;
      merged ATE % of path): 2 agents tabletop 0.239 / 0.270 -> 0.254 / 0.262, room 0.156 /
      0.250 -> 0.171 / 0.260, aerial 0.183 / 0.191 -> 0.196 / 0.185, decodes 9-15 % fewer;
      3 agents tabletop 0.236 / 0.213 -> 0.252 / 0.202, room 0.185 / 0.261 -> 0.188 / 0.260,
      aerial 0.201 / 0.260 -> 0.216 / 0.255, decodes 10-14 % fewer, inter-agent edges 14-16
      -> 9-12. 16 agents (benchmarks/team_scale.py's scene in one process, realistic
      prior): decodes 185 -> 163, edges 48 -> 40, merged ATE 16.7 -> 15.6 mm; the same
      team's captured multi-process calls replayed (benchmarks/coordinator_replay.py): 204
      -> 182 decodes, the same 15 merges. benchmarks/team_scale.py in processes (one run
      each, load 1-7; decodes per keyframe, the cores it needs to keep up, merged ATE): 4
      agents 3.6 -> 2.8, 4 -> 4, 3.33 -> 4.11 mm; 8 agents 4.36 -> 3.57, 8 -> 16, 6.95 ->
      7.83 mm; 16 agents 5.1 -> 4.55, 32 -> 16, 15.7 -> 16.0 mm (these runs' schedules
      differ from run to run). Always fewer decodes, an ATE a little worse in most runs and
      no consistent change in the cores a coordinator needs: not the default; it trades
      accuracy for decodes.
    * ``max_decodes_per_batch``: a coordinator that fell behind takes the waiting keyframes
      as one batch (``global_ba.max_batch_keyframes``) and verifies them newest first; a
      keyframe is verified only while the batch's decodes so far plus its own worst case
      (``max_decodes_per_keyframe``) fit this budget; the older ones are skipped (indexed:
      later keyframes still find them; counted in ``verification_skipped``) and deferred,
      not lost (:mod:`como3r.coordination.deferral`): verified later, newest first, with
      what a later batch leaves of this budget, one at a time by a multi-process coordinator
      with no keyframe waiting, and all that remain when the input ends, before the terminal
      cleanup (``verification_deferred``, of those ``verification_deferred_at_finish``);
      each keyframe with hits is verified once, and the session store keeps the deferred
      ones for a resumed run. A batch of one (``--single-process``, lockstep, a coordinator
      that keeps up) is always verified: this only bounds the work of a backlog. 0
      (default): no batch budget. Before the deferral (d99a887's 12,
      benchmarks/team_scale.py, 160x120 -> 512) the 4 / 8 / 16 teams left 9 / 19 / 35
      keyframes unverified and ended in 1 / 4 / 12 maps. With it, measured at 12 against 0
      (same script, multi-process, seed 0, 2 shared cores under a load of 5-27; ``end kf``
      the one-core replay's backlog at the end of the input): 4 agents: end kf 5 -> 5 (P =
      2: 1 -> 0), drain 14.1 -> 8.7 s, 7 keyframes deferred (5 verified at the end), decodes
      per keyframe 3.6 both, 1 map, merged ATE 3.33 -> 3.35 mm. 6 agents: end kf 15 -> 7 (P
      = 2 / 4 / 8: 8 / 3 / 1 -> 2 / 1 / 1), drain 34.1 -> 14.2 s, 13 deferred (12 at the
      end: 21.7 s of verification CPU), 1 map, merged ATE 3.31 -> 3.18 mm, but the 5 merges
      came at keyframes 17, 21, 25, 25, 25 of 25 instead of all at 17 (the older keyframes,
      where neighbours met, waited). 16 agents: end kf 34 -> 2 (P = 2 / 4 / 8: 28 / 20 / 11
      -> 0 / 0 / 0), drain 88 -> 0.9 s, in-stream verification CPU 2238 -> 704 ms per
      keyframe, 32 keyframes deferred, 31 of them verified at the end (about 60 s of
      verification CPU, thread and pool, moved into ``finish``: cleanup 218 -> 274 s wall),
      the same 114 edges tried, 15 merges and 1 map (without the budget 14 merges at
      keyframe 36 of 40, with it 2 at keyframe 26 and 13 at the end), merged ATE 15.8 ->
      16.2 mm (1.31 -> 1.35 % of an agent's path). The backlog does not vanish: it moves to
      the end of the input, where the map waits for it, and agents may get the merges' pose
      updates later. Not the default yet: one seed, one scene, 8 and 24 agents not measured.
    * ``max_loop_candidates``: an agent's intra-agent loop edges stay in its local graph
      (C-Sec. 3.5), so the global BA (C-Eq. 5) re-bends a loop-closed chain along its
      sequential edges alone. The coordinator's retrieval also returns up to this many
      keyframes of the keyframe's OWN agent other than its predecessor (the agent's loop
      candidates, found the same way). They share ``max_decodes_per_keyframe`` (the bound
      holds), after the hits that can merge two gauge components and before those of
      agents already merged; one that passes C-Eq. 12 and the co-visibility test and
      agrees with the agent's own poses (``max_residual_ratio`` and
      ``gauge.scale_alarm_log``, the test of a relinked chain edge) enters the global
      graph as a ``"loop"`` link. 0: none, the paper's global graph. Measured with
      benchmarks/robustness.py (prior v2, 2 agents, 160x120, 80 frames, seeds 0 / 1):
      merged ATE (% of path) room 0.90 / 1.20 -> 0.82 / 0.93, tabletop 0.87 / 1.30 ->
      0.71 / 1.05, aerial 0.84 / 1.15 -> 0.69 / 1.01; the room's decodes per keyframe
      4.04 / 3.31 -> 4.36 / 3.69 (8-12 loop links a run). Taking the loop candidates only
      from what every cross-agent hit left of the budget: room 0.90 / 0.98 (1-3 links).
      The demo scene (``como3r demo``'s, 2 agents): 8.31 -> 6.45 mm, 1.57 -> 2.79 decodes
      per keyframe; 16 agents of benchmarks/team_scale.py's scene in one process: 17.50 ->
      17.23 mm (3 loop links), 4.53 -> 4.62 decodes per keyframe.
    * ``workers``: threads that verify candidate pairs beside the coordinator's own
      (:mod:`como3r.coordination.decode_pool`): the re-encodes of keyframes that came
      without their encodings, the prior decodes and the matching, 74 % of the
      coordinator's CPU in ``add_keyframes`` (below) and independent per pair, run ahead for the next
      keyframes of a batch (and for a keyframe's other pairs beside the one the coordinator
      verifies itself, where the prior decodes pair by pair) while the coordinator's thread
      keeps every decision in its order: the outputs are bit for bit those of 0 (in line, no
      thread). Measured on benchmarks/team_scale.py's 4-agent scene (160x120 -> 512,
      simulated prior, multi-process in lockstep, ``OMP_NUM_THREADS=1``, 2 cores shared
      under a load of 10-17; thread CPU per keyframe): 0 -> 2, the coordinator's thread in
      ``add_keyframes`` 2251 -> 1317 ms (its serial part 595 / 610, the verification in it
      1656 -> 708, on the pool 963), trajectories, keyframes, ``graph.json`` and
      ``map.ply`` identical. Free-running at 2 (batches of up to 9 / 32 keyframes), 4 / 16
      agents: the coordinator's thread 686 / 919 ms, the pool 1400 / 2021, 0 / 6 of 72 / 204
      decodes wasted. Its replay for a coordinator of P cores cuts the 16-agent backlog at
      the end of the input only from 34 keyframes (P = 1) to 31 / 27 / 23 (P = 2 / 4 / 8):
      what stays serial, about 0.8 s per keyframe (journal, merges and focal alignment,
      global BA), is itself above the 0.26 s at which 16 agents bring keyframes. 2: the two
      cores the suite and the demo run on; a coordinator on a larger machine sets its cores
      (more threads than cores only share them).
    * ``on_agents``: the agents' processes verify the candidates the coordinator selects
      (:mod:`como3r.coordination.remote`) instead of the coordinator: it sends each
      selection with the keyframes' images, an agent process re-encodes, decodes and
      matches them between its frames and returns the matches, the coordinator admits the
      edges when they come back. Its own work per keyframe is then retrieval, admission,
      merges and global BA. benchmarks/team_scale.py (16 agents, 48 frames, simulated prior
      at 512x384, three runs): the coordinator's CPU per keyframe 1.9-2.0 s -> 325-358 ms, and
      on one core it keeps up with the agents' measured frame rates (144-146 keyframes
      behind when the input ended -> none); each agent spends 2.1-2.3 s of CPU per keyframe
      verifying (its frames 2.1 -> 3.3 s), the requests carry the keyframes' images (70 MB
      per robot against 15), merged ATE 17.9-18.1 -> 19.3-20.1 mm. Off by default: a team
      whose coordinator keeps up (4 agents here) gains nothing and its agents slow down;
      a run whose coordinator trailed its team says so in its summary.
      Runs with agent processes, on this machine (``como3r run``) or across machines
      (``como3r coordinator`` and ``como3r agent``); in one process (``--single-process``)
      and in lockstep the coordinator verifies, as with false.
    """

    tau_inter: float = 0.1
    min_covisible_ratio: float = 0.7
    covisible_min_confidence: float = 1.5
    max_residual_ratio: float = 0.25
    max_decodes_per_keyframe: int = 6
    max_within_component: int = 3
    max_decodes_per_batch: int = 0
    max_loop_candidates: int = 1
    workers: int = 2
    link_spacing: int = 0
    on_agents: bool = False


@dataclass(frozen=True)
class GaugeConfig:
    """Gauge synchronization, C-Eq. 14-15.

    ``min_consistent_edges`` is not in the paper (como3r addition): two gauge components
    merge once this many verified edges between them agree on the aligning transform
    (each within ``verification.max_residual_ratio`` under it). Edges still waiting between
    two components when the stream ends merge them on the set most of them agree with, a
    lone edge too (the paper's merge, late), unless an edge outside that set has as much
    support (two disagreeing edges leave the maps apart). 1 is the paper's synchronization
    on the first verified edge (C-Eq. 14-15), which nothing tests: a look-alike that comes
    first merges two maps alone, and the true edges after it disagree with the bent poses
    and are refused. benchmarks/wrong_loops_centralized.py (prior v2, 3 agents, 3 seeds, 20 %
    wrong edges): 10.85 % of path with 1 (a seed at 565.6 mm against 9.0 clean), 0.846 %
    with 2 (clean 0.651 %). What 2 costs on true data (prior v2, benchmarks/robustness.py,
    160x120, 80 frames, long side 160, seeds 0 / 1; merged ATE % of path, 1 -> 2): 2 agents
    tabletop 0.235 / 0.266 -> 0.239 / 0.270, room 0.160 / 0.256 -> 0.156 / 0.250, aerial
    0.183 / 0.185 -> 0.183 / 0.191, each merge 3 / 0 keyframes after the first verified
    edge (of 21-23); 3 agents tabletop 0.261 / 0.214 -> 0.236 / 0.213, room 0.228 / 0.245
    -> 0.185 / 0.261, aerial 0.249 / 0.250 -> 0.201 / 0.260, the team in one map 2
    keyframes later in every cell (of 28-29); no merge missed (the 3-agent seed-0 cells run
    again with 1 on this code gave 0.261, 0.228 and 0.249 again). The
    demo scene (``como3r demo``, 2 agents): 6.45 -> 6.30 mm, merged at keyframe 10 instead
    of 5 (of 14). The 7-Scenes split of tests/test_real_data.py (one keyframe per agent,
    one edge) merges at the end.

    ``align_focal`` (como3r addition, self-calibrated runs only): at a merge the moving
    component's focal length is corrected to agree with the anchor's on the supporting
    keyframe pairs (:mod:`como3r.frontend.focal`), searched within
    ``focal_search`` in log focal. Measured on a two-agent simulated scene (160 px,
    2 x 30 frames, realistic prior, merged ATE % of mean agent path): agents' estimates
    +1.2 % and -8.7 % off give 3.8 % without it; both on one focal length 0.72 %.
    The terminal cleanup re-aligns every agent of a component on up to four of its
    admitted edges to the agents settled before it (anchor first,
    ``Coordinator._refine_focals``): a merge often rests on one pair. Measured on a 3-agent
    room (320x240 -> 512, 12 processed frames each, seed 0): merged ATE 2.7 -> 1.07 % of
    path (calibrated: 0.38 %); seed 1: 0.72 -> 0.85 % (one focal length, but the single
    edge between agents 0 and 1 leaves a 3 % scale offset the focal errors had hidden).

    ``max_correspondences`` (como3r addition; issue 41): an edge's valid matches are evenly
    subsampled to at most this many per direction for its ``T*`` (C-Eq. 14), its agreement
    test and its scale watch; 0 takes every valid match (C-Eq. 14 as printed). At 512x384 an
    edge has about 200,000, and the Umeyama fits over them were most of a 16-agent
    coordinator's merge time. A captured 16-agent run's coordinator calls (batches 1 / 1 /
    24 / 14, replayed in one thread; ``benchmarks/team_scale.py``'s scene): in-stream thread
    CPU 533 -> 305 ms per keyframe from all to 8192, in-stream keyframe ATE 67.66 -> 67.53
    mm, the same 15 merges and 52 edges. The prior's errors are smooth across the image, so
    the fit is set by them, not by the number of pixels.

    ``focal_max_matches`` (como3r addition; issue 41): the focal BA builds each edge over
    an even subset of at most this many of its valid matches, weighed by the share left out
    (:func:`~como3r.frontend.graph.thinned`), as the in-stream global BA does
    (``global_ba.stream_max_matches``); the pose passes after it take every match. 0: every
    match. It held every edge's dense factors for its solve: the largest part of a 16-agent
    coordinator's memory at the end of a long mission (190 keyframes, 512x384: 6.2 -> 7.6
    GB while it ran).

    ``scale_alarm_log`` (como3r addition): the scale watch of wrong links. An edge between
    agents that already share a gauge whose own similarity (Umeyama on its lifted points)
    would rescale the map by more than this in ``|log s|`` is held back (status
    ``inconsistent``, counted in ``edges_scale_inconsistent`` and logged); at a merge over
    several agreeing edges, an edge whose own ``T*`` scale differs from the joint one by
    more than this does not count as support (``gauge_scale_held``). A single first edge
    has nothing to be compared with: ``min_consistent_edges`` > 1 makes the merge watch it.

    ``focal_loops`` (como3r addition, off by default; issue 41): after that chain, where the
    agents' admitted pairs close a loop, re-measure every agent pair and solve all focal
    lengths jointly in least squares (``Coordinator._close_focal_loops``). Measured on a
    ring of agents (160x120 -> 512, 8 processed frames each, single process, seed 0):
    merged ATE 4 agents 7.0 -> 6.4 mm, 8 agents 8.0 -> 8.0 mm, 16 agents 62.1 -> 59.2 mm,
    but the 16 agents' map accuracy 0.151 -> 0.181 m (F-score 0.70 -> 0.55): its pairwise
    estimates scatter by 2-5 %, so it is not the default.

    ``focal_ba`` (como3r addition, on by default; issue 41): instead of that chain (and of
    ``focal_loops``, which then does nothing), the terminal cleanup estimates one focal
    length per agent inside the global BA, jointly with the poses over every edge of the
    component (C-Eq. 5 with the C-Eq. 17 residual and a log focal variable per agent:
    :mod:`como3r.backend.focal_solver`), with a prior of standard deviation ``focal_prior``
    (log focal) on each agent's own self-calibration: the edges fix the ratios of the
    agents' focal lengths, the prior what they leave open (a focal scale common to all of
    them, which nearly translational motion cannot tell from a baseline). Measured (true
    focal 333.6 px, ring scenes of ``benchmarks/team_scale.py``, 160x120 -> 512, seed 0):
    4 agents multi-process, merged ATE 9.93 -> 3.05 mm, focal lengths 335.7-336.1 ->
    333.6-333.7 px; 16 agents multi-process 223 -> 24.8 mm, 270-337 -> 332-336 px; offline
    on the stored 16-agent single-process session (keyframe ATE) 62.7 -> 14.2 mm, 306-337
    -> 331-335 px. A 2-agent room of the prior-v2 grid (160 px,
    80 frames) stays at 166 mm: its agents each drift on their own (6.9 and 18.8 cm alone)
    and their focal lengths were already within 0.7 %.
    """

    min_correspondences: int = 64
    max_correspondences: int = 8192
    min_consistent_edges: int = 2
    align_focal: bool = True
    focal_loops: bool = False
    focal_search: float = 0.3
    focal_ba: bool = True
    focal_prior: float = 0.05
    focal_max_matches: int = 8192
    scale_alarm_log: float = 0.2


@dataclass(frozen=True)
class GlobalBAConfig:
    """Global Sim(3) bundle adjustment, C-Eq. 5 and C-Eq. 25 (C-Tab. 3)."""

    trigger_interval_edges: int = 1
    # not in the paper: keyframes that waited for a busy coordinator are taken together,
    # up to this many (Coordinator.add_keyframes): inserted, retrieved and verified in time
    # order (newest first under a verification.max_decodes_per_batch budget), and the
    # in-stream BA runs at most once per batch, so the solves a falling-behind
    # coordinator makes do not grow with the keyframes waiting.
    # A keyframe handed over as it comes (the single-process runner, lockstep) is a batch
    # of one: the paper's BA after every trigger_interval_edges
    max_batch_keyframes: int = 32
    max_iters_stream: int = 50
    # not in the paper (issue 41): the in-stream BA linearizes each edge over an even subset
    # of at most this many of its valid matches, weighed by the share left out
    # (backend.global_graph.thinned); the terminal cleanup takes every match. 0: every
    # match in-stream too (C-Eq. 5). The long 16-agent capture of
    # benchmarks/coordinator_replay.py (190 keyframes, 512x384, one thread) at 0 / 8192 /
    # 2048: in-stream BA 152 / 41 / 35 ms per keyframe, coordinator thread 276 / 176 / 172,
    # in-stream keyframe ATE 119.40 / 119.26 / 119.23 mm, the same merges, edges and decodes
    stream_max_matches: int = 8192
    max_iters_cleanup: int = 100
    cleanup_passes: int = 5
    # cleanup stops when no keyframe moved more than this fraction of the component's median
    # keyframe depth (C-Sec. A.7's 5 mm at the 1 m reference depth of geometry.units)
    cleanup_stop_translation: float = 5e-3
    # a solve stops when ||tau||_2 < step_tol, its translations in units of the component's
    # median keyframe depth (optim.optimizer, length_scale). C-Sec. B.2 prints 1e-8; below
    # about 1e-6 float32 factors cannot resolve the step, and Huber IRLS converges linearly
    # (|tau| shrinks x0.6-0.8 per iteration), so 1e-8 runs nearly every solve to max_iters.
    # Demo scene (2 agents x 15 frames, long side 256, scene depth 4.6 m), absolute
    # tolerance 1e-8 / 1e-5 / 1e-4 / 1e-3: in-stream BA 154 / 100 / 73 / 47 iterations,
    # cleanup 129 / 58 / 37 / 20, coordinator 71 / 41 / 33 / 23 s; merged ATE 4.180 / 4.180 /
    # 4.179 / 4.175 cm, map accuracy 33.42 cm and F-score 0.5735 in all four. 1e-4 of the
    # scene depth (4.6e-4 there) keeps a margin; 1e-8 restores the paper at 1 m.
    step_tol: float = 1e-4
    # not in the paper: an edge's matches are linearized again only when its relative pose
    # moved more than this (radians, nepers, the component's median keyframe depth) since
    # they last were, in this solve or an earlier one, or an endpoint's pointmap changed;
    # in between, its blocks come from the quadratic model of that linearization
    # (optim.relinearization; iSAM2's relinearization threshold). 0: every edge at every
    # iteration, as the paper
    relinearize_tol: float = 1e-3
    lm_lambda: float = 0.0
    tikhonov_base: float = 1e-6
    tikhonov_retries: int = 6
    # backend of the C-Eq. 25 solve (como3r.optim.linear.solve): "auto" takes a dense
    # Cholesky up to 60 free keyframes and above it "band" (conjugate gradients with a band
    # + coarse two-level preconditioner, como3r.optim.band), whose cost grows about linearly
    # with and without many loop closures: at 2,000 keyframes 0.25x SuperLU's solve time
    # with a loop edge every 4 keyframes, 0.9-1.6x with one every 50. "sparse" (SuperLU)
    # and "pcg" (block-Jacobi conjugate gradients, 40x SuperLU on chain-like graphs) stay
    # selectable
    linear_solver: Literal["auto", "dense", "sparse", "pcg", "band"] = "auto"


@dataclass(frozen=True)
class DepthRefinementConfig:
    """Segment-level depth refinement and alternation, C-Eq. 19-24, C-Sec. A.6-A.7."""

    variant: Literal["segment", "pixel", "pixel_laplacian"] = "segment"
    slic_segments: int = 200
    slic_compactness: float = 8.0
    slic_sigma: float = 1.0
    slic_min_confidence: float = 1.5
    min_valid_pixels: int = 16
    # C-Eq. 21 point noise as a fraction of keyframe i's median range (C-Tab. 3's 0.05 m at
    # the 1 m reference depth of geometry.units)
    sigma_point: float = 0.05
    lambda_smooth: float = 1.0
    lambda_prior: float = 1.0
    lambda_lm: float = 0.05
    step_clip: float = 0.5
    inner_iters: int = 10
    alternation_rounds: int = 100
    # what the poses do in the rounds of C-Sec. A.7 step 2 in a multi-agent component:
    # "frozen" = one depth step at the poses of step 1's passes (departs from the paper, see
    # backend.alternation; alternation_rounds then only allows or, at 0, skips it),
    # "pose_pass" = the paper's rounds, a short pose pass after each depth step
    round_poses: Literal["frozen", "pose_pass"] = "frozen"
    pose_pass_iters: int = 50
    depth_convergence_tol: float = 5e-3  # max |delta s| that ends the alternation (A.7)
    # C-Eq. 19's base pointmap: "insertion" = the keyframe's first prediction (the paper),
    # "fused" = its fused pointmap (C-Eq. 3) when the cleanup starts; see backend.global_graph
    refine_from: Literal["fused", "insertion"] = "fused"
    # boundary residual of C-Eq. 22: "jump_change" = (s_a - s_b), the refinement may not
    # change the prior's depth jump between adjacent segments; "log_depth" = the paper's
    # (s_a - s_b) + Delta_ab, refined log-depths pulled together (see backend.depth_refinement)
    boundary_residual: Literal["jump_change", "log_depth"] = "jump_change"
    # a round whose max |delta s| exceeds this fraction of the previous round's has stalled
    # and ends the alternation (later rounds drift the map; inf disables)
    depth_stall_ratio: float = 0.5
