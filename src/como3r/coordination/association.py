"""Cross-agent association: retrieval, then dense geometric verification (C-Sec. 3.4, B.3).

1. **Retrieval.** Every keyframe's retrieval features go into ONE shared ASMK inverted file
   tagged by agent (:class:`CrossAgentRetrieval`). A new keyframe first queries it for the
   top ``k_NN`` keyframes of OTHER agents and keeps those whose similarity exceeds the
   threshold (C-Tab. 3: 3 and ``5e-3``), then is added to it.
   **Budget** (como3r addition, :func:`budget_candidates`): of those hits, at most
   ``verification.max_within_component`` whose agent already shares the keyframe's gauge
   component, and no more than ``verification.max_decodes_per_keyframe`` decodes' worth in
   all, are verified, best first: the work a keyframe causes is bounded whatever the team.
   The keyframe's loop candidates in its own agent (``verification.max_loop_candidates``)
   share that budget: after the hits that can merge two gauge components, before those of
   agents already merged (both only add loop constraints to the global BA).
2. **Verification.** Each candidate pair is decoded symmetrically by the prior and matched
   densely in both directions (:func:`~como3r.frontend.pairs.directed_matches`, the same
   code that builds every intra-agent edge); it is accepted when ``min(nu_i, nu_j) >=
   tau_inter`` (C-Eq. 12), which rejects one-sided matches, AND (como3r addition) when in
   both directions at least ``min_covisible_ratio`` of the co-visible pixels are matched.
   The query's direction is matched first; a pair it fails cannot pass, so its other
   direction is not matched (graph.json then records ``nu_i`` and ``covisible_ratio`` as
   null).

The co-visibility test exists because C-Eq. 12 alone does not reject repeated structure:
a prior shown two identical façades at different places predicts a pose that aligns them,
and the façade pixels then match in both directions (on the ``aliasing`` synthetic preset,
nu reaches 0.2 on such pairs). But the same predicted pose also places the rest of the
view, ground and clutter, inside the other view, where nothing matches it. So among the
pixels of view j that the pair's own pointmap ``X_ji`` puts inside view i's field of view
onto a confident pixel of i, we count the share with a valid match: 0.7-0.9 on true pairs
and 0.15-0.4 on hallucinated ones of that preset. View i's field of view is the box its
own rays span on the plane ``z = 1`` (1st to 99th percentile), which holds for pointmaps in
a forward-looking camera frame as MASt3R predicts them.

The simulated prior's retrieval similarities follow the MASt3R scale closely enough that
the paper's threshold applies unchanged: on synthetic scenes a keyframe scores about 0.15
against itself, 0.02-0.1 against overlapping views and below 0.005 against unrelated ones.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from torch import Tensor

from como3r.config import MatchingConfig, RetrievalConfig, VerificationConfig
from como3r.errors import Como3rError
from como3r.frontend.pairs import DirectedMatches, PairLink, direction_passes, link_pairs
from como3r.prior.base import Encoding, Prior
from como3r.prior.retrieval import Aggregated, Hit, Quantized, RetrievalDatabase


class CrossAgentRetrieval:
    """The coordinator's shared retrieval database over all agents' keyframes.

    Args:
        codebook: ``(K, d)`` ASMK codebook of the prior's retrieval features.
        config: ASMK parameters, ``k_nn`` and the similarity threshold.
    """

    def __init__(self, codebook: np.ndarray, config: RetrievalConfig) -> None:
        self.database = RetrievalDatabase(codebook, config)
        self.queries = 0

    def query_and_add(
        self,
        agent: int,
        kf_id: int,
        retrieval: tuple[Tensor | Quantized, Tensor] | Aggregated,
        loops: int = 0,
        skipped: int = 1,
    ) -> list[Hit]:
        """Candidates of OTHER agents for keyframe ``(agent, kf_id)``, then its loop
        candidates, then index it.

        Args:
            agent: the keyframe's agent.
            kf_id: its id within the agent.
            retrieval: ``(descriptors (N, d), attention (N,))`` of the keyframe, the
                descriptors perhaps already quantised (:class:`Quantized`), or their
                :class:`Aggregated` (in this database's codebook).
            loops: at most this many keyframes of its OWN agent (its loop candidates, as
                the agent's front-end finds its own, C-Sec. 3.5) follow the other agents'.
            skipped: the agent's latest keyframes that are never loop candidates.

        Returns:
            At most ``k_nn`` hits of other agents above the similarity threshold, best
            first, then at most ``loops`` of the keyframe's own agent, best first.
        """
        self.queries += 1
        descriptors, attention = (
            (retrieval, None) if isinstance(retrieval, Aggregated) else retrieval
        )
        own: list[Hit] = []
        if loops > 0 and kf_id > skipped:
            if not isinstance(descriptors, (Aggregated, Quantized)):
                descriptors = self.database.quantize(descriptors)  # one search for both
            excluded = [(agent, kf_id - n) for n in range(1, skipped + 1)]
            own = self.database.query(descriptors, k=loops, agent=agent, exclude_keyframes=excluded)
        others = self.database.query_and_add(agent, kf_id, descriptors, attention, scope="others")
        return others + own


#: prior decodes one candidate's verification costs at most (C-Eq. 12 decodes both orders)
DECODES_PER_CANDIDATE = 2


def budget_candidates(
    hits: Sequence[Hit], merged: Callable[[int], bool], verification: VerificationConfig
) -> list[Hit]:
    """The retrieval hits one keyframe verifies, best first, within its decode budget.

    Args:
        hits: the keyframe's retrieval hits over all other agents.
        merged: whether an agent already shares the keyframe's gauge component.
        verification: ``max_decodes_per_keyframe`` and ``max_within_component``.

    Returns:
        The hits by decreasing similarity (ties keep their order), skipping those of merged
        agents past ``max_within_component``, as many as fit ``max_decodes_per_keyframe``
        at two decodes each.
    """
    limit = verification.max_decodes_per_keyframe // DECODES_PER_CANDIDATE
    chosen: list[Hit] = []
    within = 0
    for hit in sorted(hits, key=lambda h: -h.similarity):
        if len(chosen) == limit:
            break
        if merged(hit.agent):
            if within == verification.max_within_component:
                continue
            within += 1
        chosen.append(hit)
    return chosen


@dataclass(frozen=True)
class Verification:
    """The dense verification of one candidate pair (C-Eq. 12 and the co-visibility test).

    The pair is ordered (candidate, query): ``ij`` is the edge (candidate, query), every
    pixel of the query keyframe looked up in the candidate keyframe. It is matched first;
    when it fails its half of the tests the pair cannot be accepted and the other direction
    is not matched (``link`` and the ``_i`` values are then None).

    Attributes:
        candidate: ``(agent, kf_id)`` of the retrieved keyframe (endpoint i).
        query: ``(agent, kf_id)`` of the new keyframe (endpoint j).
        similarity: the retrieval similarity of the pair.
        ij: the query's pixels looked up in the candidate.
        covisible_j: share of the query keyframe's pixels co-visible in the candidate.
        link: matches of both directions, None when ``ij`` failed.
        covisible_i: share of the candidate's pixels co-visible in the query keyframe.
        accepted: both tests passed in both directions.
    """

    candidate: tuple[int, int]
    query: tuple[int, int]
    similarity: float
    ij: DirectedMatches
    covisible_j: float | None
    link: PairLink | None
    covisible_i: float | None
    accepted: bool

    @property
    def nu_i(self) -> float | None:
        """Share of the candidate's pixels validly matched in the query keyframe."""
        return None if self.link is None else self.link.ji.match_fraction

    @property
    def nu_j(self) -> float:
        """Share of the query keyframe's pixels validly matched in the candidate."""
        return self.ij.match_fraction

    @property
    def covisible_ratio(self) -> float | None:
        """The smaller share, over both directions, of co-visible pixels that match."""
        return None if self.link is None else self.link.covisible_ratio


def verify_candidates(
    prior: Prior,
    query: tuple[int, int],
    query_encoding: Encoding,
    candidates: Sequence[tuple[Hit, Encoding]],
    matching: MatchingConfig,
    q_min: float,
    verification: VerificationConfig,
) -> list[Verification]:
    """Decode every (candidate, query) pair symmetrically in one batched call and test it.

    Args:
        prior: the two-view prior.
        query: ``(agent, kf_id)`` of the new keyframe.
        query_encoding: its encoding.
        candidates: retrieval hits with the encodings of their keyframes.
        matching: projective-matching parameters.
        q_min: minimum per-match confidence of a valid match.
        verification: ``tau_inter`` and the co-visibility test.

    Returns:
        One verification per candidate, in the candidates' order.
    """
    if not candidates:
        return []
    first: dict[int, tuple[DirectedMatches, float | None]] = {}

    def passes(matches: DirectedMatches, covisible: float | None) -> bool:
        return direction_passes(
            matches, covisible, verification.tau_inter, verification.min_covisible_ratio
        )

    def screen(k: int, ij: DirectedMatches, covisible: float | None) -> bool:
        first[k] = (ij, covisible)
        return passes(ij, covisible)

    # a pair whose first direction fails cannot pass (C-Eq. 12 takes the minimum over both
    # directions, the co-visibility test the smaller ratio): its second matching is skipped
    links = link_pairs(
        prior,
        [(enc, query_encoding) for _, enc in candidates],
        matching,
        q_min,
        verification.covisible_min_confidence,
        screen=screen,
    )
    results = []
    for k, ((hit, _), link) in enumerate(zip(candidates, links)):
        ij, covisible_j = first[k]
        results.append(
            Verification(
                (hit.agent, hit.keyframe),
                query,
                hit.similarity,
                ij,
                covisible_j,
                link,
                None if link is None else link.covisible_ji,
                accepted=link is not None and passes(link.ji, link.covisible_ji),
            )
        )
    return results


@dataclass(eq=False)
class Candidate:
    """A verified cross-agent candidate edge and what became of it.

    Attributes:
        verification: the dense verification (C-Eq. 12).
        i: global index of the candidate keyframe (endpoint i).
        j: global index of the new keyframe (endpoint j).
        status: ``"rejected"`` (C-Eq. 12 failed), ``"pending"`` (waiting for agreeing
            edges between two components), ``"admitted"`` (in the graph) or
            ``"inconsistent"`` (disagrees with the poses it would constrain).
        residual_ratio: the consistency measure of the last test (NaN if untested).
    """

    verification: Verification
    i: int
    j: int
    status: str = "rejected"
    residual_ratio: float = float("nan")

    @property
    def link(self) -> PairLink:
        """Both directions' matches; only verified candidates reach the code that asks."""
        link = self.verification.link
        if link is None or not self.verification.accepted:
            raise Como3rError(
                f"candidate {self.verification.candidate}-"
                f"{self.verification.query} was not verified"
            )
        return link
