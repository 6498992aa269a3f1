"""Wrong loops against the decentralized pose graph: merged ATE and scale error per rate.

A pose-graph-level benchmark (no images, no prior: seconds on one CPU core). Three robots
drive overlapping circles (keyframes every ~0.5 m); their metric odometry drifts (0.3 deg
and 2 % of the step per keyframe); true inter-robot loops join keyframes less than 1.5
spacings apart, measured as a prior would (1 deg, 4 cm noise, translation in the prior's
own units: divided by the scene's random prior scale, which varies 15 % from pair to pair;
the F-Eq. 6 factor recovers each pair's within 10 %).
Wrong loops are then added until they are 0, 5, 20 or 50 % of all loops, half of each
kind the issue names:

* look-alike places: keyframes more than 4 spacings apart registered to a plausible
  close-range pose (as an aliased façade registers);
* true places with a wrong scale: a true pair whose prior translation is 1.6-3x too long
  or too short (the F-Eq. 6 factor, from the robot's own pair, does not see it).

Each solver setting runs the same missions in two rounds, as the robots do (round 1: the
first half of the keyframes and the loops among them; round 2: everything, from round 1's
estimates); a solve the scale-collapse alarm holds back leaves the robots where they were.
The merged ATE is the RMSE of all robots' final keyframe positions after one Sim(3)
alignment to the ground truth, in % of the path length, and the scale error is
``|s - 1|`` of that alignment (means over the seeds); ``merged log`` is the largest
round-2 merged scale change and ``alarms`` counts the solves held back.

    PYTHONPATH=src python benchmarks/wrong_loops.py --seeds 5

Measured (5 seeds, 14 s CPU; ATE and scale error are means, ``merged log`` the largest):

    setting                      wrong % loops  kept wrong kept ATE % path scale err % merged log alarms
    old default: lm                    0    26    26        0.0      0.096        0.29      0.003      0
    old default: lm                   20    33    30        4.2      1.947        8.55      0.989      0
    old default: lm                   50    53    40       13.4      2.977        4.46      0.980      0
    gnc                               20    33    30        4.2      0.096        0.29      0.907      0
    gnc                               50    53    40       13.4      0.096        0.30      0.969      0
    lm + alarm                        20    33    30        4.2      3.323       30.82      0.989      3
    lm + pcm + alarm                  20    33    26        2.0      0.096        0.29      0.003      0
    lm + pcm + alarm                  50    53    26        6.8      0.238        0.47      0.049      0
    default: gnc + pcm + alarm         0    26    26        0.0      0.096        0.29      0.003      0
    default: gnc + pcm + alarm         5    28    26        0.2      0.096        0.29      0.003      0
    default: gnc + pcm + alarm        20    33    26        2.0      0.096        0.29      0.003      0
    default: gnc + pcm + alarm        50    53    26        6.8      0.100        0.30      0.055      0

Before the floor on loop translation noise (``decentralized.loop_lever_arm_depths``: 0.5
keyframe spacings here, issue 37; this benchmark's loops carry 4 cm of noise, more precise
than the prior's)
the default's rows were 0.089 % at 0, 5 and 20 % wrong and 0.093 % at 50 % (scale error
0.22 %). With pairwise consistency weighing loops with that floor and the odometry's
unconverged start discounted (``decentralized.vio_start_scale_error`` 0.3, session 26; since
session 28 the default for robots whose ``odometry.json`` declares a ``vio``, while this
benchmark's robots declare nothing) the default's rows are unchanged; the bent solves without pairwise consistency moved (``old
default: lm`` at 20 % wrong 1.888 -> 1.947 %, at 50 % 3.175 -> 2.977 %).

With 20 % wrong loops the default's merged ATE is 1.00x the clean run's and its scale
error 0.29 %. The alarm alone does not help: it holds back round 2 but the robots keep
round 1's map, already bent (``lm + alarm`` is worse than ``old default``); behind pairwise
consistency it never fires here. The look-alike loops of this benchmark are independent of
each other; a façade repeated along a street gives aliased loops that agree with each
other, which ``tests/decentralized/test_flocc_aliasing.py`` covers on rendered images.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass, replace

import gtsam
import numpy as np

from como3r.config_decentralized import DecentralizedConfig, PoseGraphConfig
from como3r.decentralized.consistency import LoopCheck, solve_shares
from como3r.decentralized.messages import PoseGraphShare
from como3r.decentralized.pose_graph_problem import LoopClosure, from_pose3, to_pose3

ROBOTS = 3
KEYFRAMES = 40
RADIUS = 3.0
RATES = (0.0, 0.05, 0.2, 0.5)


@dataclass
class Scenario:
    truth: dict[int, list[gtsam.Pose3]]
    odometry: dict[int, np.ndarray]
    true_loops: list[LoopClosure]
    spacing: float
    scene_scale: float


def _trajectory(robot: int) -> list[gtsam.Pose3]:
    """Keyframes on a circle of its own centre and phase, looking along the path."""
    centre = np.array([0.8 * math.cos(2.1 * robot), 0.8 * math.sin(2.1 * robot), 0.2 * robot])
    poses = []
    for k in range(KEYFRAMES):
        angle = 2 * math.pi * k / KEYFRAMES + 1.3 * robot
        R = gtsam.Rot3.Ypr(angle + math.pi / 2, 0.0, 0.0)
        t = centre + RADIUS * np.array([math.cos(angle), math.sin(angle), 0.0])
        poses.append(gtsam.Pose3(R, t))
    return poses


def _noise(rng: np.random.Generator, rot: float, trans: float) -> gtsam.Pose3:
    return gtsam.Pose3.Expmap(
        np.concatenate([rot * rng.normal(size=3), trans * rng.normal(size=3)])
    )


def _loop(
    a: int,
    ka: int,
    b: int,
    kb: int,
    relative: gtsam.Pose3,
    scene_scale: float,
    rng: np.random.Generator,
) -> LoopClosure:
    """A loop measured by a prior whose scale is the scene's within 15 %; F-Eq. 6 recovers
    it within 10 %."""
    prior_scale = scene_scale * math.exp(rng.normal(0.0, 0.15))
    T = from_pose3(gtsam.Pose3(relative.rotation(), relative.translation() / prior_scale))
    probability = float(rng.uniform(0.6, 0.95))
    return LoopClosure(
        a, ka, b, kb, T, prior_scale * math.exp(rng.normal(0.0, 0.1)), 0.5, probability, 300
    )


def scenario(seed: int) -> Scenario:
    rng = np.random.default_rng(seed)
    truth = {r: _trajectory(r) for r in range(ROBOTS)}
    spacing = float(np.linalg.norm(truth[0][1].translation() - truth[0][0].translation()))
    scene_scale = math.exp(rng.normal(0.0, 0.5))
    odometry = {}
    for r, poses in truth.items():
        frame = gtsam.Pose3(gtsam.Rot3.Rodrigues(rng.normal(size=3)), 5 * rng.normal(size=3))
        current = frame
        rows = [from_pose3(current)]
        for k in range(1, KEYFRAMES):
            step = poses[k - 1].between(poses[k])
            current = current.compose(step).compose(_noise(rng, math.radians(0.3), 0.02 * spacing))
            rows.append(from_pose3(current))
        odometry[r] = np.stack(rows)
    loops = []
    for a in range(ROBOTS):
        for b in range(a + 1, ROBOTS):
            for ka in range(KEYFRAMES):
                for kb in range(KEYFRAMES):
                    relative = truth[a][ka].between(truth[b][kb])
                    angle = np.linalg.norm(gtsam.Rot3.Logmap(relative.rotation()))
                    if (
                        np.linalg.norm(relative.translation()) < 1.5 * spacing
                        and angle < math.radians(30)
                        and rng.random() < 0.5
                    ):
                        noisy = relative.compose(_noise(rng, math.radians(1.0), 0.04))
                        loops.append(_loop(a, ka, b, kb, noisy, scene_scale, rng))
    return Scenario(truth, odometry, loops, spacing, scene_scale)


def wrong_loops(data: Scenario, count: int, rng: np.random.Generator) -> list[LoopClosure]:
    """``count`` wrong loops, alternately a look-alike place and a wrong-scale true place."""
    wrong = []
    while len(wrong) < count:
        if len(wrong) % 2 == 0:
            a, b = (int(v) for v in rng.choice(ROBOTS, 2, replace=False))
            ka, kb = (int(v) for v in rng.integers(0, KEYFRAMES, 2))
            true = data.truth[a][ka].between(data.truth[b][kb])
            if np.linalg.norm(true.translation()) < 4 * data.spacing:
                continue
            claimed = gtsam.Pose3(
                gtsam.Rot3.Ypr(*rng.uniform(-0.25, 0.25, 3)),
                rng.uniform(-0.7, 0.7, 3) * data.spacing,
            )
            wrong.append(_loop(a, ka, b, kb, claimed, data.scene_scale, rng))
        else:
            base = data.true_loops[int(rng.integers(len(data.true_loops)))]
            factor = math.exp(rng.choice([-1, 1]) * rng.uniform(math.log(1.6), math.log(3.0)))
            T = base.T_ab.copy()
            T[:3] *= factor
            wrong.append(replace(base, T_ab=T))
    return wrong


def merged_errors(
    truth: dict[int, list[gtsam.Pose3]], poses: dict[int, np.ndarray]
) -> tuple[float, float]:
    """``(ATE RMSE in % of the path, |scale - 1|)`` after one Sim(3) alignment (Umeyama)."""
    est = np.concatenate([poses[r][:, :3] for r in sorted(truth)])
    gt = np.concatenate([np.stack([p.translation() for p in truth[r]]) for r in sorted(truth)])
    mu_e, mu_g = est.mean(0), gt.mean(0)
    E, G = est - mu_e, gt - mu_g
    U, D, Vt = np.linalg.svd(G.T @ E / len(est))
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    scale = float(np.trace(np.diag(D) @ S) / (E**2).sum(1).mean())
    aligned = scale * E @ R.T + mu_g
    rmse = float(np.sqrt(((aligned - gt) ** 2).sum(1).mean()))
    path = sum(
        np.linalg.norm(np.diff(np.stack([p.translation() for p in truth[r]]), axis=0), axis=1).sum()
        for r in truth
    )
    return 100 * rmse / path, abs(scale - 1.0)


#: name -> (solver, pose_graph.consistency, pose_graph.scale_alarm_log); all "smoothed".
SETTINGS = {
    "old default: lm": ("lm", "none", math.inf),
    "gnc": ("gnc", "none", math.inf),
    "lm + alarm": ("lm", "none", PoseGraphConfig().scale_alarm_log),
    "lm + pcm + alarm": ("lm", "pcm", PoseGraphConfig().scale_alarm_log),
    "default: gnc + pcm + alarm": ("gnc", "pcm", PoseGraphConfig().scale_alarm_log),
}


def _extend(estimate: np.ndarray, odometry: np.ndarray) -> np.ndarray:
    """``(K, 8)``: ``estimate`` for the first keyframes, odometry increments after it."""
    poses = [to_pose3(T) for T in estimate]
    for k in range(len(poses), len(odometry)):
        poses.append(poses[-1].compose(to_pose3(odometry[k - 1]).between(to_pose3(odometry[k]))))
    return np.stack([from_pose3(p) for p in poses])


@dataclass
class Mission:
    """Two rounds as the robots run them; what they end with."""

    poses: dict[int, np.ndarray]
    alarms: int
    merged_log: float
    loops: int
    kept: int
    wrong_kept: int


def _shares(
    odometry: dict[int, np.ndarray],
    loops: list[LoopClosure],
    estimates: dict[int, tuple[np.ndarray, int]],
) -> dict[int, PoseGraphShare]:
    return {
        r: PoseGraphShare(
            sender=r,
            recipient=0,
            round=0,
            time_s=0.0,
            odometry=o,
            estimate=estimates.get(r, (np.zeros((0, 8)), r))[0],
            frame=estimates.get(r, (None, r))[1],
            loops=[l for l in loops if l.robot_a == r],
        )
        for r, o in odometry.items()
    }


def mission(
    data: Scenario, wrong: list[LoopClosure], solver: str, config: PoseGraphConfig
) -> Mission:
    """Round 1: the first half of every robot's keyframes and the loops among them; round
    2: everything, from round 1's estimates; both solved as the elected robot does
    (:func:`~como3r.decentralized.consistency.solve_shares`). A solve the alarm holds back leaves
    the robots with their previous estimates (extended by odometry), or their odometry."""
    settings = DecentralizedConfig(
        pose_graph=replace(config, solver=solver, formulation="smoothed")
    )
    half = KEYFRAMES // 2
    loops = data.true_loops + wrong
    early = [l for l in loops if l.keyframe_a < half and l.keyframe_b < half]
    first: list[LoopCheck] = []
    estimates = solve_shares(
        _shares({r: o[:half] for r, o in data.odometry.items()}, early, {}), settings, checks=first
    )
    final: list[LoopCheck] = []
    updates = solve_shares(_shares(data.odometry, loops, estimates), settings, checks=final)
    poses = {}
    for r, odometry in data.odometry.items():
        if r in updates:
            poses[r] = updates[r][0]
        elif r in estimates:
            poses[r] = _extend(estimates[r][0], odometry)
        else:
            poses[r] = odometry
    check = final[0]
    # solve_shares gathers the loops share by share (robot by robot).
    ordered = [l for r in sorted(data.odometry) for l in loops if l.robot_a == r]
    wrong_ids = {id(l) for l in wrong}
    wrong_kept = sum(bool(c) for l, c in zip(ordered, check.consistent) if id(l) in wrong_ids)
    return Mission(
        poses,
        sum(c.alarm for c in first + final),
        check.merged_scale_log,
        len(loops),
        int(check.consistent.sum()),
        wrong_kept,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument(
        "--settings", default=",".join(SETTINGS), help="comma-separated subset of the settings"
    )
    args = parser.parse_args()
    chosen = [s.strip() for s in args.settings.split(",")]
    print(
        f"{'setting':<28} {'wrong %':>7} {'loops':>5} {'kept':>5} {'wrong kept':>10} "
        f"{'ATE % path':>10} {'scale err %':>11} {'merged log':>10} {'alarms':>6}"
    )
    for name in chosen:
        solver, consistency, alarm = SETTINGS[name]
        config = PoseGraphConfig(solver=solver, consistency=consistency, scale_alarm_log=alarm)
        for rate in RATES:
            runs = []
            for seed in range(args.seeds):
                data = scenario(seed)
                count = round(rate / (1 - rate) * len(data.true_loops))
                wrong = wrong_loops(data, count, np.random.default_rng(1000 + seed))
                run = mission(data, wrong, solver, config)
                runs.append((run, *merged_errors(data.truth, run.poses)))
            merged = [abs(run.merged_log) for run, _, _ in runs]
            print(
                f"{name:<28} {100 * rate:>7.0f} "
                f"{np.mean([r.loops for r, _, _ in runs]):>5.0f} "
                f"{np.mean([r.kept for r, _, _ in runs]):>5.0f} "
                f"{np.mean([r.wrong_kept for r, _, _ in runs]):>10.1f} "
                f"{np.mean([a for _, a, _ in runs]):>10.3f} "
                f"{100 * np.mean([s for _, _, s in runs]):>11.2f} "
                f"{np.nanmax(merged) if not np.isnan(merged).all() else float('nan'):>10.3f} "
                f"{sum(r.alarms for r, _, _ in runs):>6}",
                flush=True,
            )


if __name__ == "__main__":
    main()
