"""Shared fixtures: dtypes and devices to parametrise over (kornia style)."""

from __future__ import annotations

import fcntl
import gc
import json
import os
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path

# Tests never take the width of the terminal they run in: rich's consoles (cli_common's are
# made when como3r.cli is imported, just below) would fix it from COLUMNS, which a terminal
# exports and pytest-xdist's workers start with (80), and the width a test gives a CLI run
# (CliRunner(env={"COLUMNS": ...})) would no longer reach the CLI's output.
for _name in ("COLUMNS", "LINES"):
    os.environ.pop(_name, None)

from como3r.cli import OMP_WAIT_POLICY  # noqa: E402

# as the como3r command sets it, before torch loads OpenMP; the CLI's subprocesses inherit it
os.environ.setdefault("OMP_WAIT_POLICY", OMP_WAIT_POLICY)

import pytest  # noqa: E402
import torch  # noqa: E402

from como3r.config import Config, apply_overrides  # noqa: E402
from como3r.data.synth import synthesize  # noqa: E402

from .io.tiny_run import OVERRIDES, tiny_run  # noqa: E402

# One intra-op thread per test process: with more threads than free cores (CI's 2 cores
# shared with subprocess tests) torch's spinning workers slow the dense front-end tests
# tenfold; results do not depend on the thread count.
torch.set_num_threads(1)


def pytest_collection_finish(session: pytest.Session) -> None:
    """What collection made (torch, the package and every test module: about 300,000 objects
    in this process) lives until the end: frozen, the interpreter's full collections during
    the tests and on the way out no longer walk it (tests/decentralized/test_flocc_protocol.py
    and tests/frontend, -n 0: 4.4 s of collections against 1.0 s; collect-only exit 3.1
    against 1.5 s). Garbage the tests make is still collected."""
    gc.freeze()


DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
DTYPES = [torch.float32, torch.float64]


@pytest.fixture(autouse=True)
def empty_weights_cache(monkeypatch, tmp_path_factory) -> None:
    """Every test sees an empty weights cache of its own, never the user's (COMO3R_HOME)."""
    monkeypatch.setenv("COMO3R_HOME", str(tmp_path_factory.mktemp("como3r_home")))
    monkeypatch.delenv("COMO3R_WEIGHTS_URL", raising=False)


@pytest.fixture(params=DEVICES)
def device(request) -> torch.device:
    """Every device this machine has (CPU always; CUDA where present)."""
    return torch.device(request.param)


@pytest.fixture(params=DTYPES, ids=["float32", "float64"])
def dtype(request) -> torch.dtype:
    """Both floating dtypes the geometry supports."""
    return request.param


@pytest.fixture
def only_error_line():
    """A check of a CLI result: its one non-empty output line, which must be an ``error:``
    line, with exit status 2; returns that line."""

    def check(result) -> str:
        lines = [line for line in result.output.splitlines() if line.strip()]
        assert result.exit_code == 2, result.output
        assert len(lines) == 1 and lines[0].startswith("error: "), result.output
        return lines[0]

    return check


@pytest.fixture(scope="module")
def undrawn_report_figures() -> Iterator[None]:
    """For a module whose tests read no figure of their runs' ``report.html`` (its
    ``pytestmark`` uses this fixture): the report is written whole (every section, table
    and note, from the run folder) but its figures are left undrawn, a sentence in the place
    of each, in the module's own process (its module fixtures included). Drawing them with
    matplotlib is nearly all of a report's cost, about 0.9 s of CPU for a 64x48 run.
    tests/evaluation/test_html.py and the CLI's end-to-end tests draw them."""
    from como3r.evaluation import html as report_html

    def undrawn(build, alt: str, caption: str = "") -> str:
        return f"<p class='missing'>The {alt} figure is not drawn in this test.</p>"

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(report_html, "image", undrawn)
        yield


@pytest.fixture(scope="session")
def made_once(tmp_path_factory) -> Callable[[str, Callable[[Path], object]], Path]:
    """``made_once(name, make)``: the folder ``name``, filled by ``make(folder)`` once per
    test session, for what tests in several files only read (a run of the pipeline or of a
    team: seconds of CPU each). Under pytest-xdist the first worker to ask makes it,
    holding a lock in the folder the session's workers share, and the others wait for it
    and read what it made, so what ``make`` makes must not depend on the worker (a scene
    renders byte for byte the same in each). Without workers: in this process's folder."""
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # the session's; each worker's own folder is inside

    def get(name: str, make: Callable[[Path], object]) -> Path:
        folder, done = root / f"made_once_{name}", root / f"made_once_{name}.done"
        with open(root / f"made_once_{name}.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
            if not done.exists():
                shutil.rmtree(folder, ignore_errors=True)  # what a failed attempt left
                folder.mkdir()
                make(folder)
                done.touch()
        return folder

    return get


@pytest.fixture(scope="session")
def tiny_run_dir(made_once) -> Path:
    """A finished two-agent run of the real pipeline on a tiny synthetic scene
    (tests/io/tiny_run.py), made once per session (:func:`made_once`) for the tests that
    only read it: the exports, the HTML report and the synthetic layout's sizes. Its scene
    is the sibling folder ``scene``."""
    return made_once("tiny_run", lambda folder: tiny_run(folder, OVERRIDES)) / "run"


#: image width and height of :func:`room_scene`'s scenes, and the ``input.long_side`` that
#: :func:`v2_case` sets
V2_WIDTH, V2_HEIGHT = 160, 120


@pytest.fixture(scope="session")
def room_scene(tmp_path_factory) -> Callable[..., tuple[list[Path], float]]:
    """``room_scene(agents, frames, scene_seed)``: a scene of benchmarks/robustness.py's
    ``room`` family (the ``default`` preset at scale 1, overlap 0.2, laid out for 100 frames
    of which each agent runs ``frames``) rendered at 160x120, made once per process; returns
    its agent folders and the mean ground-truth path of an agent (``scene.json``'s
    ``path_length_m``, the benchmark's "% of path"). The folders are shared by every test
    asking for the same scene: one that adds to them (tests/decentralized/
    test_accuracy_v2.py's odometry) keeps a scene of its own."""
    made: dict[tuple[int, int, int], tuple[list[Path], float]] = {}

    def make(agents: int, frames: int, scene_seed: int) -> tuple[list[Path], float]:
        key = (agents, frames, scene_seed)
        if key not in made:
            root = tmp_path_factory.mktemp(f"room_a{agents}_f{frames}_s{scene_seed}")
            synthesize(
                root,
                agents=agents,
                seed=scene_seed,
                overlap=0.2,
                frames=frames,
                preset="default",
                width=V2_WIDTH,
                height=V2_HEIGHT,
                loop_frames=100,
                progress=None,
            )
            info = json.loads((root / "scene.json").read_text())
            path = sum(a["path_length_m"] for a in info["agents_info"]) / agents
            made[key] = [root / f"agent_{a}" for a in range(agents)], path
        return made[key]

    return make


@pytest.fixture(scope="session")
def v2_case(room_scene) -> Callable[..., tuple[list[Path], float, Config]]:
    """``v2_case(agents, frames, scene_seed, prior_seed)``, for the accuracy tests on the
    hardest simulated prior (tests/*/test_accuracy_v2.py): :func:`room_scene`'s scene, its
    mean agent path and the configuration to run it with: the default, but for
    ``input.long_side`` 160 (the rendered width: the default 512 decodes about ten times the
    pixels, minutes per run on a CPU) and the ``v2`` prior drawn with ``prior_seed``."""

    def make(
        agents: int, frames: int, scene_seed: int, prior_seed: int
    ) -> tuple[list[Path], float, Config]:
        folders, path = room_scene(agents, frames, scene_seed)
        config = apply_overrides(
            Config(),
            [
                f"input.long_side={V2_WIDTH}",
                "simulated_prior.model=v2",
                f"simulated_prior.seed={prior_seed}",
            ],
        )
        return folders, path, config

    return make
