"""Bounded memory: the coordinator's large arrays paged out to its session store (issue 14).

Every keyframe the coordinator holds carries its encoding (the simulated prior's is 15.5 MB
at 512x384, MASt3R's 3 MB), its image and four pointmaps, and every sequential edge both
directions' dense matches (5 MB at 512x384): kept in memory, they grow with the sequence.
The session store holds all of them already (:mod:`.writer`), so after every message's
transaction :func:`page_out` lets go of what is outside the *working set*: the newest
``session.resident_keyframes`` keyframes of each agent, of which the coordinator keeps at
most ``session.team_resident_keyframes``, the newest by arrival (issue 41: without it the
working set grows with the team, 8 keyframes per agent):

* a keyframe outside it becomes a :class:`~como3r.frontend.paging.PagedKeyframe`: its
  light fields (pose, ids, intrinsics, retrieval features) stay, its encoding, image and
  pointmaps are read back from the store the first time something needs them (a
  verification decodes its encoding; a global BA, a gauge merge or the depth refinement
  reads its pointmap) and kept until the next page-out;
* a sequential edge between two such keyframes becomes a :class:`PagedLink`, whose matches
  are read from the store each time they are asked for (a solve builds its factors once);
* a verified candidate that was rejected or found inconsistent keeps its figures only
  (:class:`StoredVerification`): nothing reads its matches again; one refused inside a
  gauge that the coordinator tests again after its next global BA keeps them until then.

What a message needs is read while it is handled, so the results do not depend on the
working set; only memory and time do. Inter-agent edges and admitted or pending candidates
stay in memory: they grow with the places agents share, not with the sequence. The agents'
front-ends page their own keyframes to spill folders of their own
(:mod:`como3r.frontend.paging`); this pages the coordinator.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from typing import Protocol

import torch

from como3r.coordination.association import Verification
from como3r.coordination.coordinator import Coordinator
from como3r.errors import StoreError
from como3r.frontend.paging import KeyframePages, PagedKeyframe
from como3r.frontend.pairs import DirectedMatches, PairLink
from como3r.heap import give_back_freed_memory

logger = logging.getLogger(__name__)


class Pages(KeyframePages, Protocol):
    """Where paged-out arrays are read back from (the session store)."""

    def load_matches(self, n: int) -> tuple[DirectedMatches, DirectedMatches]:
        """Both directions' matches of edge ``n``."""


class PagedLink(PairLink):
    """A link whose matches are read from the session store whenever they are asked for
    (their match fractions are kept)."""

    _pages: Pages | None
    _n: int

    def __init__(
        self, pages: Pages | None, n: int, covisible_ij: float | None, covisible_ji: float | None
    ) -> None:
        for name, value in (
            ("_pages", pages),
            ("_n", n),
            ("covisible_ij", covisible_ij),
            ("covisible_ji", covisible_ji),
        ):
            object.__setattr__(self, name, value)

    def serve(self, pages: Pages) -> None:
        """Read from ``pages`` from now on (a store read back)."""
        object.__setattr__(self, "_pages", pages)

    @property
    def ij(self) -> DirectedMatches:
        return self._matches()[0]

    @property
    def ji(self) -> DirectedMatches:
        return self._matches()[1]

    def _matches(self) -> tuple[DirectedMatches, DirectedMatches]:
        if self._pages is None:
            raise StoreError(f"the matches of edge {self._n} were asked for before its store")
        return self._pages.load_matches(self._n)


@dataclass(frozen=True)
class StoredVerification(Verification):
    """A verification whose matches were let go (a rejected or inconsistent candidate, or
    one read back from a store): its figures only.

    Attributes:
        figures: ``(nu_i, nu_j, covisible_ratio)``.
    """

    figures: tuple[float | None, float, float | None] = (None, 0.0, None)

    @property
    def nu_i(self) -> float | None:
        return self.figures[0]

    @property
    def nu_j(self) -> float:
        return self.figures[1]

    @property
    def covisible_ratio(self) -> float | None:
        return self.figures[2]


#: the matches of a verification that keeps its figures only
NO_MATCHES = DirectedMatches(
    torch.zeros(0, dtype=torch.int64), torch.zeros(0, dtype=torch.bool), torch.zeros(0)
)


def figures_only(v: Verification) -> StoredVerification:
    """``v`` without its matches."""
    return StoredVerification(
        v.candidate,
        v.query,
        v.similarity,
        NO_MATCHES,
        None,
        None,
        None,
        v.accepted,
        figures=(v.nu_i, v.nu_j, v.covisible_ratio),
    )


def working_set(coordinator: Coordinator) -> set[int]:
    """Global indices of the keyframes the coordinator keeps whole: each agent's newest
    ``session.resident_keyframes``, and of those the newest
    ``session.team_resident_keyframes`` by arrival (0: all of them).

    A keyframe's global index is its arrival order (:meth:`GlobalGraph.append
    <como3r.backend.global_graph.GlobalGraph.append>` gives it the graph's length, and a
    session read back from its store appends them in that order), so the team-wide bound
    keeps the largest indices.
    """
    session = coordinator.config.session
    keep, team = session.resident_keyframes, session.team_resident_keyframes
    graph = coordinator.graph
    # max(0, ...): an agent with fewer keyframes keeps all of them (a negative start would
    # count from the end and keep only its last keep - len(own))
    own_newest = sorted(
        g
        for own in graph.local_to_global.values()
        for g in own[max(0, len(own) - keep) :]
        if keep > 0
    )
    return set(own_newest[-team:] if team > 0 else own_newest)


def page_out(coordinator: Coordinator, pages: Pages) -> None:
    """Let go of what is outside the working set (the module docstring); every keyframe
    and link must be in the store already. Only where something was let go of is the
    heap's free memory given back (:mod:`.heap`): a ``malloc_trim`` took 10-17 ms of the
    coordinator's thread after every message, where the defaults page nothing out.

    Args:
        coordinator: the coordinator whose graph and candidates are paged.
        pages: where they are read back from.
    """
    graph, kept = coordinator.graph, working_set(coordinator)
    freed = False
    for g, kf in enumerate(graph.keyframes):
        if g in kept or (isinstance(kf, PagedKeyframe) and not kf._resident):
            continue
        if not isinstance(kf, PagedKeyframe):
            kf = graph.keyframes[g] = PagedKeyframe.of(kf)
        kf.evict(pages, g)
        freed = True
    for n, link in enumerate(graph.links):
        if (
            link.kind == "sequential"
            and not isinstance(link.link, PagedLink)
            and link.i not in kept
            and link.j not in kept
        ):
            graph.links[n] = replace(
                link, link=PagedLink(pages, n, link.link.covisible_ij, link.link.covisible_ji)
            )
            freed = True
    # a refused edge the coordinator tests again after its next global BA keeps its matches
    for candidate in coordinator.candidates:
        if (
            candidate.status in ("rejected", "inconsistent")
            and not isinstance(candidate.verification, StoredVerification)
            and not coordinator.awaiting_recheck(candidate)
        ):
            candidate.verification = figures_only(candidate.verification)
            freed = True
    if freed:
        give_back_freed_memory()  # what was let go of leaves the process's RSS too (.heap)
