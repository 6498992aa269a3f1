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
``como3r synth --odometry vio|lio`` writes the declaration of the odometry it simulates,
``como3r split`` hands each piece of a sequence its own; the file itself is read and written
by :mod:`como3r.data.odometry_declaration`.
"""

from __future__ import annotations

import logging

from como3r.config_decentralized import DecentralizedConfig
from como3r.data.agent_input import AgentInput
from como3r.data.odometry_declaration import (
    KINDS,
    ODOMETRY_KIND_FILE,
    OdometryKind,
    declaration_folder,
    read_odometry_kind,
    write_odometry_kind,
)
from como3r.decentralized.pose_graph_problem import OdometryStart

logger = logging.getLogger(__name__)

#: The file's reading and writing live in the input layer, where ``como3r split`` hands
#: each piece its declaration; the names stay importable from here.
__all__ = [
    "KINDS",
    "ODOMETRY_KIND_FILE",
    "OdometryKind",
    "declaration_folder",
    "declared_start",
    "odometry_start",
    "read_odometry_kind",
    "write_odometry_kind",
]


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
