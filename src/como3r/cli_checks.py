"""The checks ``como3r run`` and the network commands (``coordinator``, ``agent``, ``robot``)
make before any work, and the summary tables ``run``, ``coordinator``, ``robot`` and ``merge``
print after: the configuration from ``--config``, ``--set`` and the flags, ``--resume``
against the stored session, ``--format``, ``--camera``, each input's layout and what
``--prior simulated`` needs of it, and ``--device``.

The command modules (:mod:`como3r.cli`, :mod:`como3r.cli_network`, :mod:`como3r.cli_sessions`)
import it; it imports none of them.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING

from como3r.cli_common import console, print_rows
from como3r.errors import InputError

if TYPE_CHECKING:
    from como3r.data.readers.camera import CameraSource


FORMAT_HELP = (
    "Layout of the input folders: auto (detect) | agent | tum (TUM RGB-D) | "
    "7scenes | euroc (EuRoC MAV) | kitti (KITTI odometry) | tanks (Tanks and "
    "Temples) | rosbag (ROS 1 .bag, ROS 2 bag folder)."
)


def config_from_options(
    config_file: Path | None,
    overrides: list[str],
    calib: bool,
    no_loop_closure: bool,
    format: str | None = None,
    topic: str | None = None,
):
    """The run's configuration: ``--config`` (or the defaults), its ``--set`` overrides, then
    the flags and ``--format``/``--topic``."""
    import dataclasses

    from como3r.config import Config, apply_overrides, load_config

    config = load_config(config_file) if config_file is not None else Config()
    extra = (["calibrated=true"] if calib else []) + (
        ["loop_closure=false"] if no_loop_closure else []
    )
    if format is not None:
        extra.append(f"input.format={format}")
    config = apply_overrides(config, [*overrides, *extra])
    if topic is not None:  # as given: a topic is any string, not a YAML scalar
        config = dataclasses.replace(config, input=dataclasses.replace(config.input, topic=topic))
    return config


def check_resumable(out: Path, config) -> None:
    """The killed run in ``out.partial`` has a session store made with ``config``."""
    from como3r.config import differing_key
    from como3r.store.reader import read_config
    from como3r.store.schema import STORE_NAME

    store = out.with_name(out.name + ".partial") / STORE_NAME
    difference = differing_key(read_config(store), config)
    if difference is not None:
        raise InputError(
            f"--resume: the configuration differs from the stored session's "
            f"({difference}); give the options of the run that was killed"
        )


def check_format(format: str) -> None:
    """``--format`` names a known input layout (:data:`como3r.data.readers.FORMATS`)."""
    from como3r.data.readers import FORMATS

    if format not in FORMATS:
        raise InputError(f"unknown --format {format!r}; choose one of {', '.join(FORMATS)}")


def camera_sources(
    camera: list[str], max_frames: int | None, agent: list[Path], prior: str, mode: str
) -> list[CameraSource]:
    """The :class:`~como3r.data.readers.camera.CameraSource` of each ``--camera``, after
    the checks of what a live input cannot do.

    Raises:
        InputError: no input at all, --camera beside --agent, --max-frames without
            --camera, or a live input with the simulated prior or the decentralized mode.
    """
    from como3r.data.readers.camera import parse_source

    if not camera:
        if not agent:
            raise InputError(
                "no input: give --agent PATH or --camera SOURCE (see: como3r run --help)"
            )
        if max_frames is not None:
            raise InputError("--max-frames ends --camera streams; there is none")
        return []
    if agent:
        raise InputError("a run takes recorded inputs (--agent) or live ones (--camera), not both")
    if prior == "simulated":
        raise InputError(
            "--camera: a live camera has no depth, which --prior simulated needs "
            "(a stand-in made from ground-truth depth); use --prior mast3r"
        )
    if mode == "decentralized":
        raise InputError(
            "--camera: --mode decentralized needs each robot's odometry "
            "(odometry.txt), which a live camera does not give"
        )
    return [parse_source(text, max_frames) for text in camera]


def check_input(path: Path, config, prior: str, every_pose: bool = False) -> bool:
    """An input opened before any work and before MASt3R's weights are looked for (its
    layout, files and image headers: :func:`como3r.data.agent.open_agent`), and what
    ``--prior simulated`` needs of it: depth, intrinsics and ground-truth poses (or
    appearance keys); frames without a pose (before the first, after the last, in a gap
    wider than :data:`como3r.data.poses.MAX_GAP`) are skipped by the run, with one warning,
    so at least one frame must have one; ``every_pose``: every frame must (decentralized
    robots pick their keyframes by odometry and do not skip frames).

    Returns:
        Whether ``--prior simulated`` could run the input (depth, intrinsics, and appearance
        keys or a ground-truth pose for some frame).

    Raises:
        InputError: naming the input and what is wrong with it or what it lacks; images
            alone take --prior mast3r.
    """
    from como3r.data.agent import open_agent, quiet_reading
    from como3r.data.poses import MAX_GAP
    from como3r.data.readers import DEPTH_SOURCES

    with quiet_reading():  # the run opens it again and says the readers' warnings once
        source = open_agent(
            path,
            fps=config.input.frame_rate_hz,
            format=config.input.format,
            topic=config.input.topic,
        )
    if prior != "simulated":
        return bool(
            source.has_depth
            and source.calib is not None
            and (
                source.has_surface or (source.groundtruth is not None and source.has_gt_pose.any())
            )
        )
    needs = (
        "which --prior simulated needs (a stand-in made from ground-truth depth); "
        "images alone take --prior mast3r"
    )
    if not source.has_depth:
        raise InputError(f"{path}: no {DEPTH_SOURCES[source.format]}, {needs}")
    if source.calib is None:
        raise InputError(f"{path}: no intrinsics (calib.txt 'fx fy cx cy'), {needs}")
    if not source.has_surface:
        if source.groundtruth is None:
            raise InputError(f"{path}: no ground truth, {needs}")
        has = source.has_gt_pose
        if not has.any():
            raise InputError(
                f"{path}: no frame has a ground-truth pose within {MAX_GAP:g} s, {needs}"
            )
        if every_pose and not has.all():
            raise InputError(
                f"{path}: {int((~has).sum())} of {source.num_frames} frames have "
                f"no ground-truth pose within {MAX_GAP:g} s, which --prior "
                "simulated needs for every frame in --mode decentralized"
            )
    return True


def check_device(device: str) -> None:
    """``--device`` is cpu, cuda or cuda:N, and CUDA only where this torch can use it.

    Raises:
        InputError: another device, or CUDA that torch cannot reach (no silent CPU run).
    """
    if device == "cpu":
        return
    match = re.fullmatch(r"cuda(?::(\d+))?", device)
    if match is None:
        raise InputError(f"unknown --device {device!r}; choose cpu or cuda")
    import torch

    if not torch.cuda.is_available():
        why = (
            f"this torch ({torch.__version__}) is built without CUDA"
            if torch.version.cuda is None
            else "torch finds no usable CUDA device"
        )
        raise InputError(f"--device {device}: {why}; use --device cpu")
    count = torch.cuda.device_count()
    if int(match.group(1) or 0) >= count:
        raise InputError(f"--device {device}: this machine has {count} CUDA device(s)")


def print_summary(summary, out: Path) -> None:
    """The final tables of a run."""
    print_rows("agents", summary.agents)
    if summary.evaluation is not None:
        print_rows("ATE RMSE [m] (Sim(3)-aligned)", summary.evaluation.table_rows())
    for line in summary.notes:
        console.print(line)
    console.print(f"wrote {out}")
