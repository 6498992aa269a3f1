"""``synthesize``: render a preset scene and write it in the agent input format.

Layout (DESIGN.md, "Command line and files")::

    scene.json                      preset, seed, parameters, intrinsics, meetings
    agent_<a>/rgb/<stem>.png        8-bit RGB
    agent_<a>/depth/<stem>.npy      float32 z-depth in metres, 0 for sky
    agent_<a>/surface/<stem>.npy    float32 (H, W, 3) appearance keys (id, s, t), id -1 sky
    agent_<a>/groundtruth.txt       TUM, T_WC (OpenCV camera, world z up)
    agent_<a>/timestamps.txt        one time per line, frame i at i / 30 s
    agent_<a>/calib.txt             fx fy cx cy

Everything is a deterministic function of the arguments: the same call writes
byte-identical files.
"""

from __future__ import annotations

import json
import logging
import math
import numbers
import time
from pathlib import Path
from typing import Callable

import numpy as np
from PIL import Image

from como3r.data.synth.presets import PRESETS, SceneSpec, build_preset
from como3r.data.synth.render import Frame, Intrinsics, Renderer
from como3r.errors import InputError
from como3r.io.tum import write_tum

logger = logging.getLogger(__name__)

FRAME_RATE = 30.0
HFOV_DEG = 75.0
MAX_AGENTS = 64
MAX_FRAMES = 100_000
MIN_SIZE = 8
MAX_SIZE = 4096


def _validate(staging_dir: Path, agents: int, overlap: float, frames: int, preset: str,
              width: int, height: int) -> None:
    if preset not in PRESETS:
        raise InputError(f"--preset: unknown preset {preset!r} (valid: {', '.join(PRESETS)})")
    if not isinstance(agents, numbers.Integral) or not 1 <= agents <= MAX_AGENTS:
        raise InputError(f"--agents: must be an integer in [1, {MAX_AGENTS}], got {agents!r}")
    if not isinstance(frames, numbers.Integral) or not 2 <= frames <= MAX_FRAMES:
        raise InputError(f"--frames: must be an integer in [2, {MAX_FRAMES}], got {frames!r}")
    if not (isinstance(overlap, numbers.Real) and math.isfinite(overlap) and 0 <= overlap <= 1):
        raise InputError(f"--overlap: must be a number in [0, 1], got {overlap!r}")
    for name, size in (("--width", width), ("--height", height)):
        if not isinstance(size, numbers.Integral) or not MIN_SIZE <= size <= MAX_SIZE:
            raise InputError(
                f"{name}: must be an integer in [{MIN_SIZE}, {MAX_SIZE}], got {size!r}")
    if not staging_dir.is_dir():
        raise InputError(f"{staging_dir}: output folder does not exist")


def _write_frame(agent_dir: Path, stem: str, frame: Frame) -> None:
    # Level 1: noisy textures hardly compress, and level 6 costs more than rendering.
    Image.fromarray(frame.rgb).save(agent_dir / "rgb" / f"{stem}.png", compress_level=1)
    np.save(agent_dir / "depth" / f"{stem}.npy", frame.depth)
    np.save(agent_dir / "surface" / f"{stem}.npy", frame.surface)


def _scene_json(spec: SceneSpec, K: Intrinsics, args: dict) -> dict:
    """Everything about the scene a consumer may want, JSON-serialisable."""
    meetings = [{
        "agents": list(m.agents),
        "junction_xy": [round(v, 6) for v in m.junction],
        "shared_length_m": round(m.length, 6),
        "frames": {str(m.agents[0]): list(m.frames[0]), str(m.agents[1]): list(m.frames[1])},
    } for m in spec.meetings]
    agents = []
    for a, path in enumerate(spec.paths):
        shared = np.zeros(len(path.arc), dtype=bool)
        for m in spec.meetings:
            for who, (first, last) in zip(m.agents, m.frames):
                if who == a:
                    shared[first:last + 1] = True
        agents.append({"name": f"agent_{a}", "frames": len(path.arc),
                       "path_length_m": round(float(path.arc[-1] - path.arc[0]), 6),
                       "shared_frame_fraction": round(float(shared.mean()), 6)})
    info = {k: (round(v, 6) if isinstance(v, float) else v) for k, v in spec.info.items()}
    return {
        "format": "como3r-synth",
        "version": 1,
        **args,
        "frame_rate_hz": FRAME_RATE,
        "speed_m_per_frame": spec.motion.speed,
        "camera": {"model": "pinhole", "convention": "OpenCV (x right, y down, z forward)",
                   "hfov_deg": HFOV_DEG, "fx": K.fx, "fy": K.fy, "cx": K.cx, "cy": K.cy,
                   "height_m": spec.motion.height},
        "world": "z up, ground plane z = 0, metres; poses are T_WC",
        "depth": "float32 z-depth in metres, 0 for sky",
        "surface": "float32 (H, W, 3): texture id, s, t in metres; id -1 for sky",
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
        progress: called once after every rendered frame.

    Returns:
        The generated scene and ground-truth paths.

    Raises:
        InputError: unknown preset or impossible arguments.
    """
    staging_dir = Path(staging_dir)
    _validate(staging_dir, agents, overlap, frames, preset, width, height)
    spec = build_preset(preset, agents, frames, float(overlap), seed)
    K = Intrinsics.from_hfov(width, height, HFOV_DEG)
    renderer = Renderer(spec.scene, K)
    args = {"preset": preset, "seed": seed, "agents": agents, "frames": frames,
            "overlap": float(overlap), "width": width, "height": height}
    (staging_dir / "scene.json").write_text(
        json.dumps(_scene_json(spec, K, args), indent=2, sort_keys=True) + "\n")
    timestamps = np.arange(frames) / FRAME_RATE
    started = time.perf_counter()
    for a, path in enumerate(spec.paths):
        agent_dir = staging_dir / f"agent_{a}"
        for sub in ("rgb", "depth", "surface"):
            (agent_dir / sub).mkdir(parents=True)
        width_digits = max(6, len(str(frames - 1)))
        for i in range(frames):
            frame = renderer.render(path.rotations[i], path.positions[i])
            _write_frame(agent_dir, f"{i:0{width_digits}d}", frame)
            if progress is not None:
                progress()
        write_tum(agent_dir / "groundtruth.txt", timestamps, path.sim3())
        (agent_dir / "timestamps.txt").write_text("".join(f"{t:.6f}\n" for t in timestamps))
        (agent_dir / "calib.txt").write_text(f"{K.fx:.6f} {K.fy:.6f} {K.cx:.6f} {K.cy:.6f}\n")
    logger.info("rendered %d frames in %.1f s", agents * frames, time.perf_counter() - started)
    return spec
