"""Shared fixtures of the decentralized-mode tests: one small synthetic scene, rendered once.

The scene is the ``forward`` preset (cameras driving a ring road at 0.4 m per frame) with
three robots of 60 frames at 96x72 pixels, each with LIO-like odometry (the paper's
accurate-odometry backbone, F-Table III). The simulated prior gets a MASt3R-like scale
inconsistency between pairs (``scale_sigma`` 0.25; F-Sec. III-C: the prior's relative
scales are "often inconsistent or very imprecise"), which is what the scale-aware
formulations address.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from como3r.config import Config, InputConfig, SimulatedPriorConfig
from como3r.data.synth import synthesize
from como3r.decentralized.config import DecentralizedConfig, ProtocolConfig
from como3r.decentralized.odometry_sim import add_odometry

ROBOTS = 3


@pytest.fixture(scope="session")
def scene(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Agent folders of a 3-robot synthetic scene with ``odometry.txt``."""
    root = tmp_path_factory.mktemp("flocc_scene")
    synthesize(root, agents=ROBOTS, seed=6, overlap=0.6, frames=60, preset="forward",
               width=96, height=72)
    paths = [root / f"agent_{a}" for a in range(ROBOTS)]
    for a, path in enumerate(paths):
        add_odometry(path, seed=60 + a, params="lio")
    return paths


@pytest.fixture(scope="session")
def main_config() -> Config:
    """Network resolution of the scene; MASt3R-like scale inconsistency of the prior, on the
    easy simulated prior (registration and accuracy bounds fail under the realistic one)."""
    return Config(input=InputConfig(long_side=96),
                  simulated_prior=SimulatedPriorConfig(model="easy", scale_sigma=0.25))


def flocc_settings(keyframe_distance_m: float = 2.0, timeout_s: float = 60.0,
                   processes: bool = False, table: bool = False) -> DecentralizedConfig:
    """Decentralized settings for tests: threads, short timeouts, sparse keyframes."""
    return DecentralizedConfig(keyframe_distance_m=keyframe_distance_m, table=table,
                               protocol=ProtocolConfig(processes=processes,
                                                       message_timeout_s=timeout_s))


@pytest.fixture(scope="session")
def settings_factory():
    """:func:`flocc_settings`, for test modules (which cannot import this file)."""
    return flocc_settings
