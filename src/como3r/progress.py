"""Progress events of a run: what the command line (or any other sink) shows while it runs.

A run reports two kinds of event through one optional callback (no globals):

* :class:`AgentProgress` -- after every frame of an agent (and when an agent fails): its
  frames done of its total, keyframes, lost and relocalized frames and tracking state;
* :class:`PhaseEvent` -- when the coordinator's terminal work starts a step: focal
  refinement, the global BA cleanup passes, the rounds of the pose-depth alternation
  (C-Sec. A.7), writing the outputs, evaluation, the report.

Both are small frozen dataclasses built from plain values, so the multi-process runtime
emits them in the coordinator's process from the agents' typed messages
(:class:`~como3r.transport.messages.FrameDone`), exactly as the single-process runner does
from its front-ends. This module imports nothing of como3r: every layer may emit events.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

__all__ = [
    "AgentProgress",
    "PhaseEvent",
    "ProgressEvent",
    "ProgressCallback",
    "PhaseCallback",
    "report_phase",
    "tracking_state",
]

#: tracking states of :attr:`AgentProgress.state`
STATES = ("tracking", "lost", "relocalized", "away", "failed")


def tracking_state(outcome: str) -> str:
    """The tracking state after a frame with front-end ``outcome`` (``"keyframe"``,
    ``"tracked"``, ``"relocalized"`` or ``"lost"``)."""
    return outcome if outcome in ("lost", "relocalized") else "tracking"


@dataclass(frozen=True)
class AgentProgress:
    """One agent's state after its latest frame.

    Attributes:
        agent: agent id.
        frames_done: frames the agent has processed.
        frames_total: frames it will process (its input after ``input.subsample``); a live
            input's ``--max-frames``, or None when its stream's length is not known.
        keyframes: keyframes it has made so far.
        lost: frames it could neither track nor relocalize.
        relocalized: frames on which tracking recovered after being lost.
        state: ``"tracking"``, ``"lost"``, ``"relocalized"`` (the last frame's outcome),
            ``"away"`` (a networked agent's link is lost; it may come back) or ``"failed"``
            (the agent stopped on an error; no more events follow).
    """

    agent: int
    frames_done: int
    frames_total: int | None
    keyframes: int
    lost: int
    relocalized: int
    state: str = "tracking"


@dataclass(frozen=True)
class PhaseEvent:
    """The coordinator starts step ``done + 1`` of phase ``name``.

    Attributes:
        name: the phase: ``"backlog"`` (while agents stream, multi-process
            runs: keyframes waiting and seconds of input behind in ``detail``, keyframes
            handled of those received in ``done`` and ``total``), ``"queued keyframes"``,
            ``"focal refinement"``, ``"cleanup pass"``,
            ``"alternation round"``, ``"outputs"``, ``"evaluation"``, ``"report"``; in the
            decentralized mode also ``"formulation table"``.
        detail: what the step works on, one short line (agents, last step's change, files).
        done: steps of this phase finished before this one.
        total: steps planned; for passes and rounds the most there can be (the loop stops
            early once converged); None for a single step.
    """

    name: str
    detail: str = ""
    done: int = 0
    total: int | None = None


ProgressEvent = AgentProgress | PhaseEvent

ProgressCallback = Callable[[ProgressEvent], None]
"""What a run calls with every progress event."""

PhaseCallback = Callable[[PhaseEvent], None]
"""What the coordinator's terminal stages call with their phase events."""


def report_phase(
    progress: PhaseCallback | None,
    name: str,
    detail: str = "",
    done: int = 0,
    total: int | None = None,
) -> None:
    """Tell ``progress`` (if any) that step ``done + 1`` of phase ``name`` starts."""
    if progress is not None:
        progress(PhaseEvent(name, detail, done, total))
