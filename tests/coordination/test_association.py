"""Cross-agent retrieval and dense verification (C-Sec. 3.4, C-Eq. 12, co-visibility test)."""

from __future__ import annotations

import pytest
import torch

from como3r.config import Config, apply_overrides
from como3r.coordination.association import (
    CrossAgentRetrieval,
    budget_candidates,
    verify_candidates,
)
from como3r.data.agent import open_agent
from como3r.data.ground_truth import AgentFolderTruth
from como3r.data.preprocess import make_view
from como3r.data.synth import synthesize
from como3r.errors import ConfigError
from como3r.frontend.pairs import DirectedMatches, covisible_fraction
from como3r.geometry.lie import quat_conjugate, quat_multiply, sim3_compose, sim3_inverse, so3_log
from como3r.geometry.umeyama import umeyama_sim3
from como3r.prior.base import PairPrediction
from como3r.prior.retrieval import Hit
from como3r.prior.simulated import SimulatedPrior

WIDTH, HEIGHT, STEP = 96, 72, 4


@pytest.fixture(scope="module")
def facades(tmp_path_factory):
    """Two agents among identical façades: every 4th frame's encoding, pointmap and pose."""
    root = tmp_path_factory.mktemp("aliasing")
    synthesize(
        root,
        agents=2,
        seed=1,
        overlap=0.2,
        frames=20,
        preset="aliasing",
        width=WIDTH,
        height=HEIGHT,
    )
    # the easy simulated prior: the façade verification fails under the realistic default
    config = apply_overrides(Config(), [f"input.long_side={WIDTH}", "simulated_prior.model=easy"])
    prior = SimulatedPrior(
        config.simulated_prior,
        AgentFolderTruth({a: open_agent(root / f"agent_{a}") for a in range(2)}, WIDTH),
    )
    views = {}
    for a in range(2):
        agent = open_agent(root / f"agent_{a}")
        for index in range(0, agent.num_frames, STEP):
            enc = prior.encode(make_view(agent.load_frame(index), a, WIDTH))
            views[(a, index)] = (
                enc,
                prior.decode(enc, enc).X_ii,
                agent.groundtruth.T_WC[index].double(),
            )
    return prior, config, views


def _is_true_pair(verification, views) -> bool:
    """Whether the relative pose implied by the matches is the true one (5 deg, 0.3 m)."""
    _, X_i, T_i = views[verification.candidate]
    _, X_j, T_j = views[verification.query]
    matches = verification.link.ij
    implied = umeyama_sim3(
        X_j.reshape(-1, 3)[matches.valid].double(),
        X_i.reshape(-1, 3)[matches.idx[matches.valid]].double(),
    )
    T_ij = sim3_compose(sim3_inverse(T_i), T_j)
    angle = float(so3_log(quat_multiply(quat_conjugate(implied[3:7]), T_ij[3:7])).norm())
    # the pointmaps are metric up to the prior's ~5 % scale error
    return angle < 5.0 * torch.pi / 180.0 and float((implied[:3] - T_ij[:3]).norm()) < 0.3


def _verify_all_pairs(prior, config, views):
    results = []
    for query in [k for k in views if k[0] == 1]:
        candidates = [(Hit(*key, 0.0), views[key][0]) for key in views if key[0] == 0]
        results += verify_candidates(
            prior,
            query,
            views[query][0],
            candidates,
            config.matching,
            config.tracking.q_min,
            config.verification,
        )
    return results


@pytest.mark.slow
def test_only_true_pairs_pass_among_identical_facades(facades) -> None:
    prior, config, views = facades
    results = _verify_all_pairs(prior, config, views)
    accepted = [v for v in results if v.accepted]
    assert accepted, "the agents' true meeting was not verified"
    assert all(_is_true_pair(v, views) for v in accepted)
    assert all(v.covisible_ratio >= config.verification.min_covisible_ratio for v in accepted)
    # C-Eq. 12 alone (the paper's test, no co-visibility ratio) accepts hallucinated pairs here
    paper = apply_overrides(config, ["verification.min_covisible_ratio=0"])
    fooled = [
        v
        for v, ours in zip(_verify_all_pairs(prior, paper, views), results)
        if v.accepted and not ours.accepted
    ]
    assert fooled and not any(_is_true_pair(v, views) for v in fooled)


def test_a_pair_failing_its_first_direction_is_not_matched_twice(facades) -> None:
    prior, config, views = facades
    results = _verify_all_pairs(prior, config, views)
    screened = [v for v in results if v.link is None]
    assert screened, "no candidate failed its first direction on this scene"
    for v in screened:
        passes_nu = v.nu_j >= config.verification.tau_inter
        passes_ratio = v.nu_j / v.covisible_j >= config.verification.min_covisible_ratio
        assert not v.accepted and not (passes_nu and passes_ratio)
        assert v.nu_i is None and v.covisible_i is None and v.covisible_ratio is None
    for v in results:
        if v.link is not None:
            assert v.nu_j == v.link.ij.match_fraction


def test_verification_reports_both_directions(facades) -> None:
    prior, config, views = facades
    accepted = [v for v in _verify_all_pairs(prior, config, views) if v.accepted]
    query, candidate = accepted[0].query, accepted[0].candidate
    [result] = verify_candidates(
        prior,
        query,
        views[query][0],
        [(Hit(*candidate, 0.02), views[candidate][0])],
        config.matching,
        config.tracking.q_min,
        config.verification,
    )
    assert result.candidate == candidate and result.query == query
    assert result.similarity == 0.02 and result.accepted
    assert result.nu_i == result.link.ji.match_fraction
    assert result.nu_j == result.link.ij.match_fraction
    assert 0.0 <= result.covisible_i <= 1.0 and 0.0 <= result.covisible_j <= 1.0
    assert (
        verify_candidates(
            prior,
            query,
            views[query][0],
            [],
            config.matching,
            config.tracking.q_min,
            config.verification,
        )
        == []
    )


def _pinhole_rays(H: int, W: int) -> torch.Tensor:
    v, u = torch.meshgrid(
        torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij"
    )
    return torch.stack([(u - W / 2) / W, (v - H / 2) / W, torch.ones_like(u)], dim=-1)


def test_covisible_fraction_counts_points_inside_the_other_view() -> None:
    H, W = 40, 50
    X_ii = 5.0 * _pinhole_rays(H, W)
    X_ji = X_ii.clone()
    X_ji[:, W // 2 :, 2] *= -1.0  # the right half of view j lies behind camera i
    ones = torch.ones(H, W)
    pred = PairPrediction(
        X_ii, X_ji, 3.0 * ones, 3.0 * ones, torch.zeros(H, W, 4), torch.zeros(H, W, 4), ones, ones
    )
    matches = DirectedMatches(
        torch.arange(H * W), torch.ones(H * W, dtype=torch.bool), torch.ones(H * W)
    )
    full = covisible_fraction(pred, matches, min_confidence=1.5)
    assert 0.4 <= full <= 0.5  # the left half, less the outermost rays of the box
    # pixels of i that are not confidently seen do not count
    dim = PairPrediction(
        X_ii, X_ji, ones, 3.0 * ones, torch.zeros(H, W, 4), torch.zeros(H, W, 4), ones, ones
    )
    assert covisible_fraction(dim, matches, min_confidence=1.5) == 0.0


def test_retrieval_returns_other_agents_only(facades) -> None:
    prior, config, views = facades
    retrieval = CrossAgentRetrieval(prior.codebook(), config.retrieval)
    hits = {}
    for a, index in sorted(views, key=lambda k: (k[1], k[0])):
        hits[(a, index)] = retrieval.query_and_add(
            a, index, prior.retrieval_features(views[(a, index)][0])
        )
    assert retrieval.queries == len(views)
    assert hits[(0, 0)] == []
    for (a, _), found in hits.items():
        assert len(found) <= config.retrieval.k_nn
        assert all(h.agent != a and h.similarity > config.retrieval.min_similarity for h in found)
        assert [h.similarity for h in found] == sorted((h.similarity for h in found), reverse=True)
    assert any(hits.values())


class _CountingPrior:
    """A prior that counts the ordered pairs it decodes."""

    def __init__(self, prior) -> None:
        self.prior, self.decodes = prior, 0

    def decode_pairs(self, pairs):
        self.decodes += len(pairs)
        return self.prior.decode_pairs(pairs)

    def decode_symmetric(self, pairs):
        self.decodes += 2 * len(pairs)
        return self.prior.decode_symmetric(pairs)


@pytest.mark.parametrize("agents", [8, 16])
@pytest.mark.parametrize("budget", [2, 6])
def test_a_keyframes_decodes_stay_within_the_budget_whatever_the_team(
    facades, agents, budget
) -> None:
    prior, config, views = facades
    config = apply_overrides(
        config,
        [f"verification.max_decodes_per_keyframe={budget}", "verification.max_within_component=1"],
    )
    [query] = [k for k in views if k[0] == 1][1:2]
    # every other agent offers candidates (agent 0's keyframes under other agents' names);
    # the lower half of the team already shares the query's gauge component
    keys = [k for k in views if k[0] == 0]
    hits = [
        Hit(agent, keyframe, 0.1 - 0.001 * n)
        for n, (agent, (_, keyframe)) in enumerate(
            (a, keys[(a + i) % len(keys)]) for i in range(3) for a in range(agents) if a != 1
        )
    ]
    merged = lambda agent: agent < agents // 2  # noqa: E731
    chosen = budget_candidates(hits, merged, config.verification)
    counting = _CountingPrior(prior)
    results = verify_candidates(
        counting,
        query,
        views[query][0],
        [(h, views[(0, h.keyframe)][0]) for h in chosen],
        config.matching,
        config.tracking.q_min,
        config.verification,
    )
    assert len(results) == len(chosen) == budget // 2 < len(hits)
    assert 0 < counting.decodes <= budget
    assert sum(merged(h.agent) for h in chosen) <= config.verification.max_within_component
    # best first: a hit is left out only for a better one or for its merged agent
    best_unmerged = sorted((h for h in hits if not merged(h.agent)), key=lambda h: -h.similarity)
    assert [h for h in chosen if not merged(h.agent)] == best_unmerged[
        : len([h for h in chosen if not merged(h.agent)])
    ]
    assert chosen[0] == max(hits, key=lambda h: h.similarity)


def test_the_budget_skips_merged_agents_past_their_share() -> None:
    verification = apply_overrides(Config(), ["verification.max_within_component=1"]).verification
    hits = [Hit(2, 0, 0.09), Hit(3, 0, 0.08), Hit(4, 0, 0.07), Hit(5, 0, 0.06)]
    merged = lambda agent: agent in (2, 3)  # noqa: E731
    assert budget_candidates(hits, merged, verification) == [hits[0], hits[2], hits[3]]
    assert budget_candidates(hits, lambda agent: False, verification) == hits[:3]
    none_within = apply_overrides(Config(), ["verification.max_within_component=0"])
    assert budget_candidates(hits, merged, none_within.verification) == hits[2:]
    # unordered hits are ranked by similarity first
    assert budget_candidates(hits[::-1], lambda agent: False, verification) == hits[:3]
    # the defaults verify every one of the paper's k_NN = 3 hits
    assert budget_candidates(hits[:3], merged, Config().verification) == hits[:3]


def test_a_budget_below_one_candidate_is_refused() -> None:
    with pytest.raises(ConfigError, match="max_decodes_per_keyframe"):
        apply_overrides(Config(), ["verification.max_decodes_per_keyframe=1"])
