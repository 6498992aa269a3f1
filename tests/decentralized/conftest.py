"""Shared fixtures of the decentralized-mode tests: one small synthetic scene, rendered once.

The scene is the ``forward`` preset (cameras driving a ring road at 0.4 m per frame) with
three robots of 60 frames at 96x72 pixels, each with LIO-like odometry (the paper's
accurate-odometry backbone, F-Table III). The simulated prior gets a MASt3R-like scale
inconsistency between pairs (``scale_sigma`` 0.25; F-Sec. III-C: the prior's relative
scales are "often inconsistent or very imprecise"), which is what the scale-aware
formulations address.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from como3r.config import Config, InputConfig, SimulatedPriorConfig
from como3r.config_decentralized import DecentralizedConfig, ProtocolConfig
from como3r.data.synth import synthesize
from como3r.decentralized.odometry_sim import add_odometry
from como3r.io.packed_arrays import read_packed, write_packed

ROBOTS = 3


@pytest.fixture(scope="session")
def scene(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Agent folders of a 3-robot synthetic scene with ``odometry.txt``."""
    root = tmp_path_factory.mktemp("flocc_scene")
    synthesize(
        root, agents=ROBOTS, seed=6, overlap=0.6, frames=60, preset="forward", width=96, height=72
    )
    paths = [root / f"agent_{a}" for a in range(ROBOTS)]
    for a, path in enumerate(paths):
        add_odometry(path, seed=60 + a, params="lio")
    return paths


@pytest.fixture(scope="session")
def main_config() -> Config:
    """Network resolution of the scene; MASt3R-like scale inconsistency of the prior, on the
    easy simulated prior: the tests compare registrations and formulations (F-Tables II-III)
    by margins that the realistic prior's errors cover (their bounds fail under it).
    Merged accuracy on the v2 prior: test_accuracy_v2.py."""
    return Config(
        input=InputConfig(long_side=96),
        simulated_prior=SimulatedPriorConfig(model="easy", scale_sigma=0.25),
    )


def flocc_settings(
    keyframe_distance_ratio: float = 0.22,
    timeout_s: float = 60.0,
    processes: bool = False,
    table: bool = False,
) -> DecentralizedConfig:
    """Decentralized settings for tests: threads, short timeouts, sparse keyframes (0.22 of
    the scene depth: about 2 m at the scene's 7-10 m median depth)."""
    return DecentralizedConfig(
        keyframe_distance_ratio=keyframe_distance_ratio,
        table=table,
        protocol=ProtocolConfig(processes=processes, message_timeout_s=timeout_s),
    )


@pytest.fixture(scope="session")
def settings_factory():
    """:func:`flocc_settings`, for test modules (which cannot import this file)."""
    return flocc_settings


def _scale_tum(path: Path, factor: float) -> None:
    rows = [line.split() for line in path.read_text().splitlines()]
    lines = [
        " ".join(
            row
            if not row or row[0].startswith("#")
            else [row[0], *(f"{float(v) * factor:.9f}" for v in row[1:4]), *row[4:]]
        )
        for row in rows
    ]
    path.write_text("\n".join(lines) + "\n")


def scaled_scene(agents: list[Path], target: Path, factor: float) -> list[Path]:
    """Copies of agent folders with every length multiplied by ``factor``: depth maps, the
    s and t channels of surface maps, ground-truth and odometry translations (the same
    world, bigger or smaller).

    Returns:
        The copied agent folders under ``target``.
    """
    copies = []
    for agent in agents:
        copy = target / agent.name
        shutil.copytree(agent, copy)
        for depth in (copy / "depth").glob("*.c3z"):
            write_packed(depth, {"depth": read_packed(depth)["depth"] * np.float32(factor)})
        for surface in (copy / "surface").glob("*.c3z"):
            keys = read_packed(surface)["surface"]
            keys[..., 1:3] *= np.float32(factor)
            write_packed(surface, {"surface": keys})
        for name in ("groundtruth.txt", "odometry.txt"):
            _scale_tum(copy / name, factor)
        copies.append(copy)
    return copies


@pytest.fixture(scope="session")
def scene_scaler():
    """:func:`scaled_scene`, for test modules."""
    return scaled_scene
