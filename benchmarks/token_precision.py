"""What MASt3R's decoder makes of encoder tokens that travelled in float16 (a script, not a test).

The coordinator (and a peer robot) decodes keyframe pairs from the encoder tokens the agents
send. This measures how much the pair prediction and the matches of the coordinator change
when those tokens arrive rounded to float16 instead of float32: the full-size network (ViT-L
encoder, ViT-B decoder: the released checkpoint's configuration) with seeded random weights
(what the network's own arithmetic does to a rounding of its tokens; trained weights may be
more or less sensitive), two frames of an agent folder at ``input.long_side``, the ordered
pair decoded once from the exact tokens and once from their float16 roundings. Printed per
output: the median and 99th percentile of the relative difference (pointmaps: ``|dX| /
|X|``; confidences: ``|dC| / C``; descriptors: ``1 - cos``), and of the directed matches of
C-Eq. 1 (``como3r.frontend.pairs.directed_matches``) the share of pixels whose match and
validity are unchanged, against a control: tokens multiplied by ``1 + 2^-20 N(0, 1)``, a
perturbation 256 times finer than float16's rounding (how chaotic the matching is anyway).

    como3r synth --out /tmp/s384 --agents 1 --frames 12 --width 640 --height 480
    python benchmarks/token_precision.py --agent /tmp/s384/agent_0
"""

import argparse
import dataclasses

import torch

from como3r.config import Config
from como3r.data.agent import open_agent
from como3r.frontend.pairs import directed_matches
from como3r.prior.mast3r import MASt3RPrior
from como3r.prior.mast3r.config import RELEASED_MODEL_STRING, parse_model_string
from como3r.prior.mast3r.testing import seeded_network
from como3r.runtime.pipeline import load_frame


def _quantiles(x: torch.Tensor) -> str:
    q = torch.quantile(x.flatten().double()[: 2**24], torch.tensor([0.5, 0.99], dtype=torch.double))
    return f"{q[0]:.2e} / {q[1]:.2e}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--agent", required=True, help="an agent folder (como3r synth)")
    parser.add_argument(
        "--frames", type=int, nargs=2, default=(0, 3), help="the two frames of the pair"
    )
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    config = Config()
    agent = open_agent(args.agent)
    prior = MASt3RPrior(seeded_network(parse_model_string(RELEASED_MODEL_STRING), 0).eval())
    views = [load_frame(agent, 0, i, config.input.long_side, False)[0] for i in args.frames]
    exact = [prior.encode(view) for view in views]
    rounded = [dataclasses.replace(e, tokens=e.tokens.half().float()) for e in exact]
    token_error = (rounded[0].tokens - exact[0].tokens).abs() / exact[0].tokens.abs().clamp_min(
        1e-12
    )
    print(
        f"pair of frames {args.frames} at {tuple(views[0].image.shape[1:])}, tokens "
        f"{tuple(exact[0].tokens.shape)}: relative rounding median / p99 "
        f"{_quantiles(token_error)}"
    )
    a, b = prior.decode(*exact), prior.decode(*rounded)
    print("output | median / p99 relative difference")
    for name in ("X_ii", "X_ji"):
        x, y = getattr(a, name), getattr(b, name)
        print(f"{name} | {_quantiles((x - y).norm(dim=-1) / x.norm(dim=-1).clamp_min(1e-12))}")
    for name in ("C_ii", "C_ji", "Q_ii", "Q_ji"):
        x, y = getattr(a, name), getattr(b, name)
        print(f"{name} | {_quantiles((x - y).abs() / x.abs().clamp_min(1e-12))}")
    for name in ("D_ii", "D_ji"):
        x, y = getattr(a, name), getattr(b, name)
        cosine = (x * y).sum(-1) / (x.norm(dim=-1) * y.norm(dim=-1))
        print(f"{name} (1 - cos) | {_quantiles(1 - cosine)}")
    generator = torch.Generator().manual_seed(0)
    jittered = [
        dataclasses.replace(
            e, tokens=e.tokens * (1 + 2**-20 * torch.randn(e.tokens.shape, generator=generator))
        )
        for e in exact
    ]
    m_a = directed_matches(a, config.matching, config.tracking.q_min)
    width = views[0].image.shape[-1]
    for label, pred in (
        ("float16 tokens", b),
        ("control: tokens x (1 + 2^-20 N(0, 1))", prior.decode(*jittered)),
    ):
        m_b = directed_matches(pred, config.matching, config.tracking.q_min)
        moved = m_a.idx != m_b.idx
        shift = torch.stack([(m_a.idx - m_b.idx) // width, (m_a.idx - m_b.idx) % width], -1)
        distance = shift[moved].float().norm(dim=-1)
        print(
            f"matches, {label}: same pixel {1 - moved.float().mean():.4f}, same validity "
            f"{(m_a.valid == m_b.valid).float().mean():.4f}, moved ones by median "
            f"{distance.median() if len(distance) else 0:.1f} px; valid "
            f"{m_a.valid.float().mean():.4f} exact, {m_b.valid.float().mean():.4f} here"
        )


if __name__ == "__main__":
    main()
