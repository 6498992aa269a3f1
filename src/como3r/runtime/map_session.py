"""A finished run's map as the start of a new run (issue 14: ``como3r run --map OLD``).

A centralized run leaves its whole map in ``OLD/session.db`` (:mod:`como3r.store.writer`): every
keyframe with its encoding, pointmaps, pose and retrieval features, the links with their
matches, the gauge components, and each agent process's final report (its trajectory
relative to its keyframes). :func:`open_map` reads it; :func:`seed_map` makes it the start
of a new run's coordinator: the saved agents keep their ids ``0 .. M-1`` and the new agents
are ``M, M+1, ...``, each in a gauge component of its own. From there nothing is special:
the new agents' keyframes query the retrieval database, which holds the saved keyframes,
candidates are verified densely, and the first verified edges (``gauge.min_consistent_edges``
that agree) move a new agent into the saved map's frame (the component with the lower root,
the saved one, keeps its gauge); global BA then refines both. With ``--freeze-map``
(:attr:`SavedMap.freeze`) the saved keyframes are held fixed by every solve, pose and depth,
and their focal length is not re-fitted: the new agents are fitted to the saved map.

The terminal refinement leaves a saved component that no new agent joined as it was (it was
refined when it was made). The new run's output holds the saved agents too
(:func:`map_results`): their keyframes and every tracked frame, composed from their reports
on their keyframes' current poses, in the one frame.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from como3r.backend.global_graph import GlobalGraph
from como3r.config import Config, differing_key
from como3r.coordination.coordinator import Coordinator, CoordinatorStats
from como3r.errors import InputError
from como3r.frontend.agent import FrontendStats
from como3r.runtime.results import AgentResult, EdgeView, MatchFraction, stored_views
from como3r.store.reader import Session, read_session
from como3r.store.resume import load_state
from como3r.store.schema import STORE_NAME

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class SavedMap:
    """A finished run's session, to start a new run on.

    Attributes:
        session: its session store's contents.
        freeze: hold its keyframes fixed (``--freeze-map``).
    """

    session: Session
    freeze: bool = False

    @property
    def agents(self) -> int:
        """How many agents (coordinator agents: map segments) it holds: the new run's
        agents are numbered after them."""
        return len(self.session.agents)


def open_map(
    folder: Path, config: Config | None, freeze: bool = False, option: str = "--map"
) -> SavedMap:
    """The map of the finished run in ``folder``, made with ``config`` (None: any).

    Raises:
        InputError: no session store in ``folder``, a run that did not finish, or one made
            with another configuration (naming the first differing key).
        StoreError: a store that cannot be read (corrupted, another format version).
    """
    if not (folder / STORE_NAME).is_file():
        raise InputError(
            f"{option} {folder}: no {STORE_NAME} there (the output folder of a "
            f"finished --mode centralized run holds one)"
        )
    session = read_session(folder / STORE_NAME)
    if not session.finished:
        raise InputError(
            f"{option} {folder}: that run did not finish (continue it with --resume first)"
        )
    difference = None if config is None else differing_key(session.config, config)
    if difference is not None:
        raise InputError(
            f"{option} {folder}: made with another configuration "
            f"({difference}); give the options of the run that made it"
        )
    return SavedMap(session, freeze)


def seed_map(coordinator: Coordinator, saved: SavedMap) -> None:
    """Make a new coordinator (with room for the saved agents and the new ones) start from
    the saved map: its keyframes, links, gauge components, candidates and retrieval
    database; then :func:`hold_map`."""
    session = saved.session
    indexed = sorted(session.retrieval, key=lambda e: (e.position is None, e.position or 0))
    load_state(
        session, coordinator, CoordinatorStats(keyframes=len(session.graph)), (0, []), indexed
    )
    hold_map(coordinator, saved)
    logger.info(
        "started from a saved map: %d keyframes of %d agents%s",
        len(session.graph),
        saved.agents,
        ", held fixed" if saved.freeze else "",
    )


def hold_map(coordinator: Coordinator, saved: SavedMap) -> None:
    """Mark the saved map in a coordinator that holds it (seeded, or resumed from a store
    that was): its components count as refined, and under ``freeze`` its keyframes (the
    first ones) are held fixed."""
    coordinator.refined = [
        set(members) for members in saved.session.gauges.components() if max(members) < saved.agents
    ]
    if saved.freeze:
        coordinator.graph.fixed = set(range(len(saved.session.graph)))


def map_results(
    saved: SavedMap, offset: int = 0, graph: GlobalGraph | None = None
) -> list[AgentResult]:
    """The saved agents' results as the outputs read them (keyframes from the map, their
    trajectories and statistics from their reports), by agent id, the ids moved by
    ``offset``; their keyframes' arrays are read from ``graph`` (the coordinator's, under
    the moved ids) where given, else from the saved map's."""
    results = []
    for agent in range(saved.agents):
        report = saved.session.reports.get(agent)
        views = stored_views(
            saved.session.graph, agent, graph, None if graph is None else offset + agent
        )
        result = AgentResult(offset + agent, views, finished=report)
        if report is not None:
            if len(report.keyframe_T_WC) != len(result.keyframes):
                result.finished = None  # a failed agent's: its keyframes only
            result.stats = report.stats
            result.edges = [
                EdgeView(e.i, e.j, e.kind, MatchFraction(e.match_fraction)) for e in report.edges
            ]
        else:
            result.stats = FrontendStats(keyframes=len(result.keyframes))
        results.append(result)
    return results
