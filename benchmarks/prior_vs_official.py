"""Our MASt3R network against the official code, same random weights (a script, not a test).

The official code (naver/mast3r with its dust3r and croco submodules) is not part of como3r;
point ``--official`` at an extracted copy, e.g.::

    mkdir -p /tmp/official && cd /tmp/official
    for r in mast3r dust3r croco; do mkdir -p $r
        git --git-dir=<mirror of naver/$r> archive HEAD | tar -x -C $r; done
    rmdir mast3r/dust3r dust3r/croco
    ln -s /tmp/official/dust3r mast3r/dust3r; ln -s /tmp/official/croco dust3r/croco
    pip install --no-deps --target /tmp/official/deps einops

Its imports are put on ``sys.path`` at run time only. ``huggingface_hub`` (a base class of the
official model, used only for hub downloads) is replaced by an empty stand-in when it is not
installed; croco's compiled RoPE is absent, so the official code uses its pure-PyTorch RoPE2D.

The official model is built with its own random initialisation (LayerNorm weights and all
biases then randomised too), and our network loads its state dict (the official keys, through
our strict checkpoint selection). Both outputs are compared (encoder tokens and every head
output), then encode (one image) and decode (one ordered pair: both decoders and both heads)
are timed, ours and official alternating in the same process, median of ``--repeats``.

Ours runs through :class:`MASt3RPrior` (the API SLAM uses: input checks included) in float32
and, where asked, bfloat16; the official code runs in float32 under ``torch.no_grad()`` through
``_encode_image`` / ``_decoder`` / ``_downstream_head`` as its ``forward`` does.

Usage::

    OMP_NUM_THREADS=2 python benchmarks/prior_vs_official.py --official /tmp/official/mast3r \\
        [--deps /tmp/official/deps] [--threads 2] [--repeats 3] [--size 512x384] \\
        [--dtypes fp32 bf16] [--tiny]

Measured (2-core AMD EPYC Zen 4 with AVX512-BF16, idle, 512x384, median of 3; speed-up of
ours over the official fp32, wall / CPU time):

    threads  fp32 encode    fp32 decode    bf16 encode    bf16 decode
    2        1.58x / 1.51x  1.56x / 1.52x  2.44x / 2.34x  1.68x / 1.68x
    1        1.38x / 1.38x  1.38x / 1.38x  2.16x / 2.16x  1.65x / 1.65x

Our encoder's linear layers run at 50-52 GMAC/s on one core (oneDNN, near the core's fp32
FMA peak; pre-packed oneDNN weights measured no faster) and its attention at ~40 GMAC/s, so
the fp32 ratio is set by how far the official code's BLAS is from that peak on the CPU at
hand. Under load (other processes on the cores) the ratios drop (1.32x / 1.40x at 1 thread
with load 5-8): compare on an idle machine.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import sys
import time
import types
from collections.abc import Callable
from pathlib import Path

import torch
from torch import nn

from como3r.prior.mast3r import MASt3RConfig, MASt3RNetwork, MASt3RPrior
from como3r.prior.mast3r.loader import select_state_dict

DTYPES = {"fp32": torch.float32, "bf16": torch.bfloat16}
#: head outputs compared: ours (HeadOutput field) -> official result key
#: a small configuration the official head accepts (it asserts dec_depth > 9)
TINY = MASt3RConfig(
    enc_embed_dim=64, enc_depth=2, enc_num_heads=2, dec_embed_dim=64, dec_depth=10, dec_num_heads=2
)
OUTPUTS = {"pts3d": "pts3d", "conf": "conf", "desc": "desc", "desc_conf": "desc_conf"}


def import_official(root: Path, deps: Path | None) -> type[nn.Module]:
    """``AsymmetricMASt3R`` from the official code at ``root`` (``mast3r`` checkout)."""
    for path in (deps, root):
        if path is not None and str(path) not in sys.path:
            sys.path.insert(0, str(path))
    try:
        import huggingface_hub  # noqa: F401
    except ImportError:
        # the official model subclasses PyTorchModelHubMixin for hub downloads only
        class PyTorchModelHubMixin:
            def __init_subclass__(cls, **kwargs: object) -> None:
                super().__init_subclass__()

        stub = types.ModuleType("huggingface_hub")
        stub.__version__ = "0.22.0"  # type: ignore[attr-defined]
        stub.PyTorchModelHubMixin = PyTorchModelHubMixin  # type: ignore[attr-defined]
        sys.modules["huggingface_hub"] = stub
    from mast3r.model import AsymmetricMASt3R

    return AsymmetricMASt3R


def official_kwargs(config: MASt3RConfig) -> dict[str, object]:
    """Constructor arguments of the official model for ``config`` (the released string's)."""
    return dict(
        pos_embed=f"RoPE{config.rope_base:g}",
        patch_embed_cls="ManyAR_PatchEmbed",
        img_size=(512, 512),
        head_type="catmlp+dpt",
        output_mode=f"pts3d+desc{config.desc_dim}",
        depth_mode=("exp", -math.inf, math.inf),
        conf_mode=("exp", config.conf_min, config.conf_max),
        enc_embed_dim=config.enc_embed_dim,
        enc_depth=config.enc_depth,
        enc_num_heads=config.enc_num_heads,
        dec_embed_dim=config.dec_embed_dim,
        dec_depth=config.dec_depth,
        dec_num_heads=config.dec_num_heads,
        two_confs=config.two_confs,
        desc_conf_mode=("exp", config.desc_conf_min, config.desc_conf_max),
    )


def build_pair(
    official_cls: type[nn.Module], config: MASt3RConfig, seed: int
) -> tuple[nn.Module, MASt3RNetwork]:
    """The official model (random weights) and our network holding the same tensors."""
    torch.manual_seed(seed)
    official = official_cls(**official_kwargs(config)).eval().requires_grad_(False)
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, parameter in official.named_parameters():
            if parameter.dim() == 1:  # LayerNorm weights/biases and biases: not 1 / 0
                noise = 0.1 * torch.randn(parameter.shape, generator=generator)
                parameter.copy_(1 + noise if "norm" in name and name.endswith("weight") else noise)
    state = official.state_dict()
    with torch.device("meta"):
        ours = MASt3RNetwork(config)
    expected = {key: value.shape for key, value in ours.state_dict().items()}
    ours.load_state_dict(
        select_state_dict(expected, state, "official model"), strict=True, assign=True
    )
    return official, ours.requires_grad_(False)


class Official:
    """Encode and decode of the official model, as its ``forward`` runs them."""

    def __init__(self, model: nn.Module) -> None:
        self.model = model

    def encode(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(B, 3, H, W)`` -> tokens ``(B, N, C)``, positions ``(B, N, 2)``, true shapes."""
        shape = torch.tensor(images.shape[-2:])[None].repeat(images.shape[0], 1)
        with torch.no_grad():
            tokens, pos, _ = self.model._encode_image(images, shape)
        return tokens, pos, shape

    def decode(self, enc1: tuple, enc2: tuple) -> tuple[dict, dict]:
        """Both decoders and both heads on the ordered pair (1, 2)."""
        (f1, pos1, shape1), (f2, pos2, shape2) = enc1, enc2
        with torch.no_grad():
            dec1, dec2 = self.model._decoder(f1, pos1, f2, pos2)
            res1 = self.model._downstream_head(1, [tok.float() for tok in dec1], shape1)
            res2 = self.model._downstream_head(2, [tok.float() for tok in dec2], shape2)
        return res1, res2


def relative_error(value: torch.Tensor, reference: torch.Tensor) -> float:
    """``||value - reference|| / ||reference||`` in float64."""
    reference = reference.double()
    return float((value.double() - reference).norm() / reference.norm())


def compare(prior: MASt3RPrior, official: Official, images: torch.Tensor) -> dict[str, float]:
    """Relative errors of our outputs against the official ones (tokens, both views' maps)."""
    ours_enc = prior.encode(images)
    off_enc = [official.encode(images[b : b + 1]) for b in range(2)]
    errors = {"tokens": max(relative_error(e.tokens, o[0][0]) for e, o in zip(ours_enc, off_enc))}
    first, second = prior._run([ours_enc[0]], [ours_enc[1]])
    res1, res2 = official.decode(*off_enc)
    for ours_out, theirs in ((first, res1), (second, res2)):
        for field, key in OUTPUTS.items():
            error = relative_error(getattr(ours_out, field), theirs[key])
            errors[field] = max(errors.get(field, 0.0), error)
    return errors


def timed(run: Callable[[], object]) -> tuple[float, float]:
    """Wall-clock and process CPU time of one call, in ms."""
    start_wall, start_cpu = time.perf_counter(), time.process_time()
    run()
    return (time.perf_counter() - start_wall) * 1e3, (time.process_time() - start_cpu) * 1e3


def measure(
    official_root: Path,
    deps: Path | None,
    width: int,
    height: int,
    dtypes: list[str],
    repeats: int,
    seed: int = 0,
    tiny: bool = False,
    log: Callable[[str], None] = print,
) -> dict[tuple[str, str], tuple[float, ...]]:
    """Median ms of encode and decode, ours per precision against the official fp32.

    Returns:
        ``{(precision, "encode" | "decode"): (ours wall, official wall, ours CPU,
        official CPU)}`` in ms, median of ``repeats`` interleaved runs.

    Raises:
        SystemExit: our fp32 outputs differ from the official ones by more than 1e-4.
    """
    official_cls = import_official(official_root.resolve(), deps)
    config = TINY if tiny else MASt3RConfig()
    official_model, network = build_pair(official_cls, config, seed)
    official = Official(official_model)
    images = torch.rand(2, 3, height, width, generator=torch.Generator().manual_seed(1)) * 2 - 1
    log(
        f"network: {'tiny' if tiny else 'full'} configuration, "
        f"{sum(p.numel() for p in network.parameters()):,} parameters, same random weights"
    )

    # the priors share one network, whose compute dtype is set by the prior about to run
    priors = {name: MASt3RPrior(network, dtype=DTYPES[name]) for name in dtypes}

    def use(name: str) -> MASt3RPrior:
        network.set_compute_dtype(DTYPES[name])
        return priors[name]

    for name in priors:
        errors = compare(use(name), official, images)
        log(
            f"ours {name} vs official fp32, relative error: "
            + ", ".join(f"{key} {value:.1e}" for key, value in errors.items())
        )
        if name == "fp32" and max(errors.values()) > 1e-4:
            raise SystemExit("fp32 outputs differ from the official ones (> 1e-4)")

    off_enc = [official.encode(images[b : b + 1]) for b in range(2)]
    runs: dict[str, Callable[[], object]] = {
        "official encode": lambda: official.encode(images[:1]),
        "official decode": lambda: official.decode(*off_enc),
    }
    for name in priors:
        encodings = use(name).encode(images)
        runs[f"ours {name} encode"] = lambda n=name: use(n).encode(images[:1])
        runs[f"ours {name} decode"] = lambda n=name, e=encodings: use(n).decode(*e)
    for run in runs.values():  # warm-up (allocator, oneDNN primitives, RoPE tables)
        run()
    samples: dict[str, list[tuple[float, float]]] = {key: [] for key in runs}
    for _ in range(repeats):
        for key, run in runs.items():
            samples[key].append(timed(run))
    median = {
        key: (statistics.median(w for w, _ in s), statistics.median(c for _, c in s))
        for key, s in samples.items()
    }
    return {
        (name, step): (
            *median[f"ours {name} {step}"][:1],
            median[f"official {step}"][0],
            median[f"ours {name} {step}"][1],
            median[f"official {step}"][1],
        )
        for name in priors
        for step in ("encode", "decode")
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--official",
        type=Path,
        default=Path("/tmp/official/mast3r"),
        help="extracted naver/mast3r with dust3r (and its croco) inside",
    )
    parser.add_argument(
        "--deps",
        type=Path,
        default=Path("/tmp/official/deps"),
        help="extra import path for the official code's einops",
    )
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--size", default="512x384", help="W x H, multiples of 16")
    parser.add_argument("--dtypes", nargs="+", default=["fp32", "bf16"], choices=list(DTYPES))
    parser.add_argument("--tiny", action="store_true", help="tiny configuration (quick check)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    width, height = (int(v) for v in args.size.lower().split("x"))
    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
        f"torch {torch.__version__}, {args.threads} threads, {args.size}, median of "
        f"{args.repeats} interleaved runs, load average {os.getloadavg()[0]:.1f} at start"
    )
    results = measure(
        args.official, args.deps, width, height, args.dtypes, args.repeats, args.seed, args.tiny
    )
    print(f"load average {os.getloadavg()[0]:.1f} at the end (other processes share the cores)\n")
    header = (
        f"{'ours':>5} {'step':>7} {'ours ms':>9} {'official ms':>12} "
        f"{'ours/official':>14} {'speed-up':>9} {'speed-up (CPU time)':>20}"
    )
    print(header)
    print("-" * len(header))
    for (name, step), (ours_wall, off_wall, ours_cpu, off_cpu) in results.items():
        print(
            f"{name:>5} {step:>7} {ours_wall:>9.0f} {off_wall:>12.0f} "
            f"{ours_wall / off_wall:>14.2f} {off_wall / ours_wall:>8.2f}x "
            f"{off_cpu / ours_cpu:>19.2f}x"
        )


if __name__ == "__main__":
    main()
