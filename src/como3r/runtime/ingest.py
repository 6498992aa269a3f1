"""The coordinator's input as it arrives across machines, in every runtime (issue 39, item 4).

Agents on other machines send their keyframes and pointmap refreshes in the lossy wire
coding (:func:`como3r.transport.codec.encode` with ``lossy``: pointmaps as log-range and ray
direction, confidences in log steps, retrieval descriptors in 8 bits, ...). Every runtime
hands the coordinator each keyframe and refresh through that coding (:func:`received`), so
the coordinator computes on the same arrays whichever way they came, and the session store
can keep them in that coding: the codings give back their own output unchanged
(:mod:`como3r.store.coded`), so a resume reads back exactly what the coordinator held.

Who codes: the agent, as across machines. Agents on the network send in the lossy coding
(:mod:`como3r.transport.zenoh_agent`), and so do agent processes on pipes (their
:class:`~como3r.transport.pipes.Channel` codes like a link across machines, each keyframe's
encoding exact): the coordinator only decodes them, as they arrive (its runtime charges
that decode to ``stage_seconds["ingest"]``), and :func:`received` takes them as they are
(issue 41: the coordinator's CPU does not grow with the team's agents). Only the
single-process runtime, whose front-ends hand over their own arrays, codes them here.

Cost in the coordinator: a decode per keyframe and refresh (``stage_seconds.ingest`` in
``metrics.json``; in one process an encode too; ``benchmarks/store_speed.py`` times
them). On the demo scene (2 agents x 30 frames at 512x384, simulated prior,
``--single-process``) the merged ATE was 7.814 mm with the coding against 7.879 mm without.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, TypeVar

from como3r.frontend.agent import AgentFrontend
from como3r.frontend.paging import read_fields
from como3r.transport import codec, codec_reuse

if TYPE_CHECKING:  # an agent's process imports this module and needs no back-end (~0.5 s CPU)
    from como3r.coordination.coordinator import Coordinator

T = TypeVar("T")

#: ``stage_seconds`` key of the time spent here
STAGE = "ingest"


def received(message: T, coordinator: Coordinator | None = None) -> T:
    """``message`` (a :class:`~como3r.frontend.packets.KeyframePacket` or
    :class:`~como3r.frontend.packets.PointmapRefresh`) as a coordinator across machines
    receives it: lossy-encoded and decoded, unless it came so (:func:`coded`: it is taken
    as it is); the seconds coding it took are charged to ``coordinator``'s
    ``stage_seconds["ingest"]`` when given."""
    if coded(message):
        return message
    start = time.perf_counter()
    # A keyframe's encoding is handed over as its agent made it: a coordinator across
    # machines makes it again bit for bit (from the colours, and the simulated prior's
    # record: coordination/encodings.py), never from float16 tokens.
    encoding = getattr(message, "encoding", None)
    if encoding is not None:
        message = dataclasses.replace(message, encoding=None)
    back = codec.decode(codec.encode(message, lossy=True), expected=type(message))
    if encoding is not None:
        back = dataclasses.replace(back, encoding=encoding)
    if coordinator is not None:
        coordinator.stats.add_time(STAGE, time.perf_counter() - start)
    return back


def coded(message: object) -> bool:
    """Whether ``message`` (a :class:`~como3r.frontend.packets.KeyframePacket` or
    :class:`~como3r.frontend.packets.PointmapRefresh`) was decoded from the lossy wire in
    this process (its sender coded it): its pointmap and confidence hold the coded maps they
    were decoded from, unchanged (:func:`~como3r.transport.codec_reuse.held`, until the
    session store takes them). Coding it again would give back the very values (the
    codings give back their own output) for the cost of an encode and a decode."""
    return codec_reuse.held("pointmap", getattr(message, "X_hat", None)) and codec_reuse.held(
        "confidence", getattr(message, "C_hat", None)
    )


def hold_the_coordinators(frontends: Sequence[AgentFrontend], coordinator: Coordinator) -> None:
    """After the terminal cleanup, the single-process runtime's front-ends' keyframes take
    the coordinator's pointmaps and confidences (what it received of them, refined), as the
    multi-process runtime's results read them from the coordinator: the outputs are the
    same whichever runtime ran. The front-ends have stopped: nothing tracks on them."""
    graph = coordinator.graph
    for frontend in frontends:
        keyframes = frontend.keyframes.keyframes
        for kf, g in zip(keyframes, graph.agent_keyframes(frontend.agent)):
            kf.X_hat, kf.C_hat = read_fields(graph.keyframes[g], "X_hat", "C_hat")
            frontend.page_out()  # one keyframe's arrays in memory at a time, as paged
