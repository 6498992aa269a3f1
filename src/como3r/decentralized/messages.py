"""The messages robots exchange in the decentralized mode (F-Sec. III, F-Fig. 1).

Robots share nothing but these frozen dataclasses, encoded without pickle by
:mod:`como3r.transport.codec` (msgpack with raw array bytes, size-capped and validated on
decode). Every robot-to-robot message names its ``sender``, ``recipient``, the exchange
``round`` and the mission time ``time_s`` of that round, which the router checks against
the rendezvous schedule: a message between robots that are not both in range is dropped.

Robot -> robot, in the order of a round:

* :class:`PlaceDescriptors` -- global place descriptors of new keyframes (F-Sec. III-A);
* :class:`EncodingRequest` -- which of the recipient's keyframes the sender must decode;
* :class:`EncodingReply` -- one keyframe's encoding, the latent (F-Sec. III-B), or the image the
  recipient encodes again;
* :class:`PoseGraphShare` -- to the elected robot: odometry (with its declared start,
  :mod:`.odometry_kind`), estimate and loop closures;
* :class:`PoseEstimate` -- from the elected robot: the optimised keyframe poses.

Robot <-> robot before the mission (``como3r robot``, one process per robot): a
:class:`RobotHello` answers every peer's start-up query (the team agreeing on one mission
plan; set-up, not radio traffic, not filtered, not counted).

Driver <-> robot (simulation control, not radio traffic, not counted):

* :class:`RobotTask` -- process mode only: the robot's whole job, its first message;
* :class:`RobotProgress` -- after each of the robot's rounds: how far its mission got;
* :class:`RobotReport` -- the robot's final state when the mission ends.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from como3r.decentralized.pose_graph_problem import LoopClosure, OdometryStart
from como3r.prior.base import Encoding, EncodingRecord
from como3r.transport import codec_registry
from como3r.transport.codec_types import require, require_shape

#: ``recipient`` of messages to the driver (the process that runs the simulation).
DRIVER = -1


@dataclass(frozen=True)
class PlaceDescriptors:
    """Place descriptors of keyframes ``first .. first + len(descriptors) - 1``.

    Attributes:
        descriptors: one float32 array per keyframe (``(d,)`` cosine, ``(n, d)`` ASMK).
    """

    sender: int
    recipient: int
    round: int
    time_s: float
    first: int
    descriptors: list[np.ndarray]
    version: int = 1


@dataclass(frozen=True)
class EncodingRequest:
    """The recipient's keyframes whose encodings the sender needs (possibly none: the
    sender is done requesting for this round)."""

    sender: int
    recipient: int
    round: int
    time_s: float
    keyframes: list[int]
    version: int = 1


@dataclass(frozen=True)
class EncodingReply:
    """One of the sender's keyframes, for the recipient to decode: its image's exact colours
    where the prior encodes them again (MASt3R: the recipient runs its own encoder), with its
    encoding's record where the prior makes it from both (the simulated prior's ground truth,
    :meth:`~como3r.prior.base.Encoding.portable`), else its encoding.

    Attributes:
        encoding: the keyframe's encoding (a registered prior ``Encoding``), its
            :class:`~como3r.prior.base.EncodingRecord`, or None.
        colours: ``(H, W, 3)`` uint8, the image the sender's prior encoded (the network's
            input, bit for bit: :func:`~como3r.prior.base.view_from_colors`), or None.
    """

    sender: int
    recipient: int
    round: int
    time_s: float
    keyframe: int
    encoding: Any = None
    colours: np.ndarray | None = None
    version: int = 2


@dataclass(frozen=True)
class PoseGraphShare:
    """A robot's part of the multi-robot pose graph, sent to the elected robot.

    Attributes:
        odometry: ``(K, 8)`` float64 keyframe odometry poses ``T_OC``.
        estimate: ``(K', 8)`` float64 current estimates of the first ``K'`` keyframes in
            frame ``frame`` (``K' = 0``: none yet).
        frame: id of the frame the estimate is expressed in (the robot's own id until it
            joins another robot's frame).
        loops: the loop closures it knows between robots of the round and the robots it
            relays: its own and those relayed to it.
        relayed: robot -> ``(K_r, 8)`` keyframe odometry of the robots not in the round that
            it learnt of in earlier rounds (their pose graph travels with it, so the elected
            robot solves the whole graph the group knows; :mod:`.robot`).
        start: its odometry's unconverged start, from the kind its input declares
            (:func:`~.odometry_kind.odometry_start`); None: undeclared.
        relayed_starts: the declared starts of the relayed robots that have one.
    """

    sender: int
    recipient: int
    round: int
    time_s: float
    odometry: np.ndarray
    estimate: np.ndarray
    frame: int
    loops: list[LoopClosure]
    relayed: dict[int, np.ndarray] = field(default_factory=dict)
    start: OdometryStart | None = None
    relayed_starts: dict[int, OdometryStart] = field(default_factory=dict)
    version: int = 3


@dataclass(frozen=True)
class PoseEstimate:
    """Optimised poses of the recipient's first ``len(poses)`` keyframes in frame ``frame``;
    no poses: no update this round (``frame`` is then meaningless).

    Attributes:
        relayed: robot -> ``(K_r, 8)`` keyframe odometry of the other robots of the solve,
            ``relayed_starts`` their declared odometry starts and ``loops`` its loop
            closures: the graph the recipient relays to the robots it meets later.
    """

    sender: int
    recipient: int
    round: int
    time_s: float
    poses: np.ndarray
    frame: int
    relayed: dict[int, np.ndarray] = field(default_factory=dict)
    loops: list[LoopClosure] = field(default_factory=list)
    relayed_starts: dict[int, OdometryStart] = field(default_factory=dict)
    version: int = 3


@dataclass(frozen=True)
class RobotTask:
    """Driver -> robot process: everything the robot needs.

    Attributes:
        robot: robot id.
        agent_path: the robot's agent input folder.
        config: the main configuration as a nested mapping (``config_to_dict``).
        decentralized: the :class:`~como3r.config_decentralized.DecentralizedConfig` as a
            nested mapping.
        prior: prior specification (``name``, ``weights``, ``retrieval_weights``,
            ``codebook``, ``device``; paths as strings or None).
        rounds: ``(round, time_s, group)`` of every round of the mission (the robot takes
            part in those whose group holds it).
        leave: ``(round, phase)`` at which the robot drops out (failure injection), or None.
    """

    robot: int
    agent_path: str
    config: dict[str, Any]
    decentralized: dict[str, Any]
    prior: dict[str, Any]
    rounds: list[tuple[int, float, list[int]]]
    leave: tuple[int, str] | None = None
    version: int = 1


@dataclass(frozen=True)
class RobotProgress:
    """Robot -> driver, after each round the robot took part in: how far its mission got
    (what the command line shows; :class:`~como3r.progress.AgentProgress`).

    Attributes:
        round: the round just finished.
        frames_done: its frames with odometry up to the round's mission time.
        keyframes: its keyframes up to that time.
    """

    sender: int
    recipient: int
    round: int
    frames_done: int
    keyframes: int
    version: int = 1


@dataclass(frozen=True)
class RobotReport:
    """Robot -> driver: the robot's state at the end of the mission.

    Attributes:
        estimate: ``(K', 8)`` its last estimate of its first ``K'`` keyframes (frame ``frame``).
        loops: loop closures it registered and accepted.
        rejected: registered pairs it rejected (failed fit or ratio below threshold).
        stats: counters (encodes, decodes, candidates, timings).
        left: it dropped out before the end (failure injection).
        error: what went wrong if it failed, else empty.
    """

    sender: int
    recipient: int
    estimate: np.ndarray
    frame: int
    loops: list[LoopClosure]
    rejected: list[LoopClosure]
    stats: dict[str, float] = field(default_factory=dict)
    left: bool = False
    error: str = ""
    version: int = 1


@dataclass(frozen=True)
class RobotHello:
    """Robot -> robot at start-up (``como3r robot``): who it is and which mission it runs.

    Attributes:
        robot: the robot's id.
        end_s: the mission time of its last frame with odometry [s]; the team's mission
            ends at the latest (its final exchange round).
        plan: digest of everything the robots must agree on (configuration, rendezvous
            schedule, team size, prior): robots with different plans would wait for rounds
            their peers never hold.
    """

    robot: int
    end_s: float
    plan: str
    version: int = 1


ROBOT_MESSAGES = (PlaceDescriptors, EncodingRequest, EncodingReply, PoseGraphShare, PoseEstimate)
"""Messages robots send each other (counted as radio traffic)."""

# ------------------------------------------------------------------ checks on decode
# What a robot relies on, checked at the boundary: a malformed message from a peer is
# dropped with a clear error instead of failing deep in the pose graph or the prior.


def _check_round(m: Any) -> None:
    require(
        min(m.sender, m.recipient, m.round) >= 0 and math.isfinite(m.time_s),
        "sender, recipient and round must be >= 0 and time_s finite",
    )


def _check_descriptors(m: PlaceDescriptors) -> None:
    _check_round(m)
    require(m.first >= 0, "first must be >= 0")
    for k, d in enumerate(m.descriptors):
        require(
            d.ndim in (1, 2) and d.dtype.kind == "f" and bool(np.isfinite(d).all()),
            f"descriptors[{k}] must be a finite float (d,) or (n, d) array",
        )
    require(
        len({(d.ndim, d.shape[-1]) for d in m.descriptors}) <= 1,
        "descriptors must share one shape kind and width",
    )


def _check_request(m: EncodingRequest) -> None:
    _check_round(m)
    require(
        all(k >= 0 for k in m.keyframes) and len(set(m.keyframes)) == len(m.keyframes),
        "keyframes must be distinct and >= 0",
    )


def _check_reply(m: EncodingReply) -> None:
    _check_round(m)
    require(m.keyframe >= 0, "keyframe must be >= 0")
    require(
        m.encoding is not None or m.colours is not None,
        "an encoding or colours (or both) must be given",
    )
    if m.encoding is not None:
        require(
            isinstance(m.encoding, Encoding),
            f"encoding must be a prior's Encoding, got a {type(m.encoding).__name__}",
        )
        record = isinstance(m.encoding, EncodingRecord)
        require(
            record == (m.colours is not None),
            "colours travel with an encoding's record, never with an encoding",
        )
    if m.colours is not None:
        require(
            m.colours.dtype == np.uint8 and m.colours.ndim == 3 and m.colours.shape[2] == 3,
            "colours must be an (H, W, 3) uint8 image",
        )
        require(min(m.colours.shape[:2]) > 0, "colours must not be empty")


def _check_poses(poses: np.ndarray, name: str) -> None:
    require_shape(poses, (None, 8), name)
    require(
        poses.dtype == np.float64 and bool(np.isfinite(poses).all()),
        f"{name} must be finite float64",
    )


def _check_relayed(relayed: dict[int, np.ndarray]) -> None:
    require(all(r >= 0 for r in relayed), "relayed robot ids must be >= 0")
    for r, odometry in relayed.items():
        _check_poses(odometry, f"relayed[{r}]")


def _check_starts(starts: dict[int, OdometryStart], relayed: dict[int, np.ndarray]) -> None:
    require(set(starts) <= set(relayed), "relayed_starts must be of relayed robots")


def _check_share(m: PoseGraphShare) -> None:
    _check_round(m)
    _check_poses(m.odometry, "odometry")
    _check_poses(m.estimate, "estimate")
    require(
        len(m.estimate) <= len(m.odometry) and m.frame >= 0,
        "estimate must not outnumber odometry, frame must be >= 0",
    )
    _check_relayed(m.relayed)
    _check_starts(m.relayed_starts, m.relayed)


def _check_estimate(m: PoseEstimate) -> None:
    _check_round(m)
    _check_poses(m.poses, "poses")
    _check_relayed(m.relayed)
    _check_starts(m.relayed_starts, m.relayed)


def _check_start(start: OdometryStart) -> None:
    require(
        all(math.isfinite(v) and v >= 0 for v in (start.scale_sigma, start.spacings)),
        "an odometry start's scale_sigma and spacings must be finite and >= 0",
    )


def _check_loop(loop: LoopClosure) -> None:
    require(
        min(loop.robot_a, loop.keyframe_a, loop.robot_b, loop.keyframe_b, loop.correspondences)
        >= 0,
        "robots, keyframes and correspondences >= 0",
    )
    require_shape(loop.T_ab, (8,), "T_ab")
    require(
        bool(np.isfinite(loop.T_ab).all())
        and math.isfinite(loop.ratio)
        and loop.ratio >= 0
        and 0 <= loop.probability <= 1,
        "T_ab and ratio must be finite, ratio >= 0, probability in [0, 1]",
    )


# Version 2: colours in place of an encoding the recipient's prior makes again.
codec_registry.register(EncodingReply, version=2, coded={"colours": "image"})
for _cls in (
    PlaceDescriptors,
    EncodingRequest,
    RobotTask,
    RobotProgress,
    RobotReport,
    RobotHello,
):
    codec_registry.register(_cls, version=1)
# Version 2: the relayed pose graph (``relayed``, and ``loops`` of PoseEstimate); version 3:
# the robots' declared odometry starts (``start``, ``relayed_starts``).
for _cls in (PoseGraphShare, PoseEstimate):
    codec_registry.register(_cls, version=3)
codec_registry.register(LoopClosure, version=1)
codec_registry.register(OdometryStart, version=1)
for _cls, _check in (
    (PlaceDescriptors, _check_descriptors),
    (EncodingRequest, _check_request),
    (EncodingReply, _check_reply),
    (PoseGraphShare, _check_share),
    (PoseEstimate, _check_estimate),
    (LoopClosure, _check_loop),
    (OdometryStart, _check_start),
):
    codec_registry.add_check(_cls.__name__, _check)
