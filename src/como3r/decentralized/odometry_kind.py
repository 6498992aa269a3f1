"""What a robot's odometry comes from, as its input declares it: ``odometry.json`` beside
``odometry.txt``.

FLOCC-SLAM assumes every robot's odometry metric (F-Sec. III); a monocular VIO such as
VINS-Mono is off in scale at its start, until its online scale estimate converges
(F-Sec. IV-C). The pose graph can discount such a start (its steps may stretch along
themselves, :func:`~.factor_noise.odometry_noise`), which helps a VIO and bends a metric
odometry by the loops' errors, and a run cannot tell the two apart from the trajectory
(``decentralized.vio_start_scale_error``'s docstring); the robot's operator knows. So each
robot's input says which it is, and the discount applies to that robot alone (a team may mix
a VIO and a LiDAR-inertial robot):

.. code-block:: json

    {"kind": "vio"}
    {"kind": "vio", "start_scale_error": 0.2, "start_depths": 0.5}
    {"kind": "metric"}

* ``vio``: monocular or visual-inertial, its scale unconverged at the start: steps may be
  off in scale by ``start_scale_error`` (a fraction, default
  ``decentralized.vio_start_scale_error``), decaying over ``start_depths`` scene depths
  (default ``decentralized.vio_start_depths``);
* ``metric``: metric from the start (LiDAR-inertial, stereo, wheels with a lidar): no
  discount whatever the configuration says.

Without the file the kind is undeclared: the pose graph's own setting
(``decentralized.pose_graph.odom_start_scale_sigma`` over ``odom_start_spacings``, 0 by
default: metric, the paper's assumption and the behaviour before declarations existed).
``como3r synth --odometry vio|lio`` writes the declaration of the odometry it simulates.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

from como3r.config_decentralized import DecentralizedConfig
from como3r.data.agent_input import AgentInput
from como3r.decentralized.pose_graph_problem import OdometryStart
from como3r.errors import InputError

logger = logging.getLogger(__name__)

ODOMETRY_KIND_FILE = "odometry.json"
KINDS = ("vio", "metric")
"""Declarable odometry kinds (module docstring)."""

_KEYS = ("kind", "start_scale_error", "start_depths")


@dataclass(frozen=True)
class OdometryKind:
    """A robot's declared odometry (module docstring).

    Attributes:
        kind: one of :data:`KINDS`.
        start_scale_error: ``vio``: the start's scale error (fraction, >= 0); None: the
            configuration's ``vio_start_scale_error``.
        start_depths: ``vio``: its decay length in scene depths (> 0); None: the
            configuration's ``vio_start_depths``.
    """

    kind: str
    start_scale_error: float | None = None
    start_depths: float | None = None


def declaration_folder(agent: AgentInput) -> Path:
    """The folder holding an input's ``odometry.txt`` (and its declaration)."""
    return agent.root if agent.root.is_dir() else agent.root.parent


def read_odometry_kind(folder: str | Path) -> OdometryKind | None:
    """The declaration ``folder/odometry.json``; None when there is none (undeclared).

    Raises:
        InputError: naming the file, when it is not a JSON object of :data:`KINDS`'
            ``kind`` with optional finite ``start_scale_error >= 0`` and
            ``start_depths > 0`` (``vio`` only), or has other keys.
    """
    path = Path(folder) / ODOMETRY_KIND_FILE
    if not path.is_file():
        return None
    try:
        document = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: not readable JSON ({exc})") from None
    if not isinstance(document, dict):
        raise InputError(f'{path}: must be a JSON object such as {{"kind": "vio"}}')
    unknown = sorted(set(document) - set(_KEYS))
    if unknown:
        raise InputError(f"{path}: unknown key(s) {unknown} (valid: {', '.join(_KEYS)})")
    kind = document.get("kind")
    if kind not in KINDS:
        raise InputError(
            f'{path}: "kind" must be one of {", ".join(KINDS)} (LiDAR-inertial, stereo or '
            f"wheel odometry is metric), got {kind!r}"
        )
    values: dict[str, float] = {}
    for key, low, strict in (("start_scale_error", 0.0, False), ("start_depths", 0.0, True)):
        if key not in document:
            continue
        value = document[key]
        if kind != "vio":
            raise InputError(f"{path}: {key!r} applies to kind vio only, not {kind!r}")
        number = isinstance(value, (int, float)) and not isinstance(value, bool)
        if not number or not math.isfinite(value) or value < low or (strict and value == low):
            bound = "> 0" if strict else ">= 0"
            raise InputError(f"{path}: {key!r} must be a finite number {bound}, got {value!r}")
        values[key] = float(value)
    return OdometryKind(kind, **values)


def write_odometry_kind(folder: str | Path, declared: OdometryKind) -> Path:
    """Write ``folder/odometry.json`` (the keys that are set); returns its path."""
    document: dict[str, str | float] = {"kind": declared.kind}
    if declared.start_scale_error is not None:
        document["start_scale_error"] = declared.start_scale_error
    if declared.start_depths is not None:
        document["start_depths"] = declared.start_depths
    path = Path(folder) / ODOMETRY_KIND_FILE
    path.write_text(json.dumps(document) + "\n")
    return path


def odometry_start(
    declared: OdometryKind | None, settings: DecentralizedConfig
) -> OdometryStart | None:
    """The pose graph's start of a robot's odometry of kind ``declared``: ``vio`` its
    ``start_scale_error`` (or ``vio_start_scale_error``) over its ``start_depths`` (or
    ``vio_start_depths``) in keyframe spacings; ``metric`` none; None when undeclared (the
    pose graph's ``odom_start_scale_sigma`` then)."""
    if declared is None:
        return None
    if declared.kind != "vio":
        return OdometryStart()
    error = settings.vio_start_scale_error
    depths = settings.vio_start_depths
    if declared.start_scale_error is not None:
        error = declared.start_scale_error
    if declared.start_depths is not None:
        depths = declared.start_depths
    return OdometryStart(error, depths / settings.keyframe_distance_ratio)


def declared_start(
    agent: AgentInput, settings: DecentralizedConfig, log: bool = False
) -> OdometryStart | None:
    """:func:`odometry_start` of ``agent``'s declaration; with ``log``, say at info level
    what the declaration is, or that there is none.

    Raises:
        InputError: a malformed declaration (:func:`read_odometry_kind`).
    """
    folder = declaration_folder(agent)
    declared = read_odometry_kind(folder)
    start = odometry_start(declared, settings)
    if not log:
        return start
    if declared is None or start is None:  # the one is None where the other is
        logger.info(
            "%s: no %s, the odometry's kind is undeclared: its start scale error is "
            "decentralized.pose_graph.odom_start_scale_sigma, %g (0: metric; declare "
            '{"kind": "vio"} for a monocular VIO)',
            folder,
            ODOMETRY_KIND_FILE,
            settings.pose_graph.odom_start_scale_sigma,
        )
    else:
        logger.info(
            "%s: %s odometry (start scale error %.2f over %.1f keyframe spacings)",
            folder,
            declared.kind,
            start.scale_sigma,
            start.spacings,
        )
    return start
