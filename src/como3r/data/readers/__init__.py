"""Dataset readers: an unmodified dataset sequence folder as an agent input.

One module per format; each has ``matches(path) -> bool`` (the layout test of detection),
``open_sequence(path, fps) -> AgentInput`` (the common return type, from
:mod:`como3r.data.agent`) and ``ground_truth(path, ...) -> (source, Trajectory)`` (what
``como3r eval --gt`` reads):

=========  ===========================================  ===================================
format     layout                                       module
=========  ===========================================  ===================================
agent      ``rgb/`` or a video, side files (README)     :mod:`como3r.data.agent`
tum        TUM RGB-D: ``rgb.txt``, ``depth.txt``,        :mod:`como3r.data.readers.tum`
           ``groundtruth.txt``, ``rgb/``, ``depth/``
7scenes    7-Scenes: ``frame-NNNNNN.color.png|jpg``,     :mod:`como3r.data.readers.sevenscenes`
           ``.depth.png``, ``.pose.txt``
=========  ===========================================  ===================================

Detection (``format="auto"``) looks at the folder only, never at the file contents: a
folder with ``rgb.txt`` is a TUM sequence; one holding ``frame-*.color.*`` files is a
7-Scenes sequence; a file, or a folder with ``rgb/`` or a video, is an agent input; a folder
whose only sub-folder of frames is a 7-Scenes sequence is that sequence. Anything else is an
:class:`InputError` saying what each format expects.
"""

from __future__ import annotations

import math
from pathlib import Path

from como3r.data.agent import (
    IMAGE_SUFFIXES,
    VIDEO_SUFFIXES,
    AgentInput,
    open_agent_folder,
)
from como3r.data.readers import sevenscenes, tum
from como3r.errors import InputError
from como3r.io.tum import Trajectory, read_tum

#: the values of ``--format`` / ``input.format``
FORMATS = ("auto", "agent", "tum", "7scenes")

#: what each format's depth is, for messages ("no ... which --prior simulated needs")
DEPTH_SOURCES = {
    "agent": "depth/ folder",
    "tum": "depth.txt (with depth/)",
    "7scenes": "frame-NNNNNN.depth.png files",
}

_EXPECTED = ("an agent folder (rgb/ or a video file), a TUM RGB-D sequence (rgb.txt, "
             "rgb/, depth.txt, depth/, groundtruth.txt) or a 7-Scenes sequence "
             "(frame-NNNNNN.color.png, .depth.png, .pose.txt)")


def detect_format(path: str | Path) -> str:
    """The format of an existing path's layout (module docstring): ``agent``, ``tum`` or
    ``7scenes``.

    Raises:
        InputError: the path does not exist, or its layout is none of the formats.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: input does not exist")
    if path.is_file():
        return "agent"
    if tum.matches(path):
        return "tum"
    if sevenscenes.matches(path, subfolders=False):
        return "7scenes"
    if (path / "rgb").is_dir() or _has_file(path, VIDEO_SUFFIXES):
        return "agent"
    if sevenscenes.matches(path, subfolders=True):
        return "7scenes"
    hint = ""
    if _has_file(path, IMAGE_SUFFIXES):
        hint = f"; as an agent folder, its images belong in {path / 'rgb'}/"
    raise InputError(f"{path}: not an input of a known layout: expected {_EXPECTED}{hint}")


def resolve_format(path: str | Path, format: str = "auto") -> str:
    """``format`` itself, or the detected one for ``auto``.

    Raises:
        InputError: an unknown format, a missing path, no known layout (``auto``), or a
            forced ``tum`` / ``7scenes`` the folder does not match.
    """
    if format not in FORMATS:
        raise InputError(f"unknown format {format!r}; choose one of {', '.join(FORMATS)}")
    path = Path(path)
    if format == "auto":
        return detect_format(path)
    if not path.exists():
        raise InputError(f"{path}: input does not exist")
    if format == "tum" and not tum.matches(path):
        raise InputError(f"{path}: not a TUM RGB-D sequence (--format tum): expected "
                         f"{tum.EXPECTED} in it")
    if format == "7scenes" and not sevenscenes.matches(path, subfolders=True):
        raise InputError(f"{path}: not a 7-Scenes sequence (--format 7scenes): expected "
                         f"{sevenscenes.EXPECTED} in it or in one sub-folder")
    return format


def open_input(path: str | Path, fps: float = 30.0, format: str = "auto") -> AgentInput:
    """Open and validate any supported input (:func:`como3r.data.agent.open_agent`)."""
    if not (math.isfinite(fps) and fps > 0):
        raise InputError(f"fps must be a positive number, got {fps}")
    kind = resolve_format(path, format)
    if kind == "tum":
        return tum.open_sequence(Path(path), fps)
    if kind == "7scenes":
        return sevenscenes.open_sequence(Path(path), fps)
    return open_agent_folder(path, fps)


def read_ground_truth(path: str | Path, format: str = "auto",
                      fps: float = 30.0) -> tuple[Path, Trajectory]:
    """The ground-truth trajectory ``como3r eval --gt PATH`` reads.

    A file is a TUM trajectory (a video file: its folder's ``groundtruth.txt``); a folder
    is read in its format (detected as :func:`detect_format` does, but a folder holding
    only ``groundtruth.txt`` counts as an agent folder): ``groundtruth.txt`` of an agent
    folder or a TUM sequence, the ``frame-NNNNNN.pose.txt`` files of a 7-Scenes sequence
    (timestamps = frame number / ``fps``, as :func:`open_input` stamps the frames).

    Returns:
        ``(source, trajectory)``: the file or folder the poses were read from, and them.

    Raises:
        InputError: no ground truth there, or a malformed file (named).
    """
    path = Path(path)
    if path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES:
        path = path.parent
    elif not path.is_dir():
        return path, read_tum(path)
    if format == "auto":  # ground truth alone is enough: no images needed
        kind = ("tum" if tum.matches(path) else
                "7scenes" if sevenscenes.matches(path, subfolders=True) else "agent")
    else:
        kind = resolve_format(path, format)
    if kind == "tum":
        return tum.ground_truth(path)
    if kind == "7scenes":
        return sevenscenes.ground_truth(path, fps)
    gt_file = path / "groundtruth.txt"
    if not gt_file.is_file():
        raise InputError(f"{path}: agent folder has no groundtruth.txt")
    return gt_file, read_tum(gt_file)


def _has_file(folder: Path, suffixes: tuple[str, ...]) -> bool:
    return any(p.suffix.lower() in suffixes and p.is_file() for p in folder.iterdir())


__all__ = ["DEPTH_SOURCES", "FORMATS", "detect_format", "open_input", "read_ground_truth",
           "resolve_format"]
