"""``synthesize``: render a preset scene and write it in the agent input format.

Layout (manual: docs/commands/synth.md)::

    scene.json                      preset, seed, scale, parameters, intrinsics, meetings
    agent_<a>/rgb/<stem>.png        8-bit RGB
    agent_<a>/depth/<stem>.c3z      float32 z-depth in metres, 0 for sky (and covered frames)
    agent_<a>/surface/<stem>.c3z    float32 (H, W, 3) appearance keys (id, s, t), id -1 sky
    agent_<a>/groundtruth.txt       TUM, T_WC (OpenCV camera, world z up)
    agent_<a>/timestamps.txt        one time per line, frame i at i / 30 s
    agent_<a>/calib.txt             fx fy cx cy

The maps are the renderer's float32 values compressed losslessly
(:mod:`como3r.io.packed_arrays`, arrays ``depth`` and ``surface``): the simulated prior reads
the very values it read from the ``.npy`` files synth wrote before (0.45-0.6 MB a 640x480 frame
in place of 4.9 MB; the agent reader takes either).

Everything is a deterministic function of the arguments: the same call writes
byte-identical files.

``scale`` multiplies the whole scene and the paths (0.1 a tabletop, 1 the rooms of the
presets, 5 a street, 20 aerial): the scene is generated and rendered at scale 1 and every
length is multiplied when written (depth, ground-truth translations, the (s, t) metres of the
surface keys, the lengths in ``scene.json``), so the images are those of scale 1 exactly, as
a scaled scene with scaled textures looks the same.
"""

from __future__ import annotations

import json
import logging
import math
import numbers
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from PIL import Image

from como3r.data.synth.families import MIN_FRAMES, PRESETS, build_preset
from como3r.data.synth.presets import SceneSpec
from como3r.data.synth.render import Frame, Intrinsics, Renderer
from como3r.errors import InputError
from como3r.io.packed_arrays import SUFFIX, write_packed
from como3r.io.tum import write_tum

logger = logging.getLogger(__name__)

FRAME_RATE = 30.0
HFOV_DEG = 75.0
MAX_AGENTS = 64
MAX_FRAMES = 100_000
MIN_SIZE = 8
MAX_SIZE = 4096


def _validate(
    staging_dir: Path,
    agents: int,
    overlap: float,
    frames: int,
    preset: str,
    width: int,
    height: int,
    scale: float,
    loop_frames: int | None,
) -> None:
    if preset not in PRESETS:
        raise InputError(f"--preset: unknown preset {preset!r} (valid: {', '.join(PRESETS)})")
    if not isinstance(agents, numbers.Integral) or not 1 <= agents <= MAX_AGENTS:
        raise InputError(f"--agents: must be an integer in [1, {MAX_AGENTS}], got {agents!r}")
    least = MIN_FRAMES.get(preset, 2)
    if not isinstance(frames, numbers.Integral) or not least <= frames <= MAX_FRAMES:
        raise InputError(
            f"--frames: must be an integer in [{least}, {MAX_FRAMES}] for preset "
            f"{preset!r}, got {frames!r}"
        )
    if not (
        isinstance(scale, numbers.Real)
        and not isinstance(scale, bool)
        and math.isfinite(scale)
        and scale > 0
    ):
        raise InputError(
            f"--scale: must be a finite number > 0 (1 = the presets' metres), got {scale!r}"
        )
    if loop_frames is not None and not (
        isinstance(loop_frames, numbers.Integral) and 2 <= loop_frames <= MAX_FRAMES
    ):
        raise InputError(
            f"--loop-frames: must be an integer in [2, {MAX_FRAMES}], got {loop_frames!r}"
        )
    if not (isinstance(overlap, numbers.Real) and math.isfinite(overlap) and 0 <= overlap <= 1):
        raise InputError(f"--overlap: must be a number in [0, 1], got {overlap!r}")
    for name, size in (("--width", width), ("--height", height)):
        if not isinstance(size, numbers.Integral) or not MIN_SIZE <= size <= MAX_SIZE:
            raise InputError(
                f"{name}: must be an integer in [{MIN_SIZE}, {MAX_SIZE}], got {size!r}"
            )
    if not staging_dir.is_dir():
        raise InputError(f"{staging_dir}: output folder does not exist")


def _write_frame(agent_dir: Path, stem: str, frame: Frame, scale: float) -> None:
    """Write one rendered frame with its lengths (depth, key s and t) times ``scale``."""
    # Level 1: noisy textures hardly compress, and level 6 costs more than rendering.
    Image.fromarray(frame.rgb).save(agent_dir / "rgb" / f"{stem}.png", compress_level=1)
    surface = frame.surface.copy()
    surface[..., 1:] *= scale
    depth = (frame.depth * scale).astype(np.float32)
    write_packed(agent_dir / "depth" / f"{stem}{SUFFIX}", {"depth": depth})
    write_packed(agent_dir / "surface" / f"{stem}{SUFFIX}", {"surface": surface})


def _covered_frame(height: int, width: int, seed: int, agent: int, index: int) -> Frame:
    """A frame taken with the lens covered: dark sensor noise (0-7 of 255), no depth
    (0) and no surface (id -1)."""
    rng = np.random.default_rng([seed % 2**32, agent, index])
    surface = np.zeros((height, width, 3), dtype=np.float32)
    surface[..., 0] = -1.0
    return Frame(
        rgb=rng.integers(0, 8, (height, width, 3), dtype=np.uint8),
        depth=np.zeros((height, width), dtype=np.float32),
        surface=surface,
    )


def _scene_json(spec: SceneSpec, K: Intrinsics, args: dict, scale: float) -> dict:
    """Everything about the scene a consumer may want, JSON-serialisable, lengths times
    ``scale``."""
    meetings = [
        {
            "agents": list(m.agents),
            "junction_xy": [round(scale * v, 6) for v in m.junction],
            "shared_length_m": round(scale * m.length, 6),
            "frames": {str(m.agents[0]): list(m.frames[0]), str(m.agents[1]): list(m.frames[1])},
        }
        for m in spec.meetings
    ]
    agents = []
    for a, path in enumerate(spec.paths):
        shared = np.zeros(len(path.arc), dtype=bool)
        for m in spec.meetings:
            for who, (first, last) in zip(m.agents, m.frames):
                if who == a:
                    shared[first : last + 1] = True
        agents.append(
            {
                "name": f"agent_{a}",
                "frames": len(path.arc),
                "path_length_m": round(scale * path.length(), 6),
                "jump_frames": list(path.jumps),
                "shared_frame_fraction": round(float(shared.mean()), 6),
            }
        )
    info = {k: (scale * v if k.endswith("_m") else v) for k, v in spec.info.items()}
    info = {k: (round(v, 6) if isinstance(v, float) else v) for k, v in info.items()}
    return {
        "format": "como3r-synth",
        "version": 2,  # 2: depth and surface maps as .c3z (1: .npy)
        **args,
        "frame_rate_hz": FRAME_RATE,
        "speed_m_per_frame": scale * spec.motion.speed,
        "camera": {
            "model": "pinhole",
            "convention": "OpenCV (x right, y down, z forward)",
            "hfov_deg": HFOV_DEG,
            "fx": K.fx,
            "fy": K.fy,
            "cx": K.cx,
            "cy": K.cy,
            "height_m": scale * spec.motion.height,
        },
        "covered_frames": None if spec.covered is None else list(spec.covered),
        "world": "z up, ground plane z = 0, metres; poses are T_WC",
        "depth": "float32 z-depth in metres, 0 for sky (depth/<stem>.c3z, array depth)",
        "surface": (
            "float32 (H, W, 3): texture id, s, t in metres; id -1 for sky "
            "(surface/<stem>.c3z, array surface)"
        ),
        "layout": info,
        "agents_info": agents,
        "meetings": meetings,
        "primitives": len(spec.scene.primitives),
        "textures": spec.scene.materials.kinds_of(),
    }


def synthesize(
    staging_dir: Path,
    *,
    agents: int,
    seed: int,
    overlap: float,
    frames: int,
    preset: str,
    width: int,
    height: int,
    scale: float = 1.0,
    loop_frames: int | None = None,
    progress: Callable[[], None] | None = None,
) -> SceneSpec:
    """Generate, render and write a multi-agent synthetic scene into ``staging_dir``.

    Args:
        staging_dir: existing, empty folder to write into.
        agents: number of agents N >= 1.
        seed: random seed; same arguments and seed give byte-identical files.
        overlap: fraction of each agent's path on stretches another agent also drives
            (ignored by ``no-meeting`` and for one agent).
        frames: frames per agent.
        preset: one of :data:`PRESETS`.
        width, height: image size in pixels.
        scale: factor on every length of the scene and paths, finite and > 0 (module
            docstring); 1 gives the presets' metres.
        loop_frames: lay the loop out for at least this many frames of motion per agent
            (:mod:`.presets`): a short path then turns as little per frame as a long one;
            None lays it out for ``frames``.
        progress: called once after every rendered frame.

    Returns:
        The generated scene and ground-truth paths at scale 1 (the files are scaled).

    Raises:
        InputError: unknown preset or impossible arguments.
    """
    staging_dir = Path(staging_dir)
    _validate(staging_dir, agents, overlap, frames, preset, width, height, scale, loop_frames)
    scale = float(scale)
    spec = build_preset(preset, agents, frames, float(overlap), seed, loop_frames)
    K = Intrinsics.from_hfov(width, height, HFOV_DEG)
    renderer = Renderer(spec.scene, K)
    args = {
        "preset": preset,
        "seed": seed,
        "agents": agents,
        "frames": frames,
        "overlap": float(overlap),
        "width": width,
        "height": height,
        "scale": scale,
        "loop_frames": loop_frames,
    }
    (staging_dir / "scene.json").write_text(
        json.dumps(_scene_json(spec, K, args, scale), indent=2, sort_keys=True) + "\n"
    )
    first_covered, last_covered = spec.covered if spec.covered is not None else (frames, -1)
    timestamps = np.arange(frames) / FRAME_RATE
    started = time.perf_counter()
    for a, path in enumerate(spec.paths):
        agent_dir = staging_dir / f"agent_{a}"
        for sub in ("rgb", "depth", "surface"):
            (agent_dir / sub).mkdir(parents=True)
        width_digits = max(6, len(str(frames - 1)))
        for i in range(frames):
            if first_covered <= i <= last_covered:
                frame = _covered_frame(height, width, seed, a, i)
            else:
                frame = renderer.render(path.rotations[i], path.positions[i])
            _write_frame(agent_dir, f"{i:0{width_digits}d}", frame, scale)
            if progress is not None:
                progress()
        poses = path.sim3()
        poses[:, :3] *= scale
        write_tum(agent_dir / "groundtruth.txt", timestamps, poses)
        (agent_dir / "timestamps.txt").write_text("".join(f"{t:.6f}\n" for t in timestamps))
        (agent_dir / "calib.txt").write_text(f"{K.fx:.6f} {K.fy:.6f} {K.cx:.6f} {K.cy:.6f}\n")
    logger.info("rendered %d frames in %.1f s", agents * frames, time.perf_counter() - started)
    return spec
