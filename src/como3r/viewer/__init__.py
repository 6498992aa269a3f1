"""The live 3D viewer: the live events of a run (:mod:`como3r.live`) shown in rerun
(manual: docs/viewer.md).

An optional extra: ``pip install "como3r[viewer]"`` installs ``rerun-sdk``, and nothing
else in como3r imports it. This module does not either; :func:`open_viewer` imports
:mod:`como3r.viewer.recording` (which imports ``rerun``) only when a viewer is opened, and
:func:`check_viewer` tells, before a run does any work, whether it can be.

One process owns the recording: the one that runs the coordinator. In the multi-process
runtime the agent processes send a small typed :class:`~como3r.live.FrameEvent` per frame
(pose, intrinsics, an image of at most 256 px) with their other messages, and everything
else the viewer shows (keyframes, the merged map, edges, final trajectories) is already in
the coordinator's process. Rerun could also merge several processes' streams into one
recording id, but ``save`` needs one writer of the file, the agents would each need the
optional dependency and a connection, and the coordinator's process would still have to
log the map; one owner keeps the agents free of rerun and the three modes alike.
"""

from __future__ import annotations

import importlib
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from como3r.errors import InputError
from como3r.viewer.spec import MODES, ViewerSpec

if TYPE_CHECKING:
    from como3r.viewer.recording import RerunViewer

__all__ = [
    "MODES",
    "INSTALL",
    "ViewerSpec",
    "check_viewer",
    "open_viewer",
    "parse_viewer",
    "require_rerun",
]


#: how to get the optional dependency
INSTALL = 'pip install "como3r[viewer]"'


def parse_viewer(value: str) -> ViewerSpec:
    """``spawn``, ``serve`` or ``save=FILE.rrd`` (the command line turns
    ``--viewer save FILE.rrd`` into the last).

    Raises:
        InputError: another mode, ``save`` without a file, or a file not named ``.rrd``.
    """
    mode, _, path = value.partition("=")
    if mode not in MODES:
        raise InputError(f"unknown --viewer {value!r}; choose spawn, serve or save FILE.rrd")
    if mode != "save":
        if path:
            raise InputError(f"--viewer {mode} takes no file (only save FILE.rrd does)")
        return ViewerSpec(mode)
    if not path:
        raise InputError("--viewer save needs a file: --viewer save FILE.rrd")
    if Path(path).suffix != ".rrd":
        raise InputError(f"--viewer save {path}: a rerun recording is named FILE.rrd")
    return ViewerSpec(mode, Path(path))


def require_rerun() -> None:
    """Import ``rerun`` or fail with the line that says how to install it.

    Raises:
        InputError: ``rerun-sdk`` is not installed (or does not import).
    """
    try:
        importlib.import_module("rerun")
    except ImportError as exc:
        missing = isinstance(exc, ModuleNotFoundError) and exc.name == "rerun"
        why = "is not installed" if missing else f"does not import ({exc})"
        raise InputError(f"--viewer needs the optional rerun-sdk, which {why}: {INSTALL}") from None


def check_viewer(value: str, out: Path) -> ViewerSpec:
    """The viewer a command asked for, checked before any work: a valid mode, a display for
    ``spawn`` (Linux: ``DISPLAY`` or ``WAYLAND_DISPLAY``; rerun's viewer cannot start
    without one and the run would log into the void), a recording file outside the run's
    output folder ``out`` (written whole at the end) in an existing folder, and rerun
    importable.

    Raises:
        InputError: naming what is wrong (one line).
    """
    spec = parse_viewer(value)
    if (
        spec.mode == "spawn"
        and sys.platform.startswith("linux")
        and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    ):
        raise InputError(
            "--viewer spawn needs a display (DISPLAY and WAYLAND_DISPLAY are "
            "unset); on a headless machine use --viewer serve or save FILE.rrd"
        )
    if spec.path is not None:
        path = spec.path.resolve()
        if path.is_relative_to(out.resolve()):
            raise InputError(
                f"--viewer save {spec.path}: write the recording outside --out "
                f"{out} (the output folder appears only when the run is done)"
            )
        if not path.parent.is_dir():
            raise InputError(f"--viewer save {spec.path}: folder {spec.path.parent} does not exist")
    require_rerun()
    return spec


def open_viewer(
    spec: ViewerSpec, grpc_port: int | None = None, web_port: int | None = None
) -> RerunViewer:
    """A :class:`~como3r.viewer.recording.RerunViewer` for ``spec`` (imports rerun).

    Args:
        spec: where the events go.
        grpc_port: ``serve``: the port of the recording's gRPC server (None: rerun's 9876).
        web_port: ``serve``: the port of the web viewer (None: rerun's 9090).

    Raises:
        InputError: rerun is not installed.
    """
    require_rerun()
    from como3r.viewer.recording import RerunViewer

    return RerunViewer(spec, grpc_port=grpc_port, web_port=web_port)
