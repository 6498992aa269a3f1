"""Dataset readers: an unmodified dataset sequence folder as an agent input.

One module per format; each has ``matches(path) -> bool`` (the layout test of detection),
``open_sequence(path, fps) -> AgentInput`` (the common return type, from
:mod:`como3r.data.agent_input`) and ``ground_truth(path, ...) -> (source, Trajectory)`` (what
``como3r eval --gt`` reads):

=========  ===========================================  ===================================
format     layout                                       module
=========  ===========================================  ===================================
agent      ``rgb/`` or a video, side files (manual)     :mod:`como3r.data.readers.agent`
tum        TUM RGB-D: ``rgb.txt``, ``depth.txt``,        :mod:`como3r.data.readers.tum`
           ``groundtruth.txt``, ``rgb/``, ``depth/``
7scenes    7-Scenes: ``frame-NNNNNN.color.png|jpg``,     :mod:`como3r.data.readers.sevenscenes`
           ``.depth.png``, ``.pose.txt``
euroc      EuRoC MAV: ``mav0/cam0/data.csv``,           :mod:`como3r.data.readers.euroc`
           ``cam0/data/``, ``cam0/sensor.yaml``,
           ``state_groundtruth_estimate0/data.csv``
kitti      KITTI odometry ``sequences/XX``:             :mod:`como3r.data.readers.kitti`
           ``image_2/`` or ``image_0/``,
           ``times.txt``, ``calib.txt``;
           ``../../poses/XX.txt``
tanks      Tanks and Temples as CoMo3R-SLAM stages      :mod:`como3r.data.readers.tanks`
           it: ``image/``, ``gt_traj.txt``
rosbag     a ROS 1 ``.bag``, a ROS 2 bag folder          :mod:`como3r.data.readers.rosbag`
           (``metadata.yaml`` with ``.db3`` or
           ``.mcap`` files); one image topic
=========  ===========================================  ===================================

Detection (``format="auto"``) looks at the folder only, never at the file contents: a
``.bag`` or ``.mcap`` file, a folder with ``metadata.yaml`` and a ``.db3`` or ``.mcap`` file,
or a ``.db3`` file in such a folder, is a ROS log; a folder with ``rgb.txt`` or
``associations.txt`` is a TUM sequence; one holding ``frame-*.color.*`` files is a 7-Scenes
sequence; one holding ``mav0/cam0/data.csv`` (or the ``mav0`` folder itself, or either with
EuRoC ground truth only) is a EuRoC sequence; one holding ``times.txt`` and ``image_2/`` or
``image_0/`` is a KITTI sequence; a file, or a folder with ``rgb/`` or a video, is an agent input; a folder with ``image/`` or
``gt_traj.txt`` is a Tanks and Temples sequence; a folder whose only sub-folder of frames is
a 7-Scenes sequence is that sequence. Anything else is an :class:`InputError` saying what
each format expects.

Live inputs (a camera, a network stream, ``como3r run --camera``) are no format of this
table: they have no length and are read while SLAM runs (:mod:`como3r.data.readers.camera`).
"""

from __future__ import annotations

import math
from pathlib import Path

from como3r.data.agent_input import IMAGE_SUFFIXES, VIDEO_SUFFIXES, AgentInput
from como3r.data.readers import euroc, kitti, rosbag, sevenscenes, tanks, tum
from como3r.data.readers.agent import open_agent_folder
from como3r.errors import InputError
from como3r.io.tum import Trajectory, read_tum

#: the values of ``--format`` / ``input.format``
FORMATS = ("auto", "agent", "tum", "7scenes", "euroc", "kitti", "tanks", "rosbag")

#: what each format's depth is, for messages ("no ... which --prior simulated needs")
DEPTH_SOURCES = {
    "agent": "depth/ folder",
    "tum": "depth.txt (with depth/)",
    "7scenes": "frame-NNNNNN.depth.png files",
    # the formats below publish no depth; named so the message says so
    "euroc": "depth (EuRoC sequences have none)",
    "kitti": "depth (KITTI odometry sequences have none)",
    "tanks": "depth (the Tanks and Temples layout has none)",
    "rosbag": "depth (the ROS log reader takes images only)",
}

#: what a forced format expects in the folder, for "not a ... (--format X)" messages
_FORCED = {
    "tum": ("a TUM RGB-D sequence", tum.matches, f"{tum.EXPECTED} in it"),
    "7scenes": (
        "a 7-Scenes sequence",
        sevenscenes.matches,
        f"{sevenscenes.EXPECTED} in it or in one sub-folder",
    ),
    "euroc": ("a EuRoC sequence", euroc.matches, f"{euroc.EXPECTED} (or the mav0 folder)"),
    "kitti": ("a KITTI odometry sequence", kitti.matches, f"{kitti.EXPECTED} in it"),
    "tanks": ("a Tanks and Temples sequence", tanks.matches, f"{tanks.EXPECTED} in it"),
    "rosbag": ("a ROS log", rosbag.matches, rosbag.EXPECTED),
}

_EXPECTED = (
    "an agent folder (rgb/ or a video file), a TUM RGB-D sequence (rgb.txt, "
    "rgb/, depth.txt, depth/, groundtruth.txt), a 7-Scenes sequence "
    "(frame-NNNNNN.color.png, .depth.png, .pose.txt), a EuRoC sequence "
    "(mav0/cam0/data.csv, mav0/cam0/data/, mav0/cam0/sensor.yaml), a KITTI odometry "
    "sequence (image_2/ or image_0/, times.txt, calib.txt), a Tanks and Temples sequence "
    "(image/, gt_traj.txt) or a ROS log (a .bag file, a ROS 2 bag folder with "
    "metadata.yaml)"
)


def detect_format(path: str | Path) -> str:
    """The format of an existing path's layout (module docstring): ``agent``, ``tum``,
    ``7scenes``, ``euroc``, ``kitti``, ``tanks`` or ``rosbag``.

    Raises:
        InputError: the path does not exist, or its layout is none of the formats.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: input does not exist")
    if rosbag.matches(path):
        return "rosbag"
    if path.is_file():
        return "agent"
    if tum.matches(path):
        return "tum"
    if sevenscenes.matches(path, subfolders=False):
        return "7scenes"
    if euroc.matches(path):
        return "euroc"
    if kitti.matches(path):
        return "kitti"
    if (path / "rgb").is_dir() or _has_file(path, VIDEO_SUFFIXES):
        return "agent"
    if tanks.matches(path):
        return "tanks"
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
            forced dataset format the folder does not match.
    """
    if format not in FORMATS:
        raise InputError(f"unknown format {format!r}; choose one of {', '.join(FORMATS)}")
    path = Path(path)
    if format == "auto":
        return detect_format(path)
    if not path.exists():
        raise InputError(f"{path}: input does not exist")
    if format in _FORCED:
        name, matches, expected = _FORCED[format]
        if not matches(path):
            raise InputError(f"{path}: not {name} (--format {format}): expected {expected}")
    return format


def open_input(
    path: str | Path, fps: float = 30.0, format: str = "auto", topic: str = ""
) -> AgentInput:
    """Open and validate any supported input (:func:`como3r.data.agent.open_agent`).

    Raises:
        InputError: as :func:`como3r.data.agent.open_agent`; also a ``topic`` for an input
            that is not a ROS log.
    """
    if not (math.isfinite(fps) and fps > 0):
        raise InputError(f"fps must be a positive number, got {fps}")
    kind = resolve_format(path, format)
    if topic and kind != "rosbag":
        raise InputError(f"{path}: --topic {topic} is for ROS logs; this is a {kind} input")
    if kind == "agent":
        return open_agent_folder(path, fps)
    if kind == "rosbag":
        return rosbag.open_sequence(Path(path), fps, topic)
    return _READERS[kind].open_sequence(Path(path), fps)


def read_ground_truth(
    path: str | Path, format: str = "auto", fps: float = 30.0
) -> tuple[Path, Trajectory]:
    """The ground-truth trajectory ``como3r eval --gt PATH`` reads.

    A file is a TUM trajectory (a video file: its folder's ``groundtruth.txt``); a folder
    is read in its format (detected as :func:`detect_format` does, but ground truth alone is
    enough: a folder holding only ``groundtruth.txt`` counts as an agent folder, one holding
    only ``gt_traj.txt`` as Tanks and Temples): ``groundtruth.txt`` of an agent folder or a
    TUM sequence, the ``frame-NNNNNN.pose.txt`` files of a 7-Scenes sequence (timestamps =
    frame number / ``fps``, as :func:`open_input` stamps the frames), the camera trajectory
    of a EuRoC sequence's ``state_groundtruth_estimate0/data.csv`` (``T_WB T_BS``), the
    ``poses/XX.txt`` beside a KITTI sequence's ``sequences/`` folder (the read camera's poses,
    stamped by ``times.txt``), a Tanks and Temples ``gt_traj.txt`` (frame id / ``fps``). A
    ROS log holds none this reader takes (an :class:`InputError` says so).

    Returns:
        ``(source, trajectory)``: the file or folder the poses were read from, and them.

    Raises:
        InputError: no ground truth there, or a malformed file (named).
    """
    path = Path(path)
    if rosbag.matches(path) and format in ("auto", "rosbag"):
        return rosbag.ground_truth(path)
    if path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES:
        path = path.parent
    elif not path.is_dir():
        return path, read_tum(path)
    if format == "auto":  # ground truth alone is enough: no images needed
        kind = next((k for k, (_, matches, _) in _FORCED.items() if matches(path)), "agent")
        if kind == "tanks" and (path / "rgb").is_dir():
            kind = "agent"
    else:
        kind = resolve_format(path, format)
    if kind in ("tum", "euroc", "kitti"):
        return _READERS[kind].ground_truth(path)
    if kind in ("7scenes", "tanks"):
        return _READERS[kind].ground_truth(path, fps)
    gt_file = path / "groundtruth.txt"
    if not gt_file.is_file():
        raise InputError(f"{path}: agent folder has no groundtruth.txt")
    return gt_file, read_tum(gt_file)


_READERS = {"tum": tum, "7scenes": sevenscenes, "euroc": euroc, "kitti": kitti, "tanks": tanks}


def _has_file(folder: Path, suffixes: tuple[str, ...]) -> bool:
    return any(p.suffix.lower() in suffixes and p.is_file() for p in folder.iterdir())


__all__ = [
    "DEPTH_SOURCES",
    "FORMATS",
    "detect_format",
    "open_input",
    "read_ground_truth",
    "resolve_format",
]
