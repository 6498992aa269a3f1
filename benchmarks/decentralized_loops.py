"""Per-loop diagnostics of a decentralized run: each inter-robot loop against ground truth.

Re-registers the inter-robot loop candidates of a finished ``como3r run --mode
decentralized`` output (its ``graph.json``) on the agent inputs it ran on, exactly as the
robot that registered them did (same prior, decode, reciprocal matching and RANSAC seed),
and prints one line per candidate: the run's verdict, ratio (F-Eq. 1) and GNC weight, the
registration's correspondences and RANSAC inliers (count and fraction of the
correspondences), and the error of its relative pose against the ground truth: rotation
error [deg] and translation error once scaled to the true length (the prior's translation
is up to scale, F-Eq. 6-8), the error and the true camera distance both in keyframe
spacings (the robots' median ``keyframe_distance``, so scale-free). A loop is wrong when either error is large; why it passed verification is in
its inlier fraction and ratio. Only ground truth the run never saw is read.

Much faster than re-running the mission: it decodes the listed pairs only (``--only`` picks
some), e.g. for the 512 runs of ``decentralized_scale.py``:

    PYTHONPATH=src python benchmarks/decentralized_loops.py \\
        /tmp/dscale/bench512/scene_x20 /tmp/dscale/bench512/run_x20 --accepted-only

Issue 12, item 5 (default synthetic scene, long side 512, 20x): the two loops smoothed/LM
accepted and GNC rejected were (0,6)-(2,3), 48 inliers of 2994 matches (1.6 %), rotation
error 3.2 deg, translation direction 94 deg off, and (1,0)-(2,3), 44 of 2797 (1.6 %),
173 deg; true loops kept 33-47 % of their matches. Hence
``registration.min_inlier_fraction``.
"""

from __future__ import annotations

import argparse
import json
import logging
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch

from como3r.config import Config, InputConfig
from como3r.config_decentralized import DecentralizedConfig
from como3r.data.agent import open_agent
from como3r.data.agent_input import AgentInput
from como3r.data.preprocess import make_view
from como3r.decentralized.registration import register_predictions
from como3r.geometry.lie import quat_to_matrix
from como3r.prior.base import Encoding, Prior
from como3r.prior.simulated_keys import generator
from como3r.runtime.pipeline import PriorSpec, build_prior

logger = logging.getLogger(__name__)


@dataclass
class LoopRow:
    """One inter-robot candidate: the run's verdict and the re-registration's errors."""

    a: int
    ka: int
    b: int
    kb: int
    accepted: bool
    ratio: float
    gnc_weight: float | None
    correspondences: int
    inliers: int
    inlier_fraction: float
    rotation_error_deg: float
    translation_error: float
    distance: float


def _matrix(T: np.ndarray) -> np.ndarray:
    """``(4, 4)`` rigid matrix of a ``(8,)`` pose (t, q_xyzw, s; the scale is dropped)."""
    M = np.eye(4)
    M[:3, :3] = quat_to_matrix(torch.as_tensor(T[3:7], dtype=torch.float64)).numpy()
    M[:3, 3] = T[:3]
    return M


def _true_relative(agents: list[AgentInput], a: int, fa: int, b: int, fb: int) -> np.ndarray:
    """``(4, 4)`` true pose of camera b (frame fb) in camera a (frame fa)."""

    def world(agent: AgentInput, frame: int) -> np.ndarray:
        return _matrix(agent.gt_poses[frame].double().numpy())

    return np.linalg.inv(world(agents[a], fa)) @ world(agents[b], fb)


def _scaled_translation_error(t: np.ndarray, t_true: np.ndarray) -> float:
    """``|t scaled to |t_true| - t_true|``: the error of a translation known up to scale."""
    norm = float(np.linalg.norm(t))
    return float(np.linalg.norm(t * float(np.linalg.norm(t_true)) / max(norm, 1e-12) - t_true))


def _rotation_error_deg(R: np.ndarray, R_true: np.ndarray) -> float:
    cos = (np.trace(R.T @ R_true) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


class Reregistration:
    """The prior and the agents of a run, to register keyframe pairs as its robots did."""

    def __init__(
        self, agents: list[Path], long_side: int, min_inlier_fraction: float | None = None
    ) -> None:
        self.config = Config(input=InputConfig(long_side=long_side))
        self.settings = DecentralizedConfig().registration
        if min_inlier_fraction is not None:
            self.settings = replace(self.settings, min_inlier_fraction=min_inlier_fraction)
        self.agents = [open_agent(p) for p in agents]
        self.prior: Prior = build_prior(
            PriorSpec("simulated"), self.config, dict(enumerate(self.agents))
        )[0]
        self._encodings: dict[tuple[int, int], Encoding] = {}

    def encoding(self, agent: int, frame: int) -> Encoding:
        key = (agent, frame)
        if key not in self._encodings:
            view = make_view(
                self.agents[agent].load_frame(frame), agent, self.config.input.long_side
            )
            self._encodings[key] = self.prior.encode(view)
        return self._encodings[key]

    def row(self, edge: dict, frames: dict[tuple[int, int], int], spacing: float) -> LoopRow:
        """Re-register one ``graph.json`` inter edge and compare it with the ground truth;
        lengths in units of ``spacing`` (the keyframe spacing)."""
        (a, ka), (b, kb) = edge["from"], edge["to"]
        fa, fb = frames[(a, ka)], frames[(b, kb)]
        pred_ij, pred_ji = self.prior.decode_symmetric(
            [(self.encoding(a, fa), self.encoding(b, fb))]
        )[0]
        reg = register_predictions(
            pred_ij.to("cpu"),
            pred_ji.to("cpu"),
            self.settings,
            generator(self.settings.seed, "loop", a, ka, b, kb),
        )
        true = _true_relative(self.agents, a, fa, b, fb)
        rot = translation = float("nan")
        if reg.T_ij is not None:
            T = _matrix(reg.T_ij.double().numpy())
            rot = _rotation_error_deg(T[:3, :3], true[:3, :3])
            translation = _scaled_translation_error(T[:3, 3], true[:3, 3]) / spacing
        return LoopRow(
            a,
            ka,
            b,
            kb,
            bool(edge["accepted"]),
            float(edge["ratio"]),
            edge.get("gnc_weight"),
            reg.correspondences,
            reg.inliers,
            reg.inliers / max(reg.correspondences, 1),
            rot,
            translation,
            float(np.linalg.norm(true[:3, 3])) / spacing,
        )


def _edges(graph: dict, accepted_only: bool, only: str) -> list[dict]:
    edges = [
        e for e in graph["edges"] if e["type"] == "inter" and (e["accepted"] or not accepted_only)
    ]
    if only:
        wanted = {tuple(int(v) for v in item.split(",")) for item in only.split(";")}
        edges = [e for e in edges if (*e["from"], *e["to"]) in wanted]
    return edges


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", type=Path, help="folder of the agent_<a> inputs of the run")
    parser.add_argument("run", type=Path, help="the run's output folder")
    parser.add_argument("--long-side", type=int, default=Config().input.long_side)
    parser.add_argument("--accepted-only", action="store_true")
    parser.add_argument("--only", default="", help="'a,ka,b,kb;...': these loops only")
    parser.add_argument("--json", type=Path, help="also write the rows here")
    parser.add_argument(
        "--min-inlier-fraction",
        type=float,
        help="registration.min_inlier_fraction (0: the inliers of fits the default refuses)",
    )
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    graph = json.loads((args.run / "graph.json").read_text())
    frames = {(k["agent"], k["keyframe"]): k["frame"] for k in graph["keyframes"]}
    robots = 1 + max(agent for agent, _ in frames)
    tool = Reregistration(
        [args.scene / f"agent_{a}" for a in range(robots)], args.long_side, args.min_inlier_fraction
    )
    spacing = float(
        np.median(
            [
                r["keyframe_distance"]
                for r in json.loads((args.run / "metrics.json").read_text())["robots"]
            ]
        )
    )
    print(
        f"{'loop':>11} {'acc':>3} {'ratio':>6} {'gnc':>4} {'corr':>6} {'inl':>5} "
        f"{'inl %':>6} {'rot deg':>8} {'t err/kf':>8} {'dist/kf':>7}"
    )
    rows = []
    for edge in _edges(graph, args.accepted_only, args.only):
        row = tool.row(edge, frames, spacing)
        rows.append(row)
        gnc = "-" if row.gnc_weight is None else f"{row.gnc_weight:.1f}"
        print(
            f"{row.a},{row.ka}-{row.b},{row.kb:<5} {'y' if row.accepted else 'n':>3} "
            f"{row.ratio:>6.3f} {gnc:>4} {row.correspondences:>6} {row.inliers:>5} "
            f"{100 * row.inlier_fraction:>6.1f} {row.rotation_error_deg:>8.2f} "
            f"{row.translation_error:>8.2f} {row.distance:>7.2f}",
            flush=True,
        )
    if args.json:
        args.json.write_text(json.dumps([asdict(r) for r in rows], indent=1))


if __name__ == "__main__":
    main()
