"""The coordinator's input as it arrives across machines, in every runtime (issue 39, item 4).

Agents on other machines send their keyframes and pointmap refreshes in the lossy wire
coding (:func:`como3r.transport.codec.encode` with ``lossy``: pointmaps as log-range and ray
direction, confidences in log steps, retrieval descriptors in 8 bits, ...). Every runtime
(the single-process pipeline, the agent processes on pipes, the network) hands the
coordinator each keyframe and refresh through that coding first (:func:`received`), so the
coordinator computes on the same arrays whichever way they came, and the session store can
keep them in that coding: the codings give back their own output unchanged
(:mod:`como3r.store.coded`), so a resume reads back exactly what the coordinator held.

Cost: one lossy encode and decode per keyframe (``stage_seconds.ingest`` in
``metrics.json``; ``benchmarks/store_speed.py`` times it). On the demo scene (2 agents x 30
frames at 512x384, simulated prior, ``--single-process``) the merged ATE was 7.814 mm with
it against 7.879 mm without.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from typing import TypeVar

from como3r.coordination.coordinator import Coordinator
from como3r.frontend.agent import AgentFrontend
from como3r.frontend.paging import read_fields
from como3r.transport import codec

T = TypeVar("T")

#: ``stage_seconds`` key of the time spent here
STAGE = "ingest"


def received(message: T, coordinator: Coordinator | None = None) -> T:
    """``message`` (a :class:`~como3r.frontend.packets.KeyframePacket` or
    :class:`~como3r.frontend.packets.PointmapRefresh`) as a coordinator across machines
    receives it: lossy-encoded and decoded; the seconds it took are charged to
    ``coordinator``'s ``stage_seconds["ingest"]`` when given."""
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
