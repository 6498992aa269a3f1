"""An agent's side of a run over any transport (C-Sec. B.1, A.8).

:class:`AgentWorker` opens the agent's input, builds its own prior from the task's
:class:`~como3r.runtime.pipeline.PriorSpec` fields, runs the agent's frame loop
(:class:`~como3r.runtime.agent_loop.AgentLoop`, the single-process runtime's too) over its
frames, sends every new keyframe as it appears and applies the pose updates it receives
between frames. It talks to the coordinator through an
:class:`~como3r.transport.links.AgentLink` only, so the same loop runs in a process
started by ``como3r run`` (pipes, :func:`agent_process_main`) and in ``como3r agent`` on
another machine (Zenoh, :mod:`como3r.runtime.network`).
"""

from __future__ import annotations

import atexit
import contextlib
import dataclasses
import gc
import logging
import os
import time
import traceback
from collections.abc import Iterator
from dataclasses import replace
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import torch

from como3r.config import Config, config_from_dict
from como3r.data.agent import open_agent, quiet_reading
from como3r.data.preprocess import upsampling
from como3r.errors import Como3rError, MessageError
from como3r.frontend.agent import AgentFrontend
from como3r.frontend.packets import KeyframePacket
from como3r.runtime.agent_loop import AgentLoop
from como3r.runtime.pipeline import PriorSpec, build_prior, load_frame, run_frames
from como3r.runtime.prefetch import PreparedFrame, prepared_frames
from como3r.transport import codec
from como3r.transport.codec import record_parts
from como3r.transport.keyframe_bytes import PartCounter
from como3r.transport.links import AgentLink
from como3r.transport.messages import (
    TO_AGENT,
    AgentFailed,
    AgentStarted,
    AgentTask,
    FrameDone,
    KeyframeMessage,
    PoseUpdateMessage,
    Shutdown,
    Step,
)
from como3r.transport.pipes import Channel
from como3r.transport.verification_messages import VerificationDone, VerificationRequest

logger = logging.getLogger(__name__)

#: lockstep ``Step`` frame indices that are no frame: the coordinator took the keyframe
#: just sent, with its pose updates sent before (the agent goes on with its frame); the
#: agent's stream ends now (after its last frame)
TAKEN, END = -2, -1


class _Stopped(Exception):
    """A Shutdown came while a lockstep agent waited for its keyframe to be taken."""


def agent_process_main(agent: int, inbox: Connection, outbox: Connection) -> None:
    """Entry point of an agent process started by :class:`~como3r.transport.pipes.PipeHub`: its task
    is the first message on its pipe; it sends in the lossy wire codings, as across
    machines, so the coordinator only decodes (:mod:`como3r.runtime.ingest`)."""
    atexit.register(gc.freeze)  # a quick exit, as the command line's (como3r.cli.main)
    channel = Channel(inbox, outbox, codec.DEFAULT_MAX_BYTES, TO_AGENT, coded=True)
    try:
        task = channel.receive()
        if not isinstance(task, AgentTask) or task.agent != agent:
            raise MessageError(f"agent {agent}: the first message must be its AgentTask")
    except (EOFError, KeyboardInterrupt):
        channel.close()
        return  # the coordinator is gone or the user interrupted: nothing to report to
    except Exception as exc:
        _report_failure(channel, agent, exc, -1)
        channel.close()
        return
    channel.max_bytes = task.max_message_bytes
    logging.basicConfig(
        level=task.log_level, format=f"[agent {agent}] %(levelname)s %(name)s: %(message)s"
    )
    run_agent(task, channel, input_checked=True)


def run_agent(task: AgentTask, link: AgentLink, input_checked: bool = False) -> bool:
    """Run one agent's task over ``link``, report a failure to the coordinator, and close
    the link (which waits until the coordinator holds every message).

    Args:
        input_checked: the run's main process opened the same input and said its readers'
            warnings (a local agent process): they are not said again here.

    Returns:
        Whether the agent ran to the end of its stream without an error.
    """
    worker: AgentWorker | None = None
    ok = False
    try:
        worker = AgentWorker(task, link, input_checked)
        ok = worker.run()
    except (EOFError, KeyboardInterrupt):
        pass  # the coordinator is gone or the user interrupted: nothing to report to
    except Exception as exc:
        _report_failure(link, task.agent, exc, worker.current_frame if worker is not None else -1)
    finally:
        link.close()
    return ok


def _report_failure(link: AgentLink, agent: int, exc: Exception, frame: int) -> None:
    details = "" if isinstance(exc, Como3rError) else traceback.format_exc()
    logger.error("agent %d failed: %s: %s", agent, type(exc).__name__, exc)
    link.send(
        AgentFailed(
            agent=agent, error=f"{type(exc).__name__}: {exc}", details=details, frame_index=frame
        )
    )


class AgentWorker:
    """One agent's loop: frames in, keyframes and progress out, pose updates applied."""

    def __init__(self, task: AgentTask, channel: AgentLink, input_checked: bool = False) -> None:
        torch.set_num_threads(max(1, task.torch_threads))
        self.task = task
        self.channel = channel
        self.config = config_from_dict(Config, task.config)
        spec = prior_spec(task.prior)
        with quiet_reading() if input_checked else contextlib.nullcontext():
            self.input = open_agent(
                task.input_path,
                fps=self.config.input.frame_rate_hz,
                format=self.config.input.format,
                topic=self.config.input.topic,
            )
        self.prior, codebook = build_prior(
            spec, self.config, {task.agent: self.input}, quiet=True
        )  # the coordinator says it once
        self.frontend = AgentFrontend(
            self.prior,
            self.config,
            task.agent,
            codebook,
            upsampling(self.input.image_size, self.config.input.long_side),
        )
        self.loop = AgentLoop(
            self.frontend, self._send_keyframe, self.channel.send if task.live else None
        )
        self.frames = [
            int(i)
            for i in run_frames(
                self.input, self.config.input.subsample, spec.name, start=task.resume_after + 1
            )
        ]
        self.applied_seq = 0
        self.current_frame = -1
        self.stream_ended = False  # every frame processed
        self.parts = PartCounter()  # bytes per part of the keyframe messages sent

    def run(self) -> bool:
        """Process every frame and send the final report; False when stopped early (a
        :class:`Shutdown`)."""
        self.channel.send(
            AgentStarted(agent=self.task.agent, pid=os.getpid(), frames=len(self.frames))
        )
        agent, long_side = self.task.agent, self.config.input.long_side
        frames = prepared_frames(
            ((agent, index) for index in self.frames),
            lambda a, i: load_frame(self.input, a, i, long_side, self.config.calibrated),
            self.prior,
            self.config.input.prefetch_frames,
        )
        try:
            with contextlib.closing(frames):
                for index in self.frames:
                    ready = self._await_step(index) if self.task.lockstep else self._drain_inbox()
                    if not ready:
                        return False
                    self._process(index, frames)
            self.current_frame = -1
            self.stream_ended = True
            # lockstep: the stream ends on the coordinator's turn too, with every pose update
            # made until then applied, as in one process
            if not (self._await_step(END) if self.task.lockstep else self._drain_inbox()):
                return False
            self.loop.end()
        except _Stopped:
            return False
        report = self.loop.report(self.applied_seq)
        self.channel.send(
            replace(
                report,
                keyframe_bytes_by_part=dict(self.parts.bytes),
                keyframes_measured=self.parts.keyframes,
            )
        )
        if self.task.verify:
            self._serve_until_released()
        return True

    def _serve_until_released(self) -> None:
        """After the stream: serve the coordinator's verification requests until it says
        no more come (or stop: :mod:`.remote_verification`); pose updates no longer matter
        here."""
        while True:
            message = self.channel.receive()
            if isinstance(message, (VerificationDone, Shutdown)):
                return
            if isinstance(message, VerificationRequest):
                self._serve(message)

    def _process(self, index: int, frames: Iterator[PreparedFrame]) -> None:
        """Frame ``index``: its live event and keyframes leave as the loop hands them out,
        then its ``FrameDone``, the agent's clock, by which the coordinator orders the
        keyframes (so it follows them)."""
        self.current_frame = index
        start = time.perf_counter()
        step = self.loop.step(next(frames), start)
        self.channel.send(
            FrameDone(
                agent=self.task.agent,
                frame_index=step.index,
                timestamp=step.timestamp,
                outcome=step.outcome,
                seconds=step.seconds,
                keyframes_waiting=len(self.frontend.new_keyframes),
            )
        )

    def _send_keyframe(self, packet: KeyframePacket) -> None:
        """Send a keyframe with the pose its predecessor had here: the coordinator
        re-anchors one exported before an update reached this agent on it (C-Sec. A.8); without
        its encoding when the task says the coordinator makes it again, else with what
        travels in its place (:meth:`~como3r.prior.base.Encoding.portable`)."""
        previous = (
            self.frontend.keyframes[packet.kf_id - 1].T_WC.clone() if packet.kf_id > 0 else None
        )
        if not self.task.send_encoding:  # the coordinator encodes the colours again
            packet = dataclasses.replace(packet, encoding=None)
        elif packet.encoding is not None:  # or from them and what else it needs
            packet = dataclasses.replace(packet, encoding=packet.encoding.portable())
        message = KeyframeMessage(
            packet=packet, applied_seq=self.applied_seq, T_WC_previous=previous
        )
        record_parts(message, self.parts.add_fields)  # sizes from the encoding that is sent
        self.channel.send(message)
        # lockstep: as in one process, the next keyframe leaves with the updates this one
        # caused applied (a merge's gauge and focal length are in it)
        if self.task.lockstep and not self._await_step(TAKEN):
            raise _Stopped

    def _handle(self, message: Any) -> bool:
        """Apply one coordinator message; False on Shutdown."""
        if isinstance(message, Shutdown):
            logger.info("shutdown requested: %s", message.reason)
            return False
        if isinstance(message, VerificationDone):
            return True  # for an agent whose stream has ended: this one's goes on
        if isinstance(message, VerificationRequest) and self.task.verify:
            self._serve(message)
            return True
        if isinstance(message, PoseUpdateMessage):
            if message.seq <= self.applied_seq and message.update.agent == self.task.agent:
                return True  # sent again after a reconnect: applied already
            if message.seq != self.applied_seq + 1 or message.update.agent != self.task.agent:
                raise MessageError(
                    f"pose update {message.seq} for agent {message.update.agent} out of sequence"
                )
            self.frontend.apply_pose_update(message.update)
            self.applied_seq = message.seq
            return True
        raise MessageError(f"unexpected {type(message).__name__} from the coordinator")

    def _serve(self, request: VerificationRequest) -> None:
        """Verify the coordinator's request and send the reply (``verification.on_agents``)."""
        # imported on the first request: an agent that verifies nothing imports no part of
        # the coordinator (tests/runtime/test_agent_worker.py)
        from como3r.runtime.verification_service import serve

        reply = serve(self.task.agent, self.prior, self.config, request, self.stream_ended)
        self.channel.send(reply)

    def _drain_inbox(self) -> bool:
        """Apply every waiting message without blocking; False on Shutdown."""
        while self.channel.poll(0.0):
            if not self._handle(self.channel.receive()):
                return False
        return True

    def _await_step(self, index: int) -> bool:
        """Lockstep: apply messages until the Step for frame ``index``; False on Shutdown."""
        while True:
            message = self.channel.receive()
            if isinstance(message, Step):
                if message.frame_index != index:
                    raise MessageError(
                        f"step for frame {message.frame_index}, expected frame {index}"
                    )
                return True
            if not self._handle(message):
                return False


PATH_FIELDS = ("weights", "retrieval_weights", "codebook")


def prior_fields(spec: PriorSpec) -> dict[str, Any]:
    """``AgentTask.prior`` of a prior specification (paths as strings)."""
    return {
        "name": spec.name,
        "device": spec.device,
        "precision": spec.precision,
        **{k: (None if getattr(spec, k) is None else str(getattr(spec, k))) for k in PATH_FIELDS},
    }


def prior_spec(fields: dict[str, Any]) -> PriorSpec:
    """The prior specification of ``AgentTask.prior`` (the inverse of :func:`prior_fields`;
    a task without ``precision`` gets the default)."""
    return PriorSpec(
        **{k: (Path(v) if k in PATH_FIELDS and v is not None else v) for k, v in fields.items()}
    )
