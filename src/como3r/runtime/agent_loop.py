"""One agent's frame loop, the same in every runtime (C-Sec. 3.1, A.8).

:class:`AgentLoop` runs an agent's front-end on its prepared frames (:mod:`.prefetch`) and
hands out what each frame produced: the live frame event (when a viewer asked for it), then
the packets of the keyframes ready to leave. The single-process runtime
(:func:`.pipeline.run`) keeps one loop per agent and gives the packets to its coordinator;
an agent process (:class:`.agent_worker.AgentWorker`) keeps one and sends them as messages.
What the loop does per frame, and in which order, is therefore the runtimes' common part;
only where its outputs go differs.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

from como3r.frontend.agent import AgentFrontend
from como3r.frontend.packets import KeyframePacket
from como3r.heap import give_back_freed_memory
from como3r.live import FrameEvent
from como3r.runtime.live import frame_event
from como3r.runtime.prefetch import PreparedFrame
from como3r.runtime.results import final_report
from como3r.transport.messages import AgentFinished

#: takes one keyframe packet as it leaves the agent
KeyframeSink = Callable[[KeyframePacket], None]

#: takes the live event of a frame just processed
FrameEventSink = Callable[[FrameEvent], None]


@dataclass(frozen=True)
class FrameStep:
    """What one frame of an agent did.

    Attributes:
        index: the frame's index in the agent's stream.
        timestamp: its timestamp [s].
        outcome: what :meth:`~como3r.frontend.agent.AgentFrontend.process` returned
            (``"keyframe"``, ``"tracked"``, ``"relocalized"`` or ``"lost"``).
        seconds: the frame's wall time, waiting for its input and encoding included.
    """

    index: int
    timestamp: float
    outcome: str
    seconds: float


class AgentLoop:
    """Frames in, keyframe packets and live events out, for one agent's front-end.

    Args:
        frontend: the agent's front-end; pose updates reach it directly
            (:meth:`~como3r.frontend.agent.AgentFrontend.apply_pose_update`), from the
            caller, between frames or from inside ``keyframe``.
        keyframe: takes each keyframe packet. Packets are made one at a time as they are
            taken (:meth:`~como3r.frontend.agent.AgentFrontend.drain_new_keyframes`), so
            the updates ``keyframe`` applies to this front-end are in the next one.
        live: takes each frame's live event (None: no event is built).
    """

    def __init__(
        self, frontend: AgentFrontend, keyframe: KeyframeSink, live: FrameEventSink | None = None
    ) -> None:
        self.frontend = frontend
        self.keyframe = keyframe
        self.live = live
        #: the agent's wall time over its frames so far [s]
        self.seconds = 0.0

    def step(self, frame: PreparedFrame, started: float) -> FrameStep:
        """Process the agent's next frame, then hand out its live event and the keyframes
        ready to leave.

        Args:
            frame: the agent's next frame.
            started: ``time.perf_counter()`` when the caller began waiting for ``frame``.
        """
        # the agent's wall time includes waiting for its input and encoding
        self.frontend.timer.charge("prior_encode", time.perf_counter() - started)
        outcome = self.frontend.process(frame.view, frame.timestamp, frame.colors, frame.encoding)
        seconds = time.perf_counter() - started
        self.seconds += seconds
        # the event shows the frame as tracked: in one process, the keyframes' hand-out
        # applies the coordinator's pose updates at once
        if self.live is not None:
            self.live(
                frame_event(self.frontend, frame.index, frame.timestamp, outcome, frame.colors)
            )
        self._hand_out()
        # the front-end pages its old keyframes out (frontend/paging.py), but every local
        # solve reads their pointmaps and matches back and lets go of them, and glibc keeps
        # such freed small blocks in the heap. One agent at 64x48 over 125 processed frames
        # (95 keyframes) stayed at 433-438 MB with the trim and rose from 439 MB to 513-590
        # MB without
        give_back_freed_memory()
        return FrameStep(frame.index, frame.timestamp, outcome, seconds)

    def end(self) -> None:
        """End the agent's stream: a short stream's camera settles on the keyframes it has,
        and the keyframes that waited for it are handed out."""
        self.frontend.settle_camera()
        self._hand_out()

    def report(self, applied_seq: int) -> AgentFinished:
        """The agent's final report (:func:`~.results.final_report`) after ``applied_seq``
        pose updates."""
        return final_report(self.frontend, self.seconds, applied_seq)

    def _hand_out(self) -> None:
        for packet in self.frontend.drain_new_keyframes():
            self.keyframe(packet)
