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
* an edge between two such keyframes (sequential, loop or inter-agent) becomes a
  :class:`PagedLink`, whose matches are read from the store each time they are asked for
  (a solve builds its factors once), and an admitted candidate holding that edge's matches
  holds the paged link in their place (:class:`PagedVerification`). Issue 41: inter-agent
  and loop edges kept in memory grew with the map (16 agents, 190 keyframes at 512x384:
  171 inter-agent and 80 loop edges, 5.1 MB each);
* a verified candidate that was rejected or found inconsistent keeps its figures only
  (:class:`StoredVerification`): nothing reads its matches again; one refused inside a
  gauge that the coordinator tests again after its next global BA keeps them until then.

What a message needs is read while it is handled, so the results do not depend on the
working set; only memory and time do. Pending candidates stay in memory (few: the edges
between two gauge components waiting for agreeing ones). The agents'
front-ends page their own keyframes to spill folders of their own
(:mod:`como3r.frontend.paging`); this pages the coordinator.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from typing import Protocol

import torch
from torch import Tensor

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
    (their co-visible shares are kept, and their match fractions where known).

    Each of :attr:`ij` and :attr:`ji` is a :class:`PagedDirection`, which reads when its
    arrays are used and keeps nothing: a solve that lists every edge of the map holds the
    matches of none of those paged (the dense factors it builds are another matter).
    """

    _pages: Pages | None
    _n: int
    _fractions: tuple[float, float] | None

    def __init__(
        self,
        pages: Pages | None,
        n: int,
        covisible_ij: float | None,
        covisible_ji: float | None,
        fractions: tuple[float, float] | None = None,
    ) -> None:
        for name, value in (
            ("_pages", pages),
            ("_n", n),
            ("covisible_ij", covisible_ij),
            ("covisible_ji", covisible_ji),
            ("_fractions", fractions),
        ):
            object.__setattr__(self, name, value)

    @classmethod
    def of(cls, pages: Pages, n: int, link: PairLink) -> PagedLink:
        """Edge ``n``'s ``link`` (in memory, stored) paged: its figures kept."""
        fractions = (link.ij.match_fraction, link.ji.match_fraction)
        return cls(pages, n, link.covisible_ij, link.covisible_ji, fractions)

    def serve(self, pages: Pages) -> None:
        """Read from ``pages`` from now on (a store read back)."""
        object.__setattr__(self, "_pages", pages)

    @property
    def ij(self) -> DirectedMatches:
        return PagedDirection(self, 0)

    @property
    def ji(self) -> DirectedMatches:
        return PagedDirection(self, 1)

    def fraction(self, direction: int) -> float | None:
        """The match fraction of ``direction`` (0: ij, 1: ji) where kept, else None."""
        return None if self._fractions is None else self._fractions[direction]

    def load(self) -> tuple[DirectedMatches, DirectedMatches]:
        """Both directions' matches, read from the store."""
        if self._pages is None:
            raise StoreError(f"the matches of edge {self._n} were asked for before its store")
        return self._pages.load_matches(self._n)


class PagedDirection(DirectedMatches):
    """One direction of a :class:`PagedLink`, its arrays read from the store at each use
    (the store keeps the last few edges read: :meth:`~.writer.SessionStore.load_matches`),
    so a solve's list of every edge holds no matches; its match fraction known without a
    read where the link kept it."""

    _link: PagedLink
    _direction: int

    def __init__(self, link: PagedLink, direction: int) -> None:
        object.__setattr__(self, "_link", link)
        object.__setattr__(self, "_direction", direction)

    def _matches(self) -> DirectedMatches:
        return self._link.load()[self._direction]

    @property
    def idx(self) -> Tensor:
        return self._matches().idx

    @property
    def valid(self) -> Tensor:
        return self._matches().valid

    @property
    def q(self) -> Tensor:
        return self._matches().q

    @property
    def match_fraction(self) -> float:
        kept = self._link.fraction(self._direction)
        return self._matches().match_fraction if kept is None else kept


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


@dataclass(frozen=True)
class PagedVerification(StoredVerification):
    """An admitted candidate's verification whose edge was paged out: its figures, and its
    edge's :class:`PagedLink` as its link (read from the store when asked for)."""


#: the matches of a verification that keeps its figures only
NO_MATCHES = DirectedMatches(
    torch.zeros(0, dtype=torch.int64), torch.zeros(0, dtype=torch.bool), torch.zeros(0)
)


def figures_only(v: Verification, link: PagedLink | None = None) -> StoredVerification:
    """``v`` without its matches; an admitted candidate's, whose edge was paged out, keeps
    that edge's paged ``link`` in their place and its co-visible shares
    (:class:`PagedVerification`)."""
    paged = link is not None
    return (PagedVerification if paged else StoredVerification)(
        v.candidate,
        v.query,
        v.similarity,
        NO_MATCHES,
        v.covisible_j if paged else None,
        link,
        v.covisible_i if paged else None,
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
    paged: dict[int, PagedLink] = {}  # id of the link let go of -> its paged link
    for n, link in enumerate(graph.links):
        if not isinstance(link.link, PagedLink) and link.i not in kept and link.j not in kept:
            paged[id(link.link)] = PagedLink.of(pages, n, link.link)
            graph.links[n] = replace(link, link=paged[id(link.link)])
            freed = True
    for candidate in coordinator.candidates:
        v = candidate.verification
        # an admitted candidate holds its edge's matches (the same link): now the paged one
        if candidate.status == "admitted" and v.link is not None and id(v.link) in paged:
            candidate.verification = figures_only(v, paged[id(v.link)])
        # a refused edge lets go of its matches, unless the coordinator tests it again after
        # its next global BA
        elif (
            candidate.status in ("rejected", "inconsistent")
            and not isinstance(v, StoredVerification)
            and not coordinator.awaiting_recheck(candidate)
        ):
            candidate.verification = figures_only(v)
            freed = True
    if freed:
        give_back_freed_memory()  # what was let go of leaves the process's RSS too (.heap)
