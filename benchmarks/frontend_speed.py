"""Front-end cost per frame vs the prior's decode (issue 4 benchmark; not a test).

For each resolution it renders a keyframe and a frame 0.3 m apart, then times, per frame:
projective matching with descriptor refinement (C-Eq. 1), the LM-IRLS tracking solve
(C-Eq. 2) and the fusion (C-Eq. 3), and compares their sum with the decode time of the
simulated prior and of the full-size MASt3R network (random weights: same cost as the
released checkpoint). Prints one table.

    python benchmarks/frontend_speed.py [--threads 2] [--repeats 3] [--skip-mast3r]
"""

from __future__ import annotations

import argparse
import platform
import time
from collections.abc import Callable

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from como3r.config import Config
from como3r.data.preprocess import ImageTransform
from como3r.data.synth import Intrinsics, Renderer, build_preset
from como3r.frontend.keyframes import Keyframe
from como3r.frontend.pairs import directed_matches
from como3r.frontend.tracker import FrameTracker
from como3r.geometry.lie import sim3_identity
from como3r.prior.base import View
from como3r.prior.ground_truth import GroundTruth, InMemoryTruth
from como3r.prior.simulated import SimulatedPrior


def best_of(repeats: int, fn: Callable[[], object]) -> float:
    """Best wall time of ``repeats`` calls, in milliseconds."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1000.0 * min(times)


def views(width: int, height: int) -> tuple[View, View, InMemoryTruth]:
    """Two rendered views 2 degrees and 0.3 m apart, and their ground truth."""
    spec = build_preset("default", 1, 100, 0.2, seed=1)
    intrinsics = Intrinsics.from_hfov(width, height, 75.0)
    renderer = Renderer(spec.scene, intrinsics)
    R, t = spec.paths[0].rotations[20], spec.paths[0].positions[20]
    out, truth = [], InMemoryTruth()
    for index, (R_WC, t_WC) in enumerate(
        [
            (R, t),
            (
                R @ Rotation.from_euler("y", 2, degrees=True).as_matrix(),
                t + R @ np.array([0, 0, 0.3]),
            ),
        ]
    ):
        frame = renderer.render(R_WC, t_WC)
        quat = Rotation.from_matrix(R_WC).as_quat()
        out.append(View(ImageTransform.to_network(frame.rgb), 0, index))
        truth.add(
            0,
            index,
            GroundTruth(
                depth=torch.from_numpy(frame.depth),
                K=torch.from_numpy(intrinsics.matrix()).float(),
                surface=torch.from_numpy(frame.surface),
                T_WC=torch.tensor([*t_WC, *quat, 1.0]),
            ),
        )
    return out[0], out[1], truth


def frontend_row(width: int, height: int, repeats: int) -> dict[str, float]:
    config = Config()
    view_k, view_f, truth = views(width, height)
    prior = SimulatedPrior(config.simulated_prior, truth)
    enc_k, enc_f = prior.encode(view_k), prior.encode(view_f)
    self_pred = prior.decode(enc_k, enc_k)
    keyframe = Keyframe(
        0,
        0,
        0.0,
        enc_k,
        sim3_identity(),
        self_pred.X_ii.clone(),
        self_pred.C_ii.clone(),
        self_pred.X_ii.clone(),
        self_pred.C_ii.clone(),
        np.zeros((height, width, 3), np.uint8),
    )
    tracker = FrameTracker(prior, config)
    pred = prior.decode(enc_f, enc_k)
    matches = directed_matches(pred, config.matching, config.tracking.q_min)
    T_kf, _ = tracker.solve(pred.X_ii, keyframe, matches, sim3_identity())
    X_hat, C_hat = keyframe.X_hat.clone(), keyframe.C_hat.clone()

    def fuse() -> None:
        keyframe.X_hat, keyframe.C_hat = X_hat.clone(), C_hat.clone()
        keyframe.fuse(T_kf, pred.X_ji, pred.C_ji)

    return {
        "matching": best_of(
            repeats, lambda: directed_matches(pred, config.matching, config.tracking.q_min)
        ),
        "tracking": best_of(
            repeats, lambda: tracker.solve(pred.X_ii, keyframe, matches, sim3_identity())
        ),
        "fusion": best_of(repeats, fuse),
        "simulated decode": best_of(repeats, lambda: prior.decode(enc_f, enc_k)),
    }


def mast3r_decode_ms(width: int, height: int, repeats: int) -> float:
    from como3r.prior.mast3r import MASt3RNetwork, parse_model_string
    from como3r.prior.mast3r.config import RELEASED_MODEL_STRING
    from como3r.prior.mast3r.prior import MASt3RPrior

    torch.manual_seed(0)
    prior = MASt3RPrior(MASt3RNetwork(parse_model_string(RELEASED_MODEL_STRING)))
    enc = prior.encode(torch.rand(1, 3, height, width) * 2 - 1)
    return best_of(repeats, lambda: prior.decode(enc, enc))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--skip-mast3r", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(
        f"machine: {platform.processor() or platform.machine()}, torch {torch.__version__}, "
        f"{args.threads} threads, best of {args.repeats}"
    )
    header = (
        "resolution",
        "matching ms",
        "tracking ms",
        "fusion ms",
        "front-end ms",
        "sim decode ms",
        "front-end/sim",
        "MASt3R decode ms",
        "front-end/MASt3R",
    )
    print(" | ".join(header))
    for width, height in ((256, 192), (512, 384)):
        row = frontend_row(width, height, args.repeats)
        total = row["matching"] + row["tracking"] + row["fusion"]
        mast3r = None if args.skip_mast3r else mast3r_decode_ms(width, height, 1)
        cells = [
            f"{width}x{height}",
            f"{row['matching']:.0f}",
            f"{row['tracking']:.0f}",
            f"{row['fusion']:.1f}",
            f"{total:.0f}",
            f"{row['simulated decode']:.0f}",
            f"{total / row['simulated decode']:.2f}",
            "-" if mast3r is None else f"{mast3r:.0f}",
            "-" if mast3r is None else f"{total / mast3r:.2f}",
        ]
        print(" | ".join(cells), flush=True)


if __name__ == "__main__":
    main()
