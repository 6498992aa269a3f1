"""Teams of 1 to 16 agents, centralized: does the coordinator's cost per keyframe stay flat?

For every team size a synthetic ring scene is made (``como3r synth --agents N``: neighbours
share ``--overlap`` of their paths, non-neighbours never meet; ``--loop-frames`` lays the
loop out for longer paths than the ``--frames`` rendered, as the dashboard's scene does) and
run with the default multi-process runtime (``como3r run``: one process per agent, the
coordinator in the measuring process, free-running, simulated prior), each size in a
process of its own so memory peaks do not carry over. Per team size the table gives

* ``coord ms/kf``: the coordinator's CPU time (its thread's, so other processes on the
  cores do not count) in ``add_keyframe(s)`` per keyframe: retrieval, verification and
  its decodes, gauge merges, in-stream global BA and the session store's writes, all of
  the in-stream work; the terminal cleanup is apart (``cleanup s``, wall);
* ``coord s/s input``: that CPU time per second of the team's input (its timestamps);
* ``decodes/kf``: prior decodes the verification caused per keyframe (the budget,
  ``verification.max_decodes_per_keyframe``, bounds it per keyframe);
* ``end kf``, ``end s``, ``drain s``: the backlog at the end of the input when every agent
  runs at its measured frame rate on a core of its own and the coordinator on another: a
  replay of the measured per-keyframe coordinator CPU times (a batch's split evenly over
  its keyframes) against the keyframes' arrival times, each agent's frames at its own
  CPU seconds per frame (read from ``/proc`` between its first and last frame: the
  agents' startup is left out). At the moment the last agent's last frame is done:
  keyframes arrived and not yet handled, seconds of input the coordinator trails (newest
  arrived keyframe's timestamp minus newest handled one's) and seconds it then needs to
  finish. A coordinator that keeps up trails by at most the keyframes of the last moment.
  One core serves all the coordinator's CPU: its thread's and its verification pool's;
* ``verify ms/kf``, ``pool ms/kf``, ``wasted``: of that CPU per keyframe, the verification's
  (re-encodes, prior decodes and matching: what ``verification.workers`` threads run,
  :mod:`como3r.coordination.decode_pool`), in the coordinator's thread and on its pool
  together, and the pool's part (its workers' thread CPU, wasted work included; not in
  ``coord ms/kf``); the decodes the pool made for a keyframe's predicted candidates that a
  merge before it then changed;
* ``agents ms/kf``: with ``verification.on_agents`` (``--set verification.on_agents=true``,
  :mod:`como3r.coordination.remote`), the agents' thread CPU per keyframe verifying for the
  coordinator (re-encodes, decodes, matching); the coordinator then verifies nothing
  itself (its ``add_verified`` calls, which admit the agents' edges, are in ``coord
  ms/kf`` and in the replays, each keyframe's share added to its work), and each agent's
  CPU per frame includes what it verified after its last frame, spread over its frames
  (between frames ``/proc`` counts it);
* ``skipped``, ``deferred``, ``at end``, ``idle s``: under a batch budget
  (``--set verification.max_decodes_per_batch=N``), keyframes whose verification a batch
  deferred, those verified later (:mod:`como3r.coordination.deferral`), of these the ones
  verified only when the input ended (before the terminal cleanup, so in ``cleanup s``), and
  the CPU seconds (thread and pool) of the verifications an idle coordinator caught up on:
  in ``coord ms/kf``, not in the replays (they ran while no keyframe waited); ``at end s``:
  the CPU seconds (thread and pool) of the verification at the end (in ``cleanup s``, wall);
* ``end kf PP``, ``drain s PP``: the same replay for a coordinator of P cores
  (``--coordinator-cores``, default 2, 4 and 8): each call's serial CPU (its thread's
  less the verification it did in line) on one core, then all of its verification, in line
  and pooled, spread evenly over the P cores. Measured, not modelled, are the two parts;
  the model is that the verification of a call parallelizes perfectly (it is independent per
  candidate pair, and what a run verified in line, a pool predicted wrongly or a batch of
  one left to the coordinator, could have been pooled) and does not overlap the serial part
  (where the pool in fact verifies the next keyframes while the coordinator admits this
  one's edges): per call ``serial + verification / P``, conservative on the overlap,
  optimistic on the speculation. P = 1 is the one-core replay (``end kf``, ``drain s``);
* ``serial ms/kf``: of the coordinator's CPU per keyframe, the part more cores do not
  shorten (its thread's less the verification in it); ``cores for 0``: the fewest cores (1,
  2, 4, ... 256) with which that replay keeps up, no keyframe queued at the end of the
  input (the one in hand is not queued: a coordinator that keeps up still works on the
  keyframe of the last moment); ``>256`` where the serial part alone falls behind the
  keyframes' arrivals;
* ``rt end kf``, ``rt max kf``: the runtime's own backlog (``metrics.json``
  ``runtime.backlog``) on this machine, where all processes share its cores: at the end
  of the input and the most during the run;
* ``out at end``: with ``verification.on_agents``, the keyframes whose verification the
  agents had not returned when the input ended (the runtime waits for them, then runs the
  terminal cleanup);
* ``batch``: the most keyframes the coordinator took at once;
* ``coord MB``, ``agent MB``: peak resident memory (``VmHWM``) of the coordinator's
  process over the whole run (terminal refinement and evaluation included) and of the
  largest agent process;
* ``ATE mm``, ``path m``, ``ATE %``, ``ATE % team``: merged ATE RMSE (every agent aligned
  by one similarity; one agent: its own), the agents' mean ground-truth path length, the
  ATE as a share of that mean ONE-AGENT path (the figure issue 41's "<= 1 % of path" was
  first measured in: strict for a team, whose map spans N paths while the denominator stays
  one), and as a share of the TEAM's path (the sum of the agents' ground-truth paths, the
  length the merged trajectory covers; with ``--overlap 0.5`` neighbours share half of
  theirs, so the ring the team closes is about 0.75 of it). Both are given; neither is
  chosen to pass. ``maps``: gauge components at the end (1: one map);
* ``kB/robot``: bytes exchanged between the coordinator and one agent (both directions),
  averaged over the agents.

With ``--decentralized`` (default) the table of ``team_scale_decentralized.py``
(``decentralized_rows``) follows when that module is present.

    python benchmarks/team_scale.py --work /tmp/team_scale   # 1, 2, 4, 8, 16 agents
    python benchmarks/team_scale.py --work /tmp/team_scale --sizes 4 16 --seeds 0 1
    python benchmarks/team_scale.py --work /tmp/team_scale --sizes 16 --scales  # finished runs

Measured (issue 41; ``--width 96 --height 72``, 16 frames rendered, 8 processed per agent,
seed 0, 2 shared cores under a load of about 20, so wall times are not comparable; CPU times
are):

    agents  kf  coord ms/kf  decodes/kf  end kf  drain s  batch  coord MB  agent MB  ATE mm  ATE %
         1   4         10.7        0         2    0.015      2       483       457    20.6    1.90
         2   9          173        2.56      1    0.11       4       515       464    29.5    2.45
         4  17          173        3.82      8    1.16      11       532       461    28.6    2.37
         8  27          170        4.48     16    2.77      23       557       460    29.8    2.48
        16  40          238        4.88     33    7.59      32       596       461    56.6    4.70

16 vs 4 agents: coordinator CPU per keyframe 1.38x, its peak memory 1.12x, decodes per
keyframe within the budget of 6. The rise at 16 is the gauge merges (with the focal
alignment, 60 % of the in-stream wall time there): a team makes N - 1 of them, and these
short runs (2.5 keyframes per agent at 16, 4.3 at 4) spread them over few keyframes. The
coordinator does not keep up at these agents' rates (5 frames per CPU second each with the
simulated prior at 96x72): it needs about 0.24 s per keyframe, and from 4 agents on the
keyframes arrive faster than that (drain 1.2 s at 4, 7.6 s at 16 after the input's 1.6 s);
batching bounds its global BAs (2 in-stream at 16 agents), not its verification and
merges. One agent alone is at 1.9 % of path at this resolution, the floor under the merged
figures; the same 16-agent scene in one process (every keyframe alone, 26 in-stream BAs)
merged at 238 mm (19.8 %).

Measured at the defaults (160x120, long side 512; 2 shared cores under a load of 8-18
from other jobs, so only CPU-time ratios mean anything; commit 08241ae, seed 0; the 1- and
2-agent rows with d99a887, whose batch budget skipped nothing there):

    agents  kf  coord ms/kf  decodes/kf  end kf  drain s  batch  coord MB  ATE mm  ATE %  ATE % team
         1   4          135        0         0      0        3       717    1.34   0.12     0.12
         2  10          666        1.2       0      0        3      1104    3.75   0.31     0.16
         4  20         1335        3.0       6     11.7     10      2031    9.93   0.83     0.21
         8  28         1567        3.71     19     30.9     18      2607    8.80   0.73     0.09
        16  42         2088        4.79     34     72.5     29      3850     223   18.6      1.16

16 vs 4 agents: coordinator CPU per keyframe 1.56x, peak memory 1.90x, decodes per keyframe
within the budget of 6; the coordinator falls behind from 4 agents on (each agent about 0.6 s
of CPU per frame here). The 16-agent merged ATE in this multi-process run (batches of up to 29
keyframes) is 223 mm where the same scene in one process (batches of one) gives 62 mm: open.
With ``verification.max_decodes_per_batch=12`` (d99a887's default, now 0) the 4 / 8 / 16 teams
left 9 / 19 / 35 keyframes unverified and ended in 1 / 4 / 12 maps. Since skipped keyframes
are deferred (:mod:`como3r.coordination.deferral`; ``--set verification.max_decodes_per_batch=12``
against the default, seed 0, load 5-27; the numbers in ``VerificationConfig``): 16 agents end kf
34 -> 2, drain 88 -> 0.9 s, 31 of 32 deferred keyframes verified at the end (cleanup 218 ->
274 s wall), one map either way, ATE 15.8 -> 16.2 mm.

Merged ATE at 160x120, long side 512 (now the defaults), the same kind of scenes run in one
process (``como3r synth --agents N --frames 16 --loop-frames 48 --overlap 0.5 --width 160
--height 120``, then ``como3r run --agent ... --prior simulated --single-process``; the
realistic simulated prior, seed 0; % of an agent's mean path, 1.2 m):

    agents             1      4      8     16
    ATE mm           1.3    7.0    8.0   62.1
    ATE % of path   0.12   0.58   0.67   5.16
    loop m          3.84   3.84   7.2   14.4    (the ring the team covers)

The size was the floor from 1 to 8 agents. At 16 it is not the links: each of the 49
admitted cross-agent edges holds (its keyframes' relative rotation after the solve within
0.05-0.95 degrees of the ground truth's), and the 12 between non-neighbours (agents i and
i + 2 or i + 3) are real views of the same facades 0.6-1.7 m apart, not false matches. Nor
is it the focal alignment: with ``gauge.align_focal=false`` the merged ATE is 63.7 mm
(5.29 %), per agent 0.14-0.67 %. What remains is the drift of a 14.4 m ring of 16 chained
maps (0.43 % of the loop) measured against one agent's 1.2 m path: each agent's segment
sits 23-120 mm off as a whole, in no agent alone. The solve puts the ring's misclosure on its
weakest junctions: after it, the relative translations of the edges around agents 4|5 and
8|9 (one or two edges each) are 100-150 mm off the ground truth's, the others' 10-50 mm;
fitted alone, the agents' scales differ from the merged one by up to 3 % (0.970-1.020),
which a chain of 16 rigid-scale segments cannot all take.

Root cause (offline on the run's session store, keyframe ATE): the agents' focal lengths.
The BA (per-keyframe Sim(3), so it can take any scale) started from the ground-truth poses
at the run's focal lengths (306-337 px after the merges and the terminal chain refinement;
true 333.6) settles 56 mm off; with every agent on the true focal length, 11 mm from the
ground truth and 13 mm from the run's own poses; all on one common but 3 % wrong focal
length, 17 mm. So it is not the solver or the scales: 16 self-calibrated cameras that
disagree by a few percent bend the ring. Re-measuring every agent pair and solving the
focal lengths jointly in least squares (``gauge.focal_loops=true``, off by default) gives
62.1 -> 59.2 mm in the run (4 agents 7.0 -> 6.4, 8 agents 8.0 -> 8.0), but worse map
accuracy at 16 (0.151 -> 0.181 m): one pair's focal estimate scatters by 2-5 %. The same
16-agent scene with the true intrinsics (``--calib``) merges at 10.0 mm, 0.83 % of one
agent's path (map F-score 0.81): the 1 % is met once the focal lengths agree.

A focal length per agent estimated inside the global BA over all its edges at once
(``gauge.focal_ba``, now the default; ``como3r.backend.focal_solver``), measured with
``--sizes 4 16 --no-decentralized --set gauge.focal_ba=true`` (branch focal41; 2 shared cores
under a load of 8-18 from other jobs: wall times and even thread CPU times are inflated;
the in-stream work, ``coord ms/kf``, is the same code as before):

    agents  kf  coord ms/kf  decodes/kf  cleanup s  ATE mm  ATE %  ATE % team  focal px (true 333.6)
         4  20         2010        3.0         237    3.05  0.254      0.0634  333.6-333.7 (was 335.7-336.1)
        16  42         3335        4.76        618    24.8   2.06      0.129   332.1-336.0 (was 270.2-336.6)

Against the table above: 4 agents 9.93 mm (0.83 %) -> 3.05 mm (0.25 %); 16 agents 223 mm
(18.6 %) -> 24.8 mm (2.06 % of one agent's path, 0.13 % of the team's), one map; per agent
2.0-7.6 mm except agent 11, 31 mm on its own. Not yet the 1 %. The terminal focal step
costs more than the chain did: the coordinator's ``focal`` stage (merges and terminal step,
wall) 118 -> 569 s at 16 agents while its verification, the same code, went 132 -> 286 s
under the heavier load: about twice the chain's cost (each Gauss-Newton iteration of the
joint solve rebuilds the dense factors and forms the focal rows in PyTorch). Offline on the stored 16-agent
single-process session above (keyframe ATE; the joint solve from the poses and focal
lengths the run ended with, 306-337 px): 62.7 -> 14.2 mm, focal lengths 331.4-334.9 px,
six Gauss-Newton iterations, 34 s of CPU. Why the multi-process 16-agent run was at 223 mm
where one process gave 62 mm: the same cause, worse. Its focal lengths ended at 270-337 px
(agents 13 and 14 at 270, 19 % short) against 306-337 px in one process; presumably (not
isolated) because in batches of up to 29 keyframes a merge aligns the moving component's
focal length on the pairs that made it at poses no BA has refined since the previous
batch, and the terminal chain carries that outwards. The joint solve on that run's stored graph brings them to 330.4-336.0 px.

With the joint solve's factors built once per solve and its blocks summed by a compiled loop
(commit 8fbf070; ``benchmarks/focal_stage.py``), ``--sizes 4 16 --no-decentralized`` (the
scenes above; 2 shared cores under a load of 6 to 23):

    agents  kf  coord ms/kf  decodes/kf  end kf  drain s  batch  cleanup s  coord MB  agent MB  ATE mm  ATE %  ATE % team
         4  20         1940        2.85       6     15.2     12        109      2390      1200    3.06  0.254      0.0635
        16  42         3190        4.81      37      122     29        117      4100      1130    32.6   2.71      0.169

The ``focal`` stage (merges' alignments and the terminal solve, wall, the loop compiled in
the 4-agent run) 185 -> 28 s at 4 agents and 569 -> 55 s at 16; the cleanup 237 -> 109 s and
618 -> 117 s. The in-stream work is the same code: 16 vs 4 agents 1.64x per keyframe (goal
1.5x), peak memory 1.72x. The merged ATE at 16 agents differs from the run above (24.8 mm)
by the multi-process schedule, not the solve (offline on one stored session the two
implementations agree within 2e-5 in focal length and 0.12 mm in position): agents (ids) 5 and 13
sit 55 and 39 mm off in the merged frame, 3.6 and 4.4 mm on their own. Agent 11 is 31.1 mm
off on its own in both runs (frames 10-12 at 56-58 mm, the step between them 220 mm for 175).
It is folder ``agent_5``: the runs took the folders in name order (``agent_10`` before
``agent_2``), so from 10 agents on the ids were not the folder numbers (now they are, which
gives the 16-agent runs other noise draws). Its front-end alone, in one process with its id,
prior and noise, tracks at 2.7 mm with the keyframes it made in the team (frames 0, 2, 12;
frame 4 matched 2 % of keyframe 0's pixels, the minimum is 5 %, so frame 2 was promoted);
in the map its last keyframe, which holds only its sequential edge (match fraction 0.38) and
an intra-agent loop edge to its first (no inter-agent edge: its 3 candidates were rejected),
ends 56 mm off: the coordinator's solves move it (its merge came with the 42nd keyframe and
no update reached the agent while it tracked). Which solve, not isolated.

Where the scale goes at 16 agents (``--scales``: per agent its merged ATE, its alignment
scale against the merged one, its focal length in the map and its own self-calibration
against the true one; per link kind of the global graph the length of its keyframes'
relative translation in the merged alignment over the true one). The 16-agent scene above in
one process (``como3r run --agent .../agent_0 ... --agent .../agent_15 --prior simulated
--single-process --set input.long_side=512``, 10 min under a load of 5-30; commit 267e5af):
merged ATE 17.2 mm (1.43 %), keyframes 14.8 mm; the agents' scales -1.9 % to +2.5 % of the
merged one, their focal lengths after the joint focal BA -1.0 % to +0.8 % (own
self-calibrations -9.0 % to +5.3 %), correlated with the scales at -0.55; sequential links
1.000 (sd 1.0 %), the agents' loop links 1.000 (sd 0.4 %), inter-agent links 0.987 (sd
2.1 %, mean relative-translation error 18 mm against 7 mm). Each link solved alone (its
second keyframe free, the insertion pointmaps; baseline over the first keyframe's median
depth, against the truth's): sequential 0.991 (sd 1.1 %), inter-agent 0.982 (sd 2.0 %),
and at the true focal length inter-agent 0.988 (sd 1.4 %). So the team's scale
inconsistency is the inter-agent links' own noise, half again that of an agent's chain, and
a third of it is the focal lengths the joint focal BA leaves (replayed offline from the
insertion pointmaps: every agent on the true focal length, keyframes 14.8 -> 11.6 mm; the
focal prior ``gauge.focal_prior`` at 0.05, 0.2 or 1.0 changes nothing, the focal lengths
are the links' optimum, not the prior's). Moving the pointmaps to the map's focal length
keeping the range instead of the depth (the simulated prior regresses true ranges along
rays of a wrong focal length; C-Eq. 16 keeps depth) gives 14.2 mm (true focal 10.1): not
the cause, and not changed. What lowers it is more inter-agent links: at
``verification.min_covisible_ratio=0.6`` 63 instead of 48, merged ATE 15.6 mm (1.30 %),
inter-agent links 0.991 (sd 1.8 %); that bar admits false pairs under the ``v2`` prior
(the ``VerificationConfig`` docstring), so it is not the default. In the multi-process
run of the table above 8 inter-agent edges were refused inside one gauge (6 by the scale
watch ``gauge.scale_alarm_log``), every one a true view of the same surface, where the
keyframe-by-keyframe run refused none: a batch's edges were judged at poses its merges left
unrefined. They are now tested once more after the batch's BA
(``InterAgentLinking._recheck_refused``); the same scene in one process with the
coordinator handed batches of 16 keyframes: 3 true edges refused, now admitted, merged ATE
18.4 -> 17.7 mm. ``--sizes 16 --no-decentralized`` before and after (2 shared cores, load
2-10; the multi-process schedule differs from run to run, one run each):

    agents  kf  coord ms/kf  decodes/kf  batch  refused  inter edges  ATE mm  ATE %  ATE % team
    16      40         3050        4.83     24        3           50    28.2   2.35      0.147
    16      40         3020        4.62     26        0           54    15.2   1.26      0.079

(before: the 3 refused edges, all between agent 2's second keyframe and agents 3 and 4, see
0.41-0.77 of a view overlapping by the ground truth.)

The session store no longer codes again what the ingest decoded (each keyframe's pointmap,
confidence, colours and sequential matches were coded twice: ``transport/codec_reuse.py``),
and a focal merge keeps a keyframe's ``X_init`` and ``X_hat`` one tensor (commits 61bd83a,
68116ae, 7d85f42, branch shed26). In the 4-agent scene run in lockstep (the reproducible
multi-process schedule, ``RuntimeOptions(lockstep=True)``; coordinator thread CPU,
``OMP_NUM_THREADS=1``) the in-stream journal went 410 -> 181 ms per keyframe and
``add_keyframes`` 2137 -> 1895 ms (load 2-10), trajectories and keyframes bit for bit the
same (in ``--single-process`` at 68116ae too: 2093 -> 1841 ms of in-stream work per
keyframe). Then ``--sizes 4 16 --no-decentralized`` at 7d85f42 (2 shared cores under a
load of 2 to 12; one run each; the "before" figures are the tables above, not run again):

    agents  kf  coord ms/kf  decodes/kf  end kf  drain s  batch  cleanup s  coord MB  agent MB  ATE mm  ATE %  ATE % team
         4  20         1838        3.5        9     22.2     12        7.7      2360      1300    3.11  0.259      0.0647
        16  40         2360        4.55      32     82.2     28       18.9      4630      1090    15.6   1.30      0.0811

16 vs 4 agents: 1.28x per keyframe (goal 1.5x; 1.56-1.64x in the tables above), peak memory
1.96x (1.72x at 8fbf070; not isolated: the store's reuse holds no coded map once a batch is
written). Per keyframe the 4-agent run did 3.5 decodes where 8fbf070's did 2.85, so its 1838
ms against 1940 understates the cut, and the ratio moves with each run's schedule too. The
coordinator still falls behind: at 4 and 16 agents 9 and 32 keyframes wait when the input
ends. Of its in-stream CPU in the lockstep run (ms per keyframe) what is left: prior decodes
608, verification 342 besides the re-encodes, re-encodes (the simulated prior's encoding from
its record) 431, ingest 293 (the lossy coding of every keyframe: 17 % of it is the decode;
agents that sent their keyframes coded, as across machines, would leave the coordinator the
decode and the store nothing to code), journal 181 (the coordinator's own pointmaps: focal
corrections at insertion and merges, 140 ms each), global BA 161, gauge 45, focal 28.

The same command on the session's final code (a batch now verified in time order, as one
keyframe at a time, and the runtime's ordering clock fixed; commit 1f559c2 plus docstrings;
2 cores at a load of 1 to 5; one run each):

    agents  kf  coord ms/kf  decodes/kf  end kf  drain s  batch  cleanup s  coord MB  agent MB  ATE mm  ATE %  ATE % team
         4  20         1840        3.6        9     22.9     10        9.5      2470      1210    3.34  0.278      0.0695
        16  40         2560        5.1       34     90.0     32        9.7      4610      1110    15.8   1.31      0.0821

16 vs 4 agents: 1.39x per keyframe, peak memory 1.87x; with the run above, 1.28-1.39x and
1.87-1.96x over two runs of each size. Decodes per keyframe stay within the budget of 6;
the backlog at the end (9 and 34 keyframes) and the 16-agent ATE (1.31 % of one agent's
path) are still over the issue's bars.

The agents now code their keyframes and pointmap refreshes in the lossy wire coding, agent
processes on pipes as across machines (their encodings exact), and the coordinator only
decodes them as they arrive (``runtime/ingest.py``; the network path no longer codes them a
second time); the pointmap coding's pinhole fit is in closed form (34 -> 5 ms per
pointmap, the same bytes). The 4-agent scene in lockstep, in-stream (before the terminal
cleanup) coordinator thread CPU per keyframe (``stage_seconds`` with ``time.perf_counter``
read as ``time.thread_time``; ``OMP_NUM_THREADS=1``, 2 shared cores at a load of 6 to 27
from other jobs, so the stages the change does not touch move by about 10 %; before, after
the ingest, after the fit too):

    ms/kf          before  after  after fit
    ingest            318     63         68   (the decode only)
    journal           211    199        197
    prior decodes     727    683        756
    verification      843    835        931   (re-encodes 440, 461, 525 of it)
    global BA         211    177        192
    gauge, focal   46, 28 51, 31     59, 37
    add_keyframes    2196   2086       2301

Trajectories, keyframe files, ``map.ply`` and ``graph.json`` byte for byte the same; the
pipes carry 1.1 MB per keyframe message instead of 6.5. ``--sizes 4 16 --no-decentralized``
with the ingest change (2 shared cores at a load of 15 to 27 from other jobs: CPU times are
inflated, wall times meaningless; one run each):

    agents  kf  coord ms/kf  decodes/kf  end kf  drain s  batch  cleanup s  coord MB  agent MB  ATE mm  ATE %  ATE % team
         4  20         2380        3.6        9     30.3     10       10.5      2330      1190    3.34  0.278      0.0695
        16  40         3030        5.1       33      106     32        138      4370      1140    15.7   1.30      0.0813

16 vs 4 agents: 1.27x per keyframe, peak memory 1.88x. ``coord ms/kf`` is the CPU time in
``add_keyframes`` and never held the ingest (which ran before it), so the cut does not show
in it; the coordinator's own CPU per keyframe falls by it. The memory ratio is where it was:
the coded maps the coordinator keeps for the store's reuse (``transport/codec_reuse.py``)
are not what grows, in the lockstep run at most 3 (0.33 MB) at any time and none at the end.
What does grow, in the same lockstep run (coordinator ``VmRSS`` after each keyframe): 410 MB
after the first, then about 55 MB per keyframe to 1497 MB after the 20th (peak 1573 MB while
streaming), 2190 MB after the terminal cleanup and 2243 MB at the end (outputs). These
scenes never page (``session.resident_keyframes`` is 8 per agent, the runs make 2.5 to 5
keyframes per agent), so the coordinator holds every keyframe whole and its memory follows
the keyframes (40 at 16 agents, 20 at 4), and the working set, per agent, grows with the
team. With ``session.resident_keyframes=1 session.encoding_cache=4`` the 4-agent lockstep
run peaked at 1837 MB instead of 2222 (the terminal cleanup's peak remains).

The coordinator's verification on threads (``verification.workers``, 2 by default;
:mod:`como3r.coordination.decode_pool`), ``OMP_NUM_THREADS=1 python benchmarks/team_scale.py
--sizes 4 16 --no-decentralized`` (branch pool41; 2 cores shared under a load of 9 to 17, so
only CPU times mean anything; one run each):

    agents  kf  coord ms/kf  verify ms/kf  pool ms/kf  wasted  decodes/kf  batch  ATE mm  ATE %  maps
         4  20          686          1580        1400       0        3.6       9    3.33  0.276     1
        16  40          919          2126        2021       6        5.1      32    15.7   1.31     1

    agents  end kf  drain s  end kf P2  drain s P2  end kf P4  drain s P4  end kf P8  drain s P8
         4       9     25.7          6        10.5          4        4.45          2        1.81
        16      34      104         31        61.0         27        39.7         23        29.1

``coord ms/kf`` is now the coordinator's thread alone (1.8-3.3 s per keyframe in the tables
above, with its verification): 4 agents 2086 ms of CPU per keyframe in all, 16 agents 2940.
The verification is 76 / 72 % of it, and 89 / 95 % of the verification ran on the pool (the
rest: a keyframe's first pair, which the coordinator verifies itself while the workers take
the others). Spread over P cores it leaves the serial part, 507 / 814 ms per keyframe (what
``add_keyframes`` does besides verifying: journal, merges and focal alignment, global BA,
retrieval; not split in CPU here): with 8 cores the 4-agent
coordinator nearly keeps up (2 keyframes waiting at the end, 1.8 s to drain, 25.7 s on one
core), the 16-agent one does not (23 keyframes, 29 s): its agents (1.05-1.89 s of CPU per
frame, a keyframe every 3.2 frames) bring one every 0.26 s, under its serial part alone.
Closing the gap at 16 agents needs that part cut or overlapped with the next batch, not more
verification cores.

That part, cut (session 29; commits 0afe625, 1de7378; ``coordination/merging.py``): a merge
decision (agreement, scale watch, the merge's ``T*``) lifted an edge's correspondences and
solved a set's Umeyama fit up to three times each, over every valid match (about 200,000
per edge at 512x384), rotating points by quaternions. Now each is computed once per
decision, points are moved by one matrix product (``geometry.lie.sim3_act_points``) and
an edge's matches are evenly subsampled to ``gauge.max_correspondences`` (8192) per
direction. A captured 16-agent run's coordinator calls replayed in one thread (the same
packets and batches, 1 / 1 / 24 / 14): in-stream thread CPU 868 -> 305 ms per keyframe,
in-stream keyframe ATE 67.66 -> 67.53 mm, the same 15 merges and 52 edges. The pipes'
decode runs on a reader thread per agent (``transport/pipe_readers.py``): the
coordinator's thread spends about 1 ms per keyframe collecting messages instead of 65-78
(not in ``coord ms/kf``, which never held it). ``--sizes 4 16 --no-decentralized`` at
1de7378 and at 97d402e (2 shared cores under a load of 3 to 22; one run each):

    agents  coord ms/kf  pool ms/kf  work ms/kf  decodes/kf  end kf P1/P2/P4/P8  drain s P8  coord MB  ATE mm  ATE %  ATE % team
         4      349/393   1267/1284   1616/1677         3.6     8/4/0/0, 8/4/0/0        0/0   2530/2810    3.34   0.277      0.0692
        16      378/410   1835/2087   2213/2497         5.1  33/28/20/11, 33/28/20/12   6.8/9.2   4070/4090    15.8   1.31       0.0817

16 vs 4 agents: work per keyframe 1.37x / 1.49x, peak memory 1.61x / 1.46x; merged ATE the
same as before to 0.01 mm. With 4 coordinator cores the 4-agent team now keeps up (no
backlog at the end; 3 keyframes before). At 16 agents the serial part is about 260-290 ms
per keyframe, near the 0.26 s at which the keyframes arrive, but the verification is 1.8-2.1
s per keyframe (5.1 decodes, the simulated prior's decodes and re-encodes 72 % of it, the
matching 25 %): in the time an agent tracks 3.2 frames the team brings 16 keyframes of up
to 6 decodes each, more than 8 cores verify (11-12 keyframes waiting, 7-9 s to drain). Keeping up there takes fewer decodes per keyframe once a team is merged, or a
coordinator with about as many cores as agents.

How many cores keep up (``serial ms/kf``, ``cores for 0``; session 34, commit fb09ba7,
``OMP_NUM_THREADS=1 python benchmarks/team_scale.py --work DIR --no-decentralized``, 2 cores
at a load of 1 to 7; one run each):

    agents  kf  coord ms/kf  serial ms/kf  decodes/kf  pool ms/kf  end kf  end kf P8  cores for 0  coord MB  ATE mm  ATE %  ATE % team
         1   4          872          19.6        1            0       0          0            1       924    1.34  0.123       0.123
         2  10          707           121        2.1        556       0          0            1      1567    3.78  0.315       0.157
         4  20          476           206        3.6       1301       8          0            4      2764    3.33  0.277      0.0692
         8  28          427           209        4.36      1609      19          0            8      2960    6.95  0.577      0.0722
        16  40          475           275        5.1       2105      33          8           32      4114    15.7   1.31      0.0816

The cores grow with the team: each keyframe's work is bounded (decodes within the budget of
6), so the work per second of input grows with the agents, and from 4 agents on a
coordinator needs about as many cores as agents, 16 agents 32. What more cores do not
shorten, the serial part, is 275 ms per keyframe at 16 agents, whose 40 keyframes arrive
over 17 s of the agents' CPU (0.42 s apart on average); that run replayed with the
serial part scaled (verification unchanged) keeps up with 16 cores at 0.75 or 0.5 of it
and 8 at 0.35; an earlier run under load (session 31: serial part 356 ms per keyframe,
keyframes 0.33 s apart) with no number of cores, with 32 at 0.5 of it. Of the serial part
in the 16-agent calls replayed in one thread (``coordinator_replay.py``, cProfile), the
merges' focal search is about half: 15 merges, 143 relative solves, 76 of them stopped at their 10
iterations with the step still shrinking by about 0.6 per iteration (Huber IRLS converges
linearly), then the global BA about a fifth. (Session 35: that profile included the first
call's numba compile, about 5.5 s of CPU once per machine; with warm caches the focal search
was 19 % of the replay's thread, and it is now one joint solve, 186 -> 82 ms a merge.)

Longer missions (session 35, ``--frames 48 --no-decentralized``: 24 frames processed per
agent, 3.8 m of path each; 4 and 8 agents at bcff8c6, 16 agents at 4227e54 with 16 GiB of
swap added, its 16 agent processes peaking at 1.4-2.0 GB each; 2 cores at a load of 2 to
25; one run each):

    agents   kf  coord ms/kf  serial ms/kf  decodes/kf  pool ms/kf  end kf  end kf P8  cores for 0  rt end kf  coord MB  agent MB  ATE mm  ATE %  ATE % team  maps
         4   32          758           512        4.56        1435      10          1            4          0      3597      1403    6.91  0.183      0.0458     1
         8   43          514           330        4.49        1665      17          0            4          7      4079      1382    11.9  0.314      0.0393     1
        16  190          678           538        5.04        2035     142         49         >256         21     12344      1954    17.7  0.466      0.0291     1

(The scenes make 8, 5.4 and 12 keyframes per agent.) Over a longer path the merged ATE is
under 1 % of one agent's path at 16 agents too, and the work per keyframe 16 vs 4 agents
is 1.24x. Two things grow with the map instead: the coordinator's peak memory (3.4x; at 16
agents its resident memory climbed from 2 to about 9.5 GB while the agents streamed, in
steps of up to 2 GB per batch, and peaked at 12.7 GB at the end of the input), and the
serial part of a batch, chiefly the in-stream global BA over the whole component: the 16
agents' calls captured and replayed in one thread (``coordinator_replay.py``, no session
store) spend 1.1 s in it for a batch at 41 keyframes and 5.2-6.6 s for one at 130-190, a
serial 226 ms per keyframe over the run. Replayed against the agents' arrivals, that run
needs more than 256 cores (its serial part alone falls behind); with no verification in
the coordinator at all one core still leaves 24 keyframes queued at the end of the input,
and keeps up only with half of the serial part too.

The same scenes again (session 36, at b89fcf4: every edge outside the working set paged,
a global BA keeping at most 256 MB of dense factors; an idle machine, 16 GiB of swap added
and unused; one run each):

    agents   kf  coord ms/kf  serial ms/kf  decodes/kf  pool ms/kf  end kf  end kf P8  cores for 0  rt end kf  coord MB  agent MB  ATE mm  ATE %  ATE % team  maps
         4   32          688           480        4.56        1304       9          0            4          0      3507      1513    6.87  0.182      0.0455     1
        16  190          718           569        5.04        2203     144         59         >256         21     11350      1881    17.8  0.468      0.0293     1

The coordinator's peak memory 16 vs 4 agents is 3.24x (3.4x before); replayed with a session
store the 16 agents' calls peak at 6.8 GB (8.5 GB before). Work per keyframe 16 vs 4 agents:
1.47x (thread and pool).

Where the whole run's peak was (session 37: the 16-agent run's coordinator sampled every 4 s
with its main thread's stack, ``py-spy dump``): not the runtime's queue but the terminal
cleanup. Its resident memory rose 7.9 -> 12.1 GB in the depth step, which kept the flattened
problems of every chunk of resident keyframes (a team keeps 8 of each agent's, 128 of 190),
and 6.2 -> 7.6 GB in the focal BA, which held every edge's dense factors. Session 37 bounds
both (the depth step keeps 256 MB of problems and spills the rest,
``backend.paged_refinement.KEEP_PROBLEM_BYTES``; the focal BA builds an edge over an even
8192 of its matches, weighed back, ``gauge.focal_max_matches``), gives what each cleanup
step let go of back to the system, and thins the in-stream global BA's edges the same way
(``global_ba.stream_max_matches``). The same command, three runs, each with one more of
these (the in-stream thinning and the depth step's budget at 4b9e3b7; the heap given back
at 383535f; the focal BA thinned at 4f5084e), an idle machine, no swap:

    agents   kf  coord ms/kf  serial ms/kf  decodes/kf  pool ms/kf  end kf  end kf P8  cores for 0  rt end kf  coord MB  agent MB  ATE mm  ATE %  ATE % team  maps
         4   32          451           294        4.56         923       9          1            2          0      3480      1445    6.91  0.183      0.0458     1
        16  190          339           229        5.04        1432     143         32         >256         21      8598      1937    17.8  0.469      0.0293     1
         4   32          450           300        4.56         927       8          0            2          0      3169      1484    6.87  0.182      0.0455     1
        16  190          341           235        5.04        1418     142         30           64         21      7963      1905    17.8  0.468      0.0293     1
         4   32          420           282        4.56         932       7          0            2          0      3054      1475    7.00  0.186      0.0464     1
        16  190          338           238        5.04        1474     142         30           64         21      6596      1824    17.8  0.470      0.0294     1
         4   32          443           295        4.56         971       8          0            2          0      3071      1533    6.96  0.184      0.0461     1
        16  190          359           248        5.04        1462     141         27           32         20      6940      1999    17.8  0.470      0.0294     1

(the last two rows: the final code, b528bac, run again.) 16 vs 4 agents with all of it: peak
memory 2.16-2.26x over two runs (3.24x before; 2.47x and 2.51x with the first changes only),
work per keyframe 1.29-1.34x (1.28-1.34x over all four). The serial part fell 480 / 569 -> 282-300
/ 229-238 ms per keyframe (the in-stream BA: replayed in one thread, 152 -> 41 ms per
keyframe). The 16 agents' calls replayed against the agents' arrivals keep up with 32-64
cores (the first run's replay left one keyframe queued at 48 to 256 cores: it arrived 0.18 s
after another at the very end of the input, and the coordinator finished 0.5 s after it;
hence its >256). The peak is now
in-stream, in a batch of up to 32 keyframes (3.3-4.3 GB after a batch's page-out, up to
6.6 GB within one); the merged ATE is the same to 0.1 mm in every run.

Session 38 (the same command, an idle machine, the coordinator sampled every 4 s as above).
With one malloc heap for the coordinator's threads (016433d, :func:`como3r.heap.
one_heap_arena`: its verification pool's and session store's threads had heaps of their
own, each keeping its own freed blocks), two runs, then with the encoding cache let go of
before the terminal cleanup (d207140: with nothing deferred it had been held through it):

    agents   kf  coord ms/kf  serial ms/kf  decodes/kf  pool ms/kf  end kf  end kf P8  cores for 0  rt end kf  coord MB  agent MB  ATE mm  ATE %  ATE % team  maps
         4   32          460           297        4.56         966       9          1            2          0      3010      1483    7.00  0.185      0.0464     1
        16  190          354           251        5.04        1541     143         32           64         21      5940      1825    17.9  0.472      0.0295     1
         4   32          471           309        4.56        1009       9          1            2          0      3025      1425    6.92  0.183      0.0458     1
        16  190          354           253        5.04        1531     144         34         >256         15      5997      1860    18.0  0.474      0.0296     1
         4   32          450           289        4.56         948       8          0            2          0      2378      1441    6.92  0.183      0.0459     1
        16  190          441           244        5.04        1576     142         35           64         15      5622      1871    17.8  0.469      0.0293     1

One heap took the 16-agent peak 6596-6940 -> 5940-5997 MB (16 vs 4 agents 1.97-1.98x).
In the second run the peak was the depth step's (6.0 GB), where the coordinator still held
the 64 encodings of its cache (1.5 GB of the simulated prior's) that nothing decodes after
the stream; the 4-agent run's peak (3.0 GB) was there too, for the same reason. Letting
them go before the cleanup lowered both peaks, the 4-agent one more (3.0 -> 2.4 GB, 16
agents 6.0 -> 5.6 GB, in-stream now, in a batch's verification): 2.36x. A byte budget on
the cache (1024 MB, 42 of the simulated prior's encodings) changed neither the re-encodes
(438) nor the peak (5631 MB against 2426) and was not kept.

Session 39 (the same command, an idle machine, one run, not sampled). The global solves
read paged-out pointmaps for the solve only (9151181), the simulated prior's descriptor
features are made 16384 keys at a time (b5bbd6e: a re-encode's transient 225 -> 96 MB),
and a batch gives freed memory back once resident memory has grown by 256 MB
(7a57baa, :class:`como3r.heap.TrimOnGrowth`):

    agents   kf  coord ms/kf  serial ms/kf  decodes/kf  pool ms/kf  end kf  end kf P8  cores for 0  rt end kf  coord MB  agent MB  ATE mm  ATE %
         4   32          428           277        4.56         990      10          1            4          0      2412      1339    6.92  0.183
        16  190          376           273        5.04        1455     145         39         >256         20      5352      1751   17.82  0.470

The 16-agent peak 5622 -> 5352 MB (2.22x the 4-agent one, which stayed at 2.4 GB); work
per keyframe 16 vs 4 1.29x. The long 16-agent capture replayed with a store peaked at 4488
MB with these changes (5430 before); a second 16-agent run, sampled, 5238 MB. A census of
a third at each new high of its resident memory (the coordinator, its runtime and every
thread's frames; 5086-5417 MB) found what the replay does not have: the keyframes waiting
for their turn, decoded (15 MB each at 512x384; 0.5-0.8 GB in the runtime's pending heap,
0.06-0.23 GB in the pipe readers' read-ahead). Held as the bytes they came in (1.2 MB) and
decoded again when their turn comes (d30bd35, :class:`como3r.runtime.agent_events.Waiting`):

    agents   kf  coord ms/kf  serial ms/kf  decodes/kf  pool ms/kf  end kf  end kf P8  cores for 0  rt end kf  coord MB  agent MB  ATE mm  ATE %
         4   32          428           281        4.56         974       9          1            2          0      2401      1347    6.92  0.183
        16  190          372           267        5.04        1520     144         40         >256         16      4869      1770   17.96  0.474

16 vs 4 agents: peak 2.03x; work per keyframe 1.35x. The second decode (46 ms per keyframe:
ingest 1.96 -> 3.42 s at 4 agents) runs on the coordinator's thread outside
``add_keyframes``, so ``coord ms/kf`` leaves it out (with it: 1.34x). The 4-agent run
overlapped another job for its first minute (its wall time 135 s against 114). Sampled
every 4 s, the 16-agent run's last in-stream batches peaked at 4.1-4.6 GB and its terminal
cleanup at 4.4-4.7 GB (after the focal BA, which leaves every rescaled keyframe's
pointmaps resident until the cleanup's end). Parking those of paged-out keyframes instead
(782f300, reverted) took the cleanup to 1.4-2.7 GB and the 16-agent peak to 4593 MB (4-agent
2262 MB: 2.03x still, the peak in-stream now), but the cleanup from 97-106 s to 252 s of
wall time: each pose pass and depth step read the parked pointmaps back from the spill.

Session 40 (the same command, an idle machine, one run each; scratch ts5-ts9). The
cleanup's focal rescale parks paged-out keyframes again, now all four pointmaps,
uncompressed, so a parked keyframe is read from the parking alone (cb71475; the 16-agent
cleanup re-run from its store: peak 5097 -> 4017 MB, 115-120 -> 136 s). Then, for 16
agents only, a byte bound on the encoding cache (``session.encoding_cache_mb=1024``, kept
as an option, off by default), whole batches of 16 (``--set
global_ba.max_batch_keyframes=16``), and batches of 32 handed over in parts of 16 with the
BA after the last (0fcfc9a, ``runtime.processes.HANDOVER_KEYFRAMES``):

    run                              agents  coord ms/kf  serial ms/kf  pool ms/kf  end kf  rt end kf  coord MB  ATE mm  ATE %  cleanup s
    ts5 parking                           4          435           285        1003       9          0      2310    6.96  0.184       14.4
    ts5 parking                          16          394           286        1591     144         20      4732    18.1  0.477        107
    ts6 + cache 1024 MB                   4          441           287        1022       9          0      2244    6.96  0.184       15.1
    ts6 + cache 1024 MB                  16          451           262        1630     144         21      4496    18.0  0.475        111
    ts7 + batches of 16                  16          527           325        1662     144         20      3942    18.1  0.476        104
    ts8 + parts of 16 (cache)             4          410           268         959       9          0      2294    6.92  0.183       13.3
    ts8 + parts of 16 (cache)            16          471           275        1598     146         12      3883    18.1  0.477        100
    ts9 parts of 16, no cache bound      16          413           297        1527     146         12      4221    17.9  0.472        109

Decodes per keyframe 4.56 / 5.04 in every run. The kept code is ts9's (the cache unbounded
in bytes): 16 vs 4 agents, peak 4221 against 2244-2310 MB, 1.83-1.88x; work per keyframe
(thread + pool) 1940 against 1369-1463 ms, 1.33-1.42x. The cache bound bought 338 MB of the
16-agent peak for 6.6 % more CPU per keyframe (re-encodes 302 -> 413): 1.68-1.73x and
1.41-1.51x. The peak is in-stream now (ts5: the global BA of the last batches, 4.5-4.7 GB
sampled; the cleanup stayed below it).

Session 41: verification on the agents (``--set verification.on_agents=true``,
:mod:`como3r.coordination.remote`), the same command otherwise (an idle machine; scratch
``/tmp/s41/ts1``-``ts4``; ts1 ran the in-stream BA after every hand-over of the agents'
replies, ts2 to ts4 only when no batch of keyframes follows, whose BA then solves with
their edges; ts4 at the final code, b95e2f2):

    run  agents  coord ms/kf  agents ms/kf  end kf  cores for 0  rt end kf  out at end  coord MB  agent MB  ATE mm  ATE %  kB/robot
    ts1       4          337          1598       1            1          0           0      2197      1377    6.95  0.184     38562
    ts1      16          451          2193       2         >256         12          13      4138      1755    20.2  0.533     70183
    ts2       4          344          1624       1            1          0           0      2179      1357    6.81  0.181     38449
    ts2      16          350          2272       1            1         10          23      4062      1735    20.1  0.530     70179
    ts3       4          328          1581       1            1          0           0      2181      1382    6.36  0.169     38390
    ts3      16          358          2169       1            1         20          27      3967      1766    19.4  0.512     70188
    ts4       4          315          1534       1            1          1           4      2186      1425    6.88  0.182     38559
    ts4      16          325          2093       1            1         21          32      4075      1765    19.3  0.508     70164

The coordinator verifies nothing (``pool ms/kf`` 0; decodes per keyframe 4.44-4.50 /
5.02-5.03, all the agents'), so its work per keyframe is what the serial part was, 16 vs 4
agents 1.02-1.09x in each run (ts2-ts4; 1.14x at most across them), and replayed against the agents' arrivals on ONE core it keeps up:
one keyframe in hand when the input ends, none queued, drained in 0.13-0.65 s (144-146
keyframes waiting when it verified itself, session 40). Peak memory 16 vs 4 agents
1.82-1.87x. The agents pay: 2.1-2.3 s of CPU per keyframe verifying (re-encodes 44 %,
decodes 35 %, matching 21 %), their CPU per frame 3.26-3.34 s at 16 agents against 2.14 s
when the coordinator verifies (session 39's run of this scene); the requests carry every
keyframe image a pair needs and here the simulated prior's ground-truth records (3.9 MB a
request, 741 MB of 1122 at 16 agents; MASt3R's carry the images alone), 70 MB per robot
against 15. ``out at end``: 23-32 keyframes' verifications were still with the agents when
their input ended, on this machine where the 16 agents share its 2 cores (in the replay
each has its own, the verification it did after its last frame spread over its frames).
The merged ATE at 16 agents 19.3-20.1 mm against 17.9-18.1: an edge enters the graph when
its reply comes back, after the merges of the keyframes verified before it.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from rich.console import Console

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _tables import print_table, write_csv  # noqa: E402

from como3r.config import Config, apply_overrides  # noqa: E402
from como3r.coordination.coordinator import Coordinator  # noqa: E402
from como3r.data.synth import synthesize  # noqa: E402
from como3r.geometry.lie import sim3_act  # noqa: E402
from como3r.geometry.umeyama import umeyama_sim3  # noqa: E402
from como3r.io.tum import read_tum  # noqa: E402
from como3r.progress import AgentProgress  # noqa: E402
from como3r.runtime.multiprocess import run_multiprocess  # noqa: E402
from como3r.runtime.pipeline import PriorSpec  # noqa: E402
from como3r.store.reader import read_session  # noqa: E402

try:
    from team_scale_decentralized import decentralized_rows  # noqa: E402
except ImportError:  # the decentralized benchmark is not in this tree
    decentralized_rows = None

COLUMNS = (
    "agents",
    "seed",
    "keyframes",
    "coord ms/kf",
    "coord s/s input",
    "serial ms/kf",
    "decodes/kf",
    "verify ms/kf",
    "pool ms/kf",
    "agents ms/kf",
    "wasted",
    "skipped",
    "deferred",
    "at end",
    "idle s",
    "at end s",
    "end kf",
    "end s",
    "drain s",
    "cores for 0",
    "rt end kf",
    "rt max kf",
    "out at end",
    "batch",
    "cleanup s",
    "coord MB",
    "agent MB",
    "ATE mm",
    "path m",
    "ATE %",
    "ATE % team",
    "maps",
    "kB/robot",
)
#: the coordinator's cores the backlog is replayed for besides one (``--coordinator-cores``)
CORES = (2, 4, 8)


# ------------------------------------------------------------------ one run (a process of its own)


def _proc_status(pid: int | str) -> float:
    """``VmHWM`` of a process [MB] (0 if it is gone or ended)."""
    try:
        lines = Path(f"/proc/{pid}/status").read_text().splitlines()
    except OSError:
        return 0.0
    fields = dict(line.split(":", 1) for line in lines if ":" in line)
    if "VmHWM" not in fields:  # a process that just ended (a zombie) has no memory left
        return 0.0
    return int(fields["VmHWM"].split()[0]) / 1024


def _proc_cpu(pid: int) -> float | None:
    """User + system CPU seconds of a process (None if it is gone)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return (int(stat[11]) + int(stat[12])) / os.sysconf("SC_CLK_TCK")


def _children() -> list[int]:
    """This process's agent processes (multiprocessing spawn children)."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            command = (entry / "cmdline").read_bytes()
        except (OSError, IndexError, ValueError):
            continue
        if ppid == os.getpid() and b"spawn_main" in command and b"resource_tracker" not in command:
            pids.append(int(entry.name))
    return pids


#: one call of ``add_keyframe(s)``: the coordinator thread's CPU seconds, the ``(agent,
#: kf_id, timestamp)`` of the keyframes it took, and of its CPU the verification done in line
#: and the pool's workers' CPU seconds during it (both 0 in runs recorded before them); a
#: call without keyframes is an idle coordinator's ``verify_deferred_one``. With
#: ``verification.on_agents`` a fifth element ``"verified"`` marks a call of
#: ``add_verified``: the agents' verifications of the keyframes it names admitted (its CPU is
#: those keyframes' work too; runs recorded before it have four elements)
Call = tuple[Any, ...]

#: the fifth element of a :data:`Call` of ``add_verified``
VERIFIED = "verified"


def _verification_cpu(coordinator: Coordinator) -> tuple[float, float]:
    """The coordinator's verification CPU so far: in its thread, on its pool."""
    stats = coordinator.stats
    return stats.verification_cpu, sum(stats.pool_seconds.values())


class _Timed:
    """The coordinator's CPU time per call of ``add_keyframe(s)``, with the keyframes and
    its verification's CPU (:data:`Call`)."""

    def __init__(self) -> None:
        self.calls: list[Call] = []
        #: CPU seconds (thread and pool) of the deferred verification at the end of the input
        self.at_end = 0.0

    def install(self) -> None:
        many = Coordinator.add_keyframes
        calls = self.calls

        def add_keyframes(coordinator: Coordinator, packets: Any, solve: bool = True) -> Any:
            start, (inline, pool) = time.thread_time(), _verification_cpu(coordinator)
            updates = many(coordinator, packets, solve)
            keys = [(p.agent, p.kf_id, p.timestamp) for p in packets]
            after = _verification_cpu(coordinator)
            calls.append((time.thread_time() - start, keys, after[0] - inline, after[1] - pool))
            return updates

        def add_keyframe(coordinator: Coordinator, packet: Any) -> Any:
            return add_keyframes(coordinator, [packet])

        one = Coordinator.verify_deferred_one

        def verify_deferred_one(coordinator: Coordinator) -> Any:
            # an idle coordinator's catch-up: a call without keyframes (the replay leaves it
            # out: it ran while no keyframe waited)
            start, (inline, pool) = time.thread_time(), _verification_cpu(coordinator)
            before = coordinator.stats.verification_deferred
            updates = one(coordinator)
            if coordinator.stats.verification_deferred > before:
                after = _verification_cpu(coordinator)
                calls.append((time.thread_time() - start, [], after[0] - inline, after[1] - pool))
            return updates

        verified = Coordinator.add_verified

        def add_verified(coordinator: Coordinator, replies: Any, solve: bool = True) -> Any:
            jobs = [coordinator._outstanding.get(r.request) for r in replies]
            start = time.thread_time()
            updates = verified(coordinator, replies, solve)
            keys = [(*job.query, math.nan) for job in jobs if job is not None]
            if keys:
                calls.append((time.thread_time() - start, keys, 0.0, 0.0, VERIFIED))
            return updates

        Coordinator.add_verified = add_verified  # type: ignore[method-assign]
        Coordinator.add_keyframe = add_keyframe  # type: ignore[method-assign]
        Coordinator.add_keyframes = add_keyframes  # type: ignore[method-assign]
        Coordinator.verify_deferred_one = verify_deferred_one  # type: ignore[method-assign]
        remaining = Coordinator._verify_all_deferred

        def verify_all_deferred(coordinator: Coordinator) -> Any:
            start, (_, pool) = time.thread_time(), _verification_cpu(coordinator)
            updates = remaining(coordinator)
            self.at_end += time.thread_time() - start + _verification_cpu(coordinator)[1] - pool
            return updates

        Coordinator._verify_all_deferred = verify_all_deferred  # type: ignore[method-assign]


def run_one(
    scene: Path, out: Path, long_side: int, overrides: list[str] | None = None
) -> dict[str, Any]:
    """One team run; what the table needs, measured (JSON-ready)."""
    # agent ids in folder-number order (by name, agent_10 would come before agent_2)
    agents = sorted(scene.glob("agent_*"), key=lambda p: int(p.name.split("_")[1]))
    config = apply_overrides(Config(), [f"input.long_side={long_side}", *(overrides or [])])
    timed = _Timed()
    timed.install()
    # per progress event of agent a: (a, frames done, {pid: cpu seconds})
    samples: list[tuple[int, int, dict[int, float]]] = []
    agent_peak: dict[int, float] = {}

    def progress(event: object) -> None:
        if not isinstance(event, AgentProgress):
            return
        cpu = {}
        for pid in _children():
            seconds = _proc_cpu(pid)
            if seconds is not None:
                cpu[pid] = seconds
            agent_peak[pid] = max(agent_peak.get(pid, 0.0), _proc_status(pid))
        samples.append((event.agent, event.frames_done, cpu))

    run_multiprocess(agents, out, config, PriorSpec("simulated"), overwrite=True, progress=progress)
    metrics = json.loads((out / "metrics.json").read_text())
    entries = {entry["agent"]: entry for entry in metrics["runtime"]["agents"]}
    cpu_per_frame = {}
    for agent, entry in entries.items():
        pid = entry["pid"]
        mine = [(done, cpu[pid]) for a, done, cpu in samples if a == agent and pid in cpu]
        if len(mine) >= 2 and mine[-1][0] > mine[0][0]:
            cpu_per_frame[agent] = (mine[-1][1] - mine[0][1]) / (mine[-1][0] - mine[0][0])
            # what it verified for the coordinator after its last frame is its frames' work
            # too (verification.on_agents; between frames /proc counted it already)
            served = entry.get("verification") or {}
            after = served.get("cpu_seconds_after_stream", 0.0)
            cpu_per_frame[agent] += after / max(1, entry["frames_done"])
    return {
        "calls": timed.calls,
        "deferred_at_end_cpu": timed.at_end,
        "cpu_per_frame": cpu_per_frame,
        "coordinator_peak_mb": _proc_status("self"),
        "agent_peak_mb": max(agent_peak.values(), default=0.0),
    }


# ------------------------------------------------------------------ scales (--scales)


def _aligned_scale(est: np.ndarray, gt: np.ndarray) -> tuple[float, np.ndarray]:
    """Scale of the similarity taking positions ``est (N, 3)`` onto ``gt``, and the aligned
    positions."""
    points = torch.from_numpy(est)
    T = umeyama_sim3(points, torch.from_numpy(gt))
    return float(T[7]), sim3_act(T, points).numpy()


def _frames(scene: Path, out: Path, agent: int) -> tuple[np.ndarray, np.ndarray]:
    """An agent's estimated frame positions (``trajectories/``) and their ground truth."""
    est = read_tum(out / "trajectories" / f"agent_{agent}.txt")
    gt = read_tum(scene / f"agent_{agent}" / "groundtruth.txt")
    rows = [int(np.argmin(np.abs(gt.timestamps - t))) for t in est.timestamps]
    return (
        np.asarray(est.T_WC[:, :3], dtype=np.float64),
        np.asarray(gt.T_WC[rows, :3], dtype=np.float64),
    )


def scale_rows(scene: Path, out: Path) -> tuple[list[dict], list[dict]]:
    """Where a team's scale goes (issue 41), from a finished run's trajectories, session
    store and the scene's ground truth: per agent its merged ATE (the team's similarity),
    its alignment scale against the merged one (the similarity fitted to the agent's frames
    alone over the one fitted to all; above 0: the agent is mapped too small), its focal
    length in the map and its own self-calibration against the true one (``calib.txt`` at
    the run's long side); per link kind of the global graph, the length of its keyframes'
    relative translation in the keyframes' merged alignment over the true one."""
    session = read_session(out / "session.db")
    graph = session.graph
    agents = sorted(graph.local_to_global)
    frames = {agent: _frames(scene, out, agent) for agent in agents}
    merged, aligned = _aligned_scale(
        np.concatenate([frames[a][0] for a in agents]),
        np.concatenate([frames[a][1] for a in agents]),
    )
    calib = np.loadtxt(scene / "agent_0" / "calib.txt")
    longest = 2 * (max(calib[2], calib[3]) + 0.5)  # the principal point sits at the centre
    true_focal = float(calib[0]) * session.config.input.long_side / longest
    per_agent, start = [], 0
    for agent in agents:
        est, gt = frames[agent]
        error = aligned[start : start + len(est)] - gt
        start += len(est)
        focal, own = graph.agent_focal(agent), graph.own_focal.get(agent)
        per_agent.append(
            {
                "agent": agent,
                "ATE mm": 1000.0 * float(np.sqrt((error**2).sum(axis=1).mean())),
                "scale %": 100.0 * (_aligned_scale(est, gt)[0] / merged - 1.0),
                "focal %": 100.0 * (focal / true_focal - 1.0) if focal else float("nan"),
                "own focal %": 100.0 * (own / true_focal - 1.0) if own else float("nan"),
            }
        )
    centres, truth = {}, {}
    for agent in agents:
        gt = read_tum(scene / f"agent_{agent}" / "groundtruth.txt")
        for g in graph.agent_keyframes(agent):
            k = int(np.argmin(np.abs(gt.timestamps - graph.keyframes[g].timestamp)))
            centres[g] = graph.keyframes[g].T_WC[:3].double().numpy()
            truth[g] = np.asarray(gt.T_WC[k, :3], dtype=np.float64)
    order = sorted(centres)
    _, placed = _aligned_scale(
        np.stack([centres[g] for g in order]), np.stack([truth[g] for g in order])
    )
    at = dict(zip(order, placed))
    ratios: dict[str, list[float]] = {}
    for link in graph.links:
        true_length = float(np.linalg.norm(truth[link.j] - truth[link.i]))
        if true_length > 0:
            length = float(np.linalg.norm(at[link.j] - at[link.i]))
            ratios.setdefault(link.kind, []).append(length / true_length)
    per_kind = [
        {
            "link": kind,
            "links": len(v),
            "length ratio": float(np.mean(v)),
            "sd %": 100.0 * float(np.std(v)),
        }
        for kind, v in sorted(ratios.items())
    ]
    return per_agent, per_kind


# ------------------------------------------------------------------ the table


def serial_seconds(call: Sequence[Any]) -> float:
    """The CPU seconds of one recorded call that more cores do not shorten: the
    coordinator thread's less the verification it did in line."""
    return call[0] - (call[2] if len(call) > 2 else 0.0)


def call_seconds(call: Sequence[Any], cores: int) -> float:
    """Seconds a coordinator with ``cores`` cores needs for one recorded call (module
    docstring): its serial CPU on one core, then its verification's spread over all."""
    inline, pool = tuple(call[2:4]) or (0.0, 0.0)
    return serial_seconds(call) + (inline + pool) / cores


#: the most cores :func:`cores_to_keep_up` tries
MOST_CORES = 256


def cores_to_keep_up(
    calls: Sequence[Sequence[Any]],
    frame_times: dict[int, np.ndarray],
    cpu_per_frame: dict[int, float],
) -> int | str:
    """The fewest cores, of 1, 2, 4, ... :data:`MOST_CORES`, with which the replayed
    coordinator (:func:`replay`) keeps up: no keyframe queued at the end of the input (at
    most the last one in hand); more than that (the serial part alone falls behind) is
    reported as ``">256"``."""
    cores = 1
    while cores <= MOST_CORES:
        if replay(calls, frame_times, cpu_per_frame, cores)[3] == 0:
            return cores
        cores *= 2
    return f">{MOST_CORES}"


def replay(
    calls: Sequence[Sequence[Any]],
    frame_times: dict[int, np.ndarray],
    cpu_per_frame: dict[int, float],
    cores: int = 1,
) -> tuple[int, float, float, int]:
    """The backlog at the end of the input at the agents' measured frame rates (module
    docstring): ``(keyframes waiting, seconds of input behind, seconds to drain, keyframes
    queued)``. Waiting are those arrived and not done, the one in hand included; queued
    those of them not yet begun (a coordinator that keeps up has none: at most the
    keyframe of the last moment in hand).

    Args:
        calls: the coordinator's calls (:data:`Call`; runs recorded before the
            verification's CPU was have ``(seconds, keys)`` only: all serial).
        frame_times: each agent's processed frames' timestamps [s], in order.
        cpu_per_frame: each agent's CPU seconds per frame.
        cores: the coordinator's cores (:func:`call_seconds`).
    """
    taken: dict[tuple[int, int], list[float]] = {}  # [arrival [s], timestamp [s], service [s]]
    for call in calls:
        keys = call[1]
        if len(call) > 4 and call[4] == VERIFIED:
            continue
        for agent, kf_id, stamp in keys:
            frames = int(np.searchsorted(frame_times[agent], stamp + 1e-9))  # frames done
            arrival = frames * cpu_per_frame.get(agent, 0.0)
            entry = taken.setdefault((agent, kf_id), [arrival, stamp, 0.0])
            entry[2] += call_seconds(call, cores) / len(keys)
    for call in calls:  # the admission of the agents' verifications: their keyframes' work
        if len(call) > 4 and call[4] == VERIFIED:
            for agent, kf_id, _ in call[1]:
                taken[(agent, kf_id)][2] += call_seconds(call, cores) / len(call[1])
    keyframes = sorted(tuple(entry) for entry in taken.values())
    if not keyframes:
        return 0, 0.0, 0.0, 0
    end = max(len(t) * cpu_per_frame.get(a, 0.0) for a, t in frame_times.items())
    free, done, queued = 0.0, [], 0
    for arrival, stamp, service in sorted(keyframes):
        begun = max(free, arrival)
        queued += arrival <= end < begun
        free = begun + service
        done.append((free, arrival, stamp))
    waiting = [(f, s) for f, a, s in done if a <= end < f]
    handled = [s for f, a, s in done if f <= end]
    newest = max(s for f, a, s in done if a <= end)
    behind = newest - max(handled) if handled else newest - min(s for _, s in waiting)
    last = max(f for f, _, _ in done)
    return len(waiting), max(0.0, behind) if waiting else 0.0, max(0.0, last - end), queued


def _path_length(groundtruth: Path) -> float:
    positions = np.asarray(read_tum(groundtruth).T_WC)[:, :3]
    return float(np.linalg.norm(np.diff(positions, axis=0), axis=1).sum())


def row(
    agents: int,
    seed: int,
    scene: Path,
    out: Path,
    measured: dict[str, Any],
    cores: Sequence[int] = CORES,
) -> dict:
    """One line of the table from a run's folder and its measurements; the backlog also
    for a coordinator of each of ``cores`` cores."""
    metrics = json.loads((out / "metrics.json").read_text())
    coordinator, runtime = metrics["coordinator"], metrics["runtime"]
    keyframes = max(1, coordinator["keyframes"])
    calls = measured["calls"]
    cpu = sum(call[0] for call in calls)
    verify = sum(call[2] + call[3] for call in calls if len(call) > 2)
    pool = sum(call[3] for call in calls if len(call) > 2)
    frame_times = {
        a: np.asarray(read_tum(out / "trajectories" / f"agent_{a}.txt").timestamps)
        for a in range(agents)
    }
    input_seconds = max(float(t[-1] - t[0]) for t in frame_times.values() if len(t))
    agent_cpu = {int(k): v for k, v in measured["cpu_per_frame"].items()}
    waiting, behind, drain, _ = replay(calls, frame_times, agent_cpu)
    per_cores = {}
    for p in cores:
        end, _, drained, _ = replay(calls, frame_times, agent_cpu, p)
        per_cores[f"end kf P{p}"], per_cores[f"drain s P{p}"] = end, drained
    serial = sum(serial_seconds(call) for call in calls if call[1])
    paths = [_path_length(scene / f"agent_{a}" / "groundtruth.txt") for a in range(agents)]
    ate_json = metrics.get("ate", {})
    merged = ate_json.get("merged") or next(iter(ate_json.get("agents", [])), None)
    rmse = merged["ate"]["rmse"] if merged else float("nan")  # one agent: its own
    backlog = runtime.get("backlog", {})
    per_robot = [
        sum(a["bytes_to_agent"].values()) + sum(a["bytes_from_agent"].values())
        for a in runtime["agents"]
    ]
    return {
        "agents": agents,
        "seed": seed,
        "keyframes": coordinator["keyframes"],
        "coord ms/kf": 1000.0 * cpu / keyframes,
        "coord s/s input": cpu / input_seconds if input_seconds > 0 else float("nan"),
        "serial ms/kf": 1000.0 * serial / keyframes,
        "decodes/kf": coordinator["prior_decodes"] / keyframes,
        "verify ms/kf": 1000.0 * verify / keyframes,
        "pool ms/kf": 1000.0 * pool / keyframes,
        "agents ms/kf": 1000.0 * sum(coordinator.get("remote_seconds", {}).values()) / keyframes,
        "wasted": coordinator.get("pool_wasted_decodes", 0),
        "skipped": coordinator.get("verification_skipped", 0),
        "deferred": coordinator.get("verification_deferred", 0),
        "at end": coordinator.get("verification_deferred_at_finish", 0),
        "idle s": sum(call[0] + call[3] for call in calls if len(call) > 2 and not call[1]),
        "at end s": measured.get("deferred_at_end_cpu", "-"),
        "end kf": waiting,
        "end s": behind,
        "drain s": drain,
        **per_cores,
        "cores for 0": cores_to_keep_up(calls, frame_times, agent_cpu),
        "rt end kf": backlog.get("end_keyframes", "-"),
        "rt max kf": backlog.get("max_keyframes", "-"),
        "out at end": "-"
        if runtime.get("verification_out_at_end") is None
        else runtime["verification_out_at_end"],
        "batch": coordinator.get("largest_batch", "-"),
        "cleanup s": coordinator["stage_seconds"].get("cleanup", 0.0),
        "coord MB": measured["coordinator_peak_mb"],
        "agent MB": measured["agent_peak_mb"],
        "ATE mm": 1000.0 * rmse,
        "path m": float(np.mean(paths)),
        "ATE %": 100.0 * rmse / float(np.mean(paths)),
        "ATE % team": 100.0 * rmse / float(np.sum(paths)),
        "maps": len(metrics["components"]),
        "kB/robot": float(np.mean(per_robot)) / 1000.0,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=Path("/tmp/team_scale"))
    parser.add_argument("--sizes", type=int, nargs="+", default=[1, 2, 4, 8, 16])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--frames", type=int, default=16, help="rendered frames per agent")
    parser.add_argument("--loop-frames", type=int, default=48, help="synth --loop-frames")
    parser.add_argument("--overlap", type=float, default=0.5)
    # 160x120 at the prior's default 512: one agent alone at 0.12 % of path (single
    # process); at 96x72 (long side 96) it is at 1.9 %, above the 1 % the teams must reach
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument("--long-side", type=int, default=512, help="input.long_side (default: 512)")
    parser.add_argument(
        "--reuse",
        action="store_true",
        help="tabulate the runs already in --work instead of running them again",
    )
    parser.add_argument("--csv", type=Path, default=None, help="also write the rows here")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a configuration override for every run (as como3r run --set)",
    )
    parser.add_argument(
        "--decentralized",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="also print the decentralized table (team_scale_decentralized.py)",
    )
    parser.add_argument(
        "--scales",
        action="store_true",
        help="print where the scale goes in the runs already in --work (per agent and link kind)",
    )
    parser.add_argument(
        "--coordinator-cores",
        type=int,
        nargs="+",
        default=list(CORES),
        metavar="P",
        help="also replay the backlog for a coordinator of P cores (its verification spread "
        "over them; default: 2 4 8)",
    )
    parser.add_argument(
        "--one", nargs=3, metavar=("SCENE", "OUT", "LONG_SIDE"), help=argparse.SUPPRESS
    )
    args = parser.parse_args()
    if args.one:
        measured = run_one(Path(args.one[0]), Path(args.one[1]), int(args.one[2]), args.set)
        print(json.dumps(measured))
        return
    long_side = args.long_side
    console = Console(width=240)
    if args.scales:
        for agents in args.sizes:
            for seed in args.seeds:
                out = args.work / f"run_a{agents}_s{seed}"
                if (out / "session.db").exists():
                    per_agent, per_kind = scale_rows(args.work / f"scene_a{agents}_s{seed}", out)
                    title = f"{agents} agents, seed {seed}"
                    print_table(console, per_agent, list(per_agent[0]), title)
                    print_table(console, per_kind, list(per_kind[0]), title)
        return
    console.print(
        f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores; "
        f"{args.width}x{args.height} (long side {long_side}), {args.frames} frames per agent "
        f"rendered, overlap {args.overlap}, simulated prior"
    )
    rows = []
    for agents in args.sizes:
        for seed in args.seeds:
            scene = args.work / f"scene_a{agents}_s{seed}"
            if not (scene / "scene.json").exists():
                scene.mkdir(parents=True, exist_ok=True)
                synthesize(
                    scene,
                    agents=agents,
                    seed=seed,
                    overlap=args.overlap,
                    frames=args.frames,
                    preset="default",
                    width=args.width,
                    height=args.height,
                    loop_frames=args.loop_frames,
                    progress=None,
                )
            out = args.work / f"run_a{agents}_s{seed}"
            kept = out / "team_scale.json"
            if not (args.reuse and kept.exists()):
                command = [sys.executable, __file__, "--one", str(scene), str(out), str(long_side)]
                command += [f"--set={override}" for override in args.set]
                start = time.perf_counter()
                done = subprocess.run(command, stdout=subprocess.PIPE, text=True, check=False)
                if done.returncode:
                    raise SystemExit(f"the {agents}-agent run (seed {seed}) failed")
                kept.write_text(done.stdout.strip().splitlines()[-1])
                console.print(f"{agents} agents, seed {seed}: {time.perf_counter() - start:.0f} s")
            measured = json.loads(kept.read_text())
            rows.append(row(agents, seed, scene, out, measured, args.coordinator_cores))
    columns = list(COLUMNS)
    at = columns.index("drain s") + 1
    columns[at:at] = [f"{k} P{p}" for p in args.coordinator_cores for k in ("end kf", "drain s")]
    print_table(console, rows, columns, "centralized teams")
    if args.csv is not None:
        write_csv(args.csv, rows, columns)
    if args.decentralized:
        if decentralized_rows is None:
            console.print(
                "(team_scale_decentralized.py is not in this tree: no decentralized table)"
            )
        else:
            robots = decentralized_rows()
            if robots:
                print_table(console, robots, list(robots[0]), "decentralized teams")


if __name__ == "__main__":
    main()
