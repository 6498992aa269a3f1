"""Logging the live events of a run (:mod:`como3r.live`) to one rerun recording.

The only module of como3r that imports ``rerun`` (``pip install "como3r[viewer]"``); it is
imported when a viewer is opened (:func:`como3r.viewer.open_viewer`).

Entities (``<a>`` an agent id, ``<k>`` a keyframe id; world frame x right, y down, z forward
as the first camera sees it):

* ``world/agents/<a>/camera`` -- the frame's pose (Sim(3): translation, rotation, scale);
  ``.../camera/image`` its pinhole (the current intrinsics, drawn as a frustum) and image;
* ``world/agents/<a>/trajectory`` -- the camera centres so far, as tracked (the final
  trajectory replaces it at the end);
* ``world/agents/<a>/keyframes/<k>`` -- the keyframe's pose, ``.../points`` its confident
  points in its camera frame, in the agent's colour; map events move the poses;
* ``world/map/points`` -- the merged map after each gauge merge, global solve and at the end,
  coloured by agent; ``world/map/edges/inter`` and ``world/map/edges/loop`` -- cross-agent and
  (at the end) intra-agent loop edges, line segments between keyframe centres;
* ``agents/<a>/state`` -- the tracking state per frame (``tracking``, ``lost``,
  ``relocalized``); ``coordinator/events`` -- one line per map event.

Timelines: ``frame`` -- an agent's frame index for its frame events; coordinator events
(keyframes, map, trajectories) take the highest frame index any agent has reached, so the
map at frame ``n`` is what the coordinator had when the team got there; ``wall_time`` --
when the event was made (an agent's frames: in the agent's process).
"""

from __future__ import annotations

import logging
import urllib.parse

import numpy as np
import rerun as rr

from como3r.errors import InputError
from como3r.live import FrameEvent, KeyframeEvent, LiveEvent, MapEvent, TrajectoryEvent
from como3r.viewer.spec import ViewerSpec

logger = logging.getLogger(__name__)

#: agent colours (RGB), agent ``a`` takes ``PALETTE[a % len(PALETTE)]``
PALETTE = np.array(
    [
        [31, 119, 180],
        [255, 127, 14],
        [44, 160, 44],
        [214, 39, 40],
        [148, 103, 189],
        [140, 86, 75],
        [227, 119, 194],
        [127, 127, 127],
        [188, 189, 34],
        [23, 190, 207],
    ],
    dtype=np.uint8,
)

#: edge colours by kind
EDGE_COLORS = {"inter": (255, 255, 255), "loop": (255, 215, 0)}

#: JPEG quality of the logged frame images (keeps a recording small)
JPEG_QUALITY = 80

#: a frustum reaches this fraction of the agent's latest keyframe's median depth
FRUSTUM_DEPTH = 0.2


def agent_color(agent: int) -> np.ndarray:
    """``(3,)`` uint8 the colour of an agent."""
    return PALETTE[agent % len(PALETTE)]


def sim3_transform(T_WC: np.ndarray) -> rr.Transform3D:
    """The rerun transform (parent from child) of an ``(8,)`` Sim(3) pose."""
    return rr.Transform3D(
        translation=T_WC[:3], quaternion=rr.Quaternion(xyzw=T_WC[3:7]), scale=float(T_WC[7])
    )


class RerunViewer:
    """A live-event sink (:data:`como3r.live.LiveCallback`) that logs to one rerun recording.

    Args:
        spec: ``spawn`` (start the native viewer and stream to it), ``serve`` (a gRPC server
            and a web viewer, see :attr:`urls`) or ``save`` (write ``spec.path``).
        grpc_port: ``serve``: the gRPC server's port (None: rerun's default 9876).
        web_port: ``serve``: the web viewer's port (None: rerun's default 9090).

    Raises:
        InputError: rerun could not start the viewer or open the file.
    """

    def __init__(
        self, spec: ViewerSpec, grpc_port: int | None = None, web_port: int | None = None
    ) -> None:
        self.spec = spec
        self.rec = rr.RecordingStream("como3r")
        #: ``serve``: ``(gRPC URL for `rerun URL`, web viewer URL)``, with localhost
        self.urls: tuple[str, str] | None = None
        try:
            if spec.mode == "save":
                self.rec.save(str(spec.path))
            elif spec.mode == "spawn":
                self.rec.spawn()
            else:
                grpc = self.rec.serve_grpc(grpc_port=grpc_port)
                rr.serve_web_viewer(web_port=web_port, open_browser=False, connect_to=grpc)
                web = (
                    f"http://localhost:{9090 if web_port is None else web_port}/?url="
                    + urllib.parse.quote(grpc, safe=":/")
                )
                self.urls = (grpc, web)
        except (OSError, RuntimeError, ValueError) as exc:
            raise InputError(f"--viewer {spec.mode}: rerun could not start ({exc})") from None
        self.rec.log("world", rr.ViewCoordinates.RDF, static=True)
        self.frame = 0  # the highest frame index so far: the coordinator events' time
        self.positions: dict[int, list[np.ndarray]] = {}
        self.depth: dict[int, float] = {}  # agent -> its latest keyframe's median depth

    def __call__(self, event: LiveEvent) -> None:
        if isinstance(event, FrameEvent):
            self.frame_event(event)
        elif isinstance(event, KeyframeEvent):
            self.keyframe_event(event)
        elif isinstance(event, MapEvent):
            self.map_event(event)
        else:
            self.trajectory_event(event)

    def _time(self, frame: int, wall_time: float) -> None:
        self.rec.reset_time()
        self.rec.set_time("frame", sequence=frame)
        self.rec.set_time("wall_time", timestamp=wall_time)

    def frame_event(self, e: FrameEvent) -> None:
        """Camera pose and frustum, image, trajectory so far, tracking state."""
        self.frame = max(self.frame, e.frame_index)
        self._time(e.frame_index, e.wall_time)
        base, color = f"world/agents/{e.agent}", agent_color(e.agent)
        if e.T_WC is not None:
            self.rec.log(f"{base}/camera", sim3_transform(e.T_WC))
            positions = self.positions.setdefault(e.agent, [])
            positions.append(e.T_WC[:3])
            self.rec.log(f"{base}/trajectory", rr.LineStrips3D([np.stack(positions)], colors=color))
        height, width = e.image.shape[:2]
        if e.K is not None:
            self.rec.log(
                f"{base}/camera/image",
                rr.Pinhole(
                    image_from_camera=e.K,
                    resolution=[width, height],
                    image_plane_distance=FRUSTUM_DEPTH * self.depth.get(e.agent, 1.0),
                    color=color,
                ),
            )
        self.rec.log(
            f"{base}/camera/image",
            rr.Image(e.image, color_model="RGB").compress(jpeg_quality=JPEG_QUALITY),
        )
        self.rec.log(
            f"agents/{e.agent}/state",
            rr.TextLog(e.state, level="WARN" if e.state == "lost" else "INFO"),
        )

    def keyframe_event(self, e: KeyframeEvent) -> None:
        """The keyframe's pose and points (in its camera frame, in the agent's colour)."""
        self._time(self.frame, e.wall_time)
        path = f"world/agents/{e.agent}/keyframes/{e.kf_id}"
        self.rec.log(path, sim3_transform(e.T_WC))
        self.rec.log(f"{path}/points", rr.Points3D(e.points, colors=agent_color(e.agent)))
        if len(e.points):
            self.depth[e.agent] = float(np.median(e.points[:, 2])) * float(e.T_WC[7])

    def map_event(self, e: MapEvent) -> None:
        """The merged map, the edges, and every keyframe moved to its new pose."""
        self._time(self.frame, e.wall_time)
        self.rec.log(
            "world/map/points", rr.Points3D(e.points, colors=PALETTE[e.point_agents % len(PALETTE)])
        )
        centres = {(int(a), int(k)): T[:3] for (a, k), T in zip(e.keyframes, e.T_WC)}
        for kind, color in EDGE_COLORS.items():
            segments = [
                np.stack([centres[(int(ai), int(ki))], centres[(int(aj), int(kj))]])
                for (ai, ki, aj, kj), k in zip(e.edges, e.edge_kinds)
                if k == kind and (int(ai), int(ki)) in centres and (int(aj), int(kj)) in centres
            ]
            self.rec.log(f"world/map/edges/{kind}", rr.LineStrips3D(segments, colors=color))
        for (agent, kf_id), T_WC in zip(e.keyframes, e.T_WC):
            self.rec.log(f"world/agents/{agent}/keyframes/{kf_id}", sim3_transform(T_WC))
        components = " ".join("{" + ", ".join(map(str, c)) + "}" for c in e.components)
        self.rec.log(
            "coordinator/events",
            rr.TextLog(
                f"{e.reason}: {len(e.keyframes)} keyframes, {len(e.edges)} edges, "
                f"{len(e.points)} map points; gauge components {components}"
            ),
        )

    def trajectory_event(self, e: TrajectoryEvent) -> None:
        """The agent's final trajectory replaces the one drawn as it was tracked."""
        self._time(self.frame, e.wall_time)
        self.rec.log(
            f"world/agents/{e.agent}/trajectory",
            rr.LineStrips3D([e.T_WC[:, :3]], colors=agent_color(e.agent)),
        )

    def close(self) -> None:
        """Flush what was logged and close the sink: the saved file is complete, the spawned
        viewer keeps what it received, a server stops. A viewer that went away is a warning:
        the run's outputs do not depend on it."""
        try:
            self.rec.flush()
        except RuntimeError as exc:  # rerun's "unable to connect" (a closed spawned viewer)
            logger.warning("viewer: not everything reached the viewer (%s)", exc)
        self.rec.disconnect()
