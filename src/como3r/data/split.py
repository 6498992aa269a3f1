"""Split one monocular sequence into N agent inputs (C-Sec. B.4, C-Sec. C.4).

CoMo3R's multi-agent protocol pre-splits an original monocular RGB stream into N contiguous
sub-sequences, each handed to one agent as its own input folder; "every adjacent pair of
sub-sequences retains a short shared traversal segment" so the agents meet there.

Here the (optionally sub-sampled) stream of M frames is covered by N chunks of length
``L = M / (1 + (N - 1)(1 - overlap))`` whose starts are ``L (1 - overlap)`` apart, so
consecutive chunks share ``overlap * L`` frames and the last chunk ends on the last frame.
Chunk bounds are rounded to whole frames: lengths differ by at most one frame and an
``overlap`` of 0 gives an exact partition.

A source that declares its odometry's kind (``odometry.json``,
:mod:`~como3r.data.odometry_declaration`) hands each piece a declaration: the first piece
starts where the sequence starts and keeps it as it is; a later piece of a ``vio`` odometry
is still ``vio`` but starts where the odometry's scale estimate has had the earlier pieces'
frames to converge, so it declares ``start_scale_error`` 0 (no start discount); ``metric``
is copied as it is. Without a declaration the pieces have none (undeclared).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import shutil
from pathlib import Path

import numpy as np
from PIL import Image

from como3r.data.agent import open_agent
from como3r.data.agent_input import DEPTH_PNG_PER_METRE, AgentInput
from como3r.data.odometry_declaration import (
    OdometryKind,
    declaration_folder,
    read_odometry_kind,
    write_odometry_kind,
)
from como3r.data.poses import MAX_GAP
from como3r.errors import InputError
from como3r.io.tum import Trajectory, write_tum

logger = logging.getLogger(__name__)

ODOMETRY_MIN_TOLERANCE = 1e-3
"""Seconds; lower bound of the frame <-> odometry association window
(:data:`como3r.decentralized.keyframes.MIN_TOLERANCE_S`: data may not import it)."""

MIN_FRAMES_PER_AGENT = 2
"""An agent needs at least two frames to track anything."""


def chunk_length(num_frames: int, agents: int, overlap: float) -> float:
    """Ideal (fractional) chunk length L with ``L + (N - 1) L (1 - overlap) = M``."""
    return num_frames / (1.0 + (agents - 1) * (1.0 - overlap))


def chunk_ranges(num_frames: int, agents: int, overlap: float) -> list[tuple[int, int]]:
    """Half-open frame ranges ``[start, stop)`` of ``agents`` overlapping chunks.

    Args:
        num_frames: M, frames to cover.
        agents: N >= 1 chunks.
        overlap: fraction in [0, 1) of a chunk's length shared with the next chunk.

    Returns:
        N ranges covering ``[0, M)`` in order, consecutive ranges sharing about
        ``overlap * length`` frames (never leaving a gap).
    """
    length = chunk_length(num_frames, agents, overlap)
    step = length * (1.0 - overlap)
    ranges = []
    for a in range(agents):
        start = _round_half_up(a * step)
        stop = num_frames if a == agents - 1 else _round_half_up(a * step + length)
        ranges.append((start, stop))
    return ranges


def split_sequence(
    src: str | Path,
    out: str | Path,
    agents: int,
    overlap: float,
    stride: int = 1,
    topic: str = "",
    format: str = "auto",
) -> list[Path]:
    """Write ``out/agent_<a>/`` agent inputs, one per contiguous sub-sequence of ``src``.

    Images, depth and surface maps are hard-linked (copied across file systems; a video's
    frames, a ROS log's, and the frames of a reader that changes the pixels such as EuRoC's
    or TUM freiburg 1/2's undistortion, are written as PNG) under the frame's stem, so they
    pair up in the agent layout; depth PNGs of another scale than the agent layout's 5000 per
    metre (7-Scenes) and the depth of an undistorting reader are written as ``.npy`` float32
    metres. Each agent gets a ``timestamps.txt`` of its frames, the
    ``groundtruth.txt`` / ``odometry.txt`` rows that fall within its time span (plus
    :data:`~como3r.data.poses.MAX_GAP` either side, the samples its end frames interpolate
    between), and the source's ``calib.txt``. A source's odometry declaration
    (``odometry.json``) goes to the first agent as it is and to the later ones as it is
    too, but for a ``vio`` odometry with ``start_scale_error`` 0: their start has converged
    (module docstring).

    Args:
        src: input holding the whole sequence (agent folder or video, dataset sequence
            folder or ROS log: :func:`~como3r.data.agent.open_agent` detects it).
        out: folder to write the agent folders into.
        agents: number of agents N >= 1.
        overlap: fraction in [0, 1) of each chunk shared with the next one.
        stride: keep every ``stride``-th frame of the source before splitting.
        topic: a ROS log's image topic (empty: its only one).
        format: the source's layout (``auto``: detected; :func:`open_agent`).

    Returns:
        The N agent folders, in order.

    Raises:
        InputError: invalid arguments, too few frames, an existing non-empty agent folder,
            or a bad source (see :func:`open_agent`) or odometry declaration.
    """
    if isinstance(agents, bool) or not isinstance(agents, int) or agents < 1:
        raise InputError(f"agents must be an integer >= 1, got {agents!r}")
    if not (isinstance(overlap, (int, float)) and 0.0 <= overlap < 1.0):
        raise InputError(f"overlap must be a fraction in [0, 1), got {overlap!r}")
    if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
        raise InputError(f"stride must be an integer >= 1, got {stride!r}")
    source = open_agent(src, format=format, topic=topic)
    declared = read_odometry_kind(declaration_folder(source))
    kept = np.arange(0, source.num_frames, stride)
    length = chunk_length(len(kept), agents, overlap)
    if length < MIN_FRAMES_PER_AGENT:
        raise InputError(
            f"{src}: {len(kept)} frames (stride {stride}) are too few for {agents} agents "
            f"with overlap {overlap} ({length:.2f} per agent, need {MIN_FRAMES_PER_AGENT})"
        )
    ranges = chunk_ranges(len(kept), agents, overlap)
    out = Path(out)
    folders = [out / f"agent_{a}" for a in range(agents)]
    for folder in folders:
        if folder.exists() and any(folder.iterdir()):
            raise InputError(f"{folder}: already exists and is not empty")
    selections = [kept[start:stop] for start, stop in ranges]
    for a, (folder, frames) in enumerate(zip(folders, selections)):
        _write_side_files(source, frames, folder)
        if declared is not None:
            write_odometry_kind(folder, piece_declaration(declared, a))
    _write_images(source, selections, folders)
    logger.info("split %s (%d frames) into %d agents under %s", src, len(kept), agents, out)
    return folders


def piece_declaration(declared: OdometryKind, piece: int) -> OdometryKind:
    """The odometry declaration of piece ``piece`` (0: the first) of a split source that
    declares ``declared``: a later piece of a ``vio`` odometry starts converged
    (``start_scale_error`` 0); anything else as declared (module docstring)."""
    if piece == 0 or declared.kind != "vio":
        return declared
    return dataclasses.replace(declared, start_scale_error=0.0)


def _write_side_files(source: AgentInput, frames: np.ndarray, folder: Path) -> None:
    """Timestamps, maps, trajectories and calibration of one agent."""
    (folder / "rgb").mkdir(parents=True, exist_ok=True)
    stamps = source.timestamps[frames]
    (folder / "timestamps.txt").write_text("".join(f"{t!r}\n" for t in stamps.tolist()))
    # a reader that changes the pixels (undistortion) changes its depth maps alike
    remapped = source.video is None and not source.frames_are_files
    for name, paths in (("depth", source.depth_paths), ("surface", source.surface_paths)):
        if paths:
            (folder / name).mkdir(exist_ok=True)
            for i in frames:
                target = folder / name / f"{source.stems[i]}{paths[i].suffix}"
                if name == "depth" and (
                    remapped
                    or paths[i].suffix.lower() == ".png"
                    and (
                        source.depth_units_per_metre != DEPTH_PNG_PER_METRE
                        or source.depth_invalid != (0,)
                    )
                ):
                    np.save(target.with_suffix(".npy"), source.load_depth(int(i)))
                else:
                    _link_or_copy(paths[i], target)
    # ground truth: the samples a chunk's end frames interpolate between (como3r.data.poses);
    # odometry: the association window of como3r.decentralized.keyframes
    odometry_window = max(0.5 / source.fps, ODOMETRY_MIN_TOLERANCE)
    for name, trajectory, window in (
        ("groundtruth.txt", source.groundtruth, MAX_GAP),
        ("odometry.txt", source.odometry, odometry_window),
    ):
        if trajectory is not None:
            _write_time_slice(trajectory, stamps[0] - window, stamps[-1] + window, folder / name)
    if source.calib is not None:
        (folder / "calib.txt").write_text(" ".join(repr(v) for v in source.calib) + "\n")


def _write_images(source: AgentInput, selections: list[np.ndarray], folders: list[Path]) -> None:
    if source.frames_are_files:
        for frames, folder in zip(selections, folders):
            for i in frames:
                image = source.image_paths[i]
                _link_or_copy(image, folder / "rgb" / f"{source.stems[i]}{image.suffix}")
        return
    if source.video is None:  # the reader changes the pixels (EuRoC undistorts): decode
        for frames, folder in zip(selections, folders):
            for i in frames:
                Image.fromarray(source.load_frame(int(i)).image).save(
                    folder / "rgb" / f"{source.stems[i]}.png"
                )
        return
    targets: dict[int, list[Path]] = {}
    for frames, folder in zip(selections, folders):
        for i in frames:
            targets.setdefault(int(i), []).append(folder / "rgb" / f"{source.stems[i]}.png")
    last = max(targets)
    written = 0
    for frame in source.frames():
        for target in targets.get(frame.index, []):
            Image.fromarray(frame.image).save(target)
        written += frame.index in targets
        if frame.index == last:
            break
    if written != len(targets):
        raise InputError(f"{source.video}: could only decode {written} of {len(targets)} frames")


def _write_time_slice(trajectory: Trajectory, begin: float, end: float, path: Path) -> None:
    """Rows of ``trajectory`` with ``begin <= t <= end`` as a TUM file (none: no file)."""
    keep = (trajectory.timestamps >= begin) & (trajectory.timestamps <= end)
    if not keep.any():
        logger.warning("%s: no trajectory rows within [%f, %f]; not written", path, begin, end)
        return
    rows = np.flatnonzero(keep)
    write_tum(path, trajectory.timestamps[rows], trajectory.T_WC[rows])


def _link_or_copy(src: Path, dst: Path) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def _round_half_up(x: float) -> int:
    return int(math.floor(x + 0.5))
