"""Helpers shared by the front-end tests."""

from __future__ import annotations

from collections.abc import Callable, Iterable

import pytest

from como3r.data.agent_input import AgentInput
from como3r.data.preprocess import make_view
from como3r.frontend.agent import AgentFrontend
from como3r.runtime.pipeline import _colors


def _process_frames(
    frontend: AgentFrontend, agent: AgentInput, long_side: int, indices: Iterable[int]
) -> list[str]:
    """Feed the agent's frames ``indices`` to ``frontend``; their outcomes in order."""
    outcomes = []
    for index in indices:
        frame = agent.load_frame(index)
        view = make_view(
            frame, frontend.agent, long_side, agent.calib if frontend.config.calibrated else None
        )
        outcomes.append(frontend.process(view, frame.timestamp, _colors(view)))
    return outcomes


@pytest.fixture(scope="session")
def process_frames() -> Callable[[AgentFrontend, AgentInput, int, Iterable[int]], list[str]]:
    """:func:`_process_frames`, for tests and module-scoped fixtures."""
    return _process_frames
