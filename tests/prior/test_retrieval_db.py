"""Tests of the codebook loader and the incremental ASMK retrieval database.

Scores are checked against an independent plain-numpy implementation of the binary ASMK of
MAST3R_SPEC.md §8.4 (quantisation, per-word residual aggregation with multiple assignment,
binarisation, selectivity, threshold, normalisation) on tiny random codebooks.
"""

from __future__ import annotations

import dataclasses
import math
import os
import pickle
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from como3r.config import RetrievalConfig
from como3r.errors import CheckpointError, ConfigError, InputError
from como3r.prior.codebook import load_codebook, train_codebook
from como3r.prior.retrieval import (
    Aggregated,
    Hit,
    Quantized,
    RetrievalDatabase,
    nearest_words,
)

K_WORDS = 16


# --- independent reference (spec §8.4) -------------------------------------------------


def _ref_words(x: np.ndarray, centroids: np.ndarray, ma: int) -> np.ndarray:
    """``(n, ma)`` nearest centroids by exact squared L2 distance."""
    d2 = ((x[:, None, :].astype(np.float64) - centroids[None].astype(np.float64)) ** 2).sum(-1)
    return np.argsort(d2, axis=1, kind="stable")[:, :ma]


def _ref_image(x: np.ndarray, centroids: np.ndarray, ma: int) -> dict[int, np.ndarray]:
    """Visual word -> binarised residual sum ``[R_w > 0]`` (bool ``(d,)``)."""
    words = _ref_words(x, centroids, ma)
    image = {}
    for w in set(words.ravel().tolist()):
        members = [i for i in range(len(x)) if w in words[i]]
        residual = np.zeros(x.shape[1], dtype=np.float32)
        for i in members:
            residual += x[i] - centroids[w]
        image[w] = residual > 0
    return image


def _ref_score(query: dict, stored: dict, dim: int, alpha: float, threshold: float) -> float:
    """``sum_w sigma(1 - 2 h_w) / sqrt(|W_q| |W_d|)`` with the packed-bit normaliser."""
    packed_bits = 32 * math.ceil(dim / 32)
    total = 0.0
    for w in query.keys() & stored.keys():
        s = 1.0 - 2.0 * np.count_nonzero(query[w] != stored[w]) / packed_bits
        if s >= threshold:
            total += s**alpha
    return total / math.sqrt(len(query) * len(stored))


# --- data ------------------------------------------------------------------------------


def _places(
    dim: int, n_places: int, seed: int, k_words: int = K_WORDS, n_desc: int = 12
) -> tuple[np.ndarray, list[np.ndarray]]:
    """A codebook and ``n_places`` base images.

    Like real local features, each descriptor lies near a centroid: a place is a set of
    ``n_desc`` distinct visual words with its own offsets from their centroids.
    """
    rng = np.random.default_rng(seed)
    centroids = rng.standard_normal((k_words, dim)).astype(np.float32)
    bases = [
        centroids[rng.choice(k_words, n_desc, replace=False)]
        + 0.3 * rng.standard_normal((n_desc, dim)).astype(np.float32)
        for _ in range(n_places)
    ]
    return centroids, bases


def _view(base: np.ndarray, rng: np.random.Generator, noise: float = 0.05) -> np.ndarray:
    """Another view of a place: the same descriptors with noise, a few dropped."""
    keep = rng.permutation(len(base))[: len(base) - 4]
    return (base[keep] + noise * rng.standard_normal((len(keep), base.shape[1]))).astype(np.float32)


CONFIGS = {
    "spec": RetrievalConfig(),
    "alpha2-thr": RetrievalConfig(alpha=2.0, similarity_threshold_asmk=0.25),
    "ma2-ma3": RetrievalConfig(multiple_assignment_build=2, multiple_assignment_query=3),
}


@pytest.mark.parametrize("dim", [8, 64])
@pytest.mark.parametrize("name", list(CONFIGS))
def test_scores_match_independent_asmk(dim, name):
    config = CONFIGS[name]
    rng = np.random.default_rng(1)
    centroids, bases = _places(dim, 3, seed=dim)
    stored = [_view(bases[i % 3], rng) for i in range(6)]
    queries = [_view(b, rng) for b in bases] + [rng.standard_normal((10, dim)).astype(np.float32)]
    db = RetrievalDatabase(centroids, config)
    for i, x in enumerate(stored):
        db.add(agent=i % 2, keyframe=i, descriptors=x)

    stored_ref = [_ref_image(x, centroids, config.multiple_assignment_build) for x in stored]
    for q in queries:
        q_ref = _ref_image(q, centroids, config.multiple_assignment_query)
        want = [
            _ref_score(q_ref, d, dim, config.alpha, config.similarity_threshold_asmk)
            for d in stored_ref
        ]
        np.testing.assert_allclose(db.scores(q), want, rtol=0, atol=1e-6)


def test_threshold_and_alpha_change_scores():
    """The config is honoured: the 'spec' and 'alpha2-thr' kernels score differently."""
    rng = np.random.default_rng(2)
    centroids, bases = _places(64, 2, seed=3)
    dbs = [RetrievalDatabase(centroids, CONFIGS[n]) for n in ("spec", "alpha2-thr")]
    for db in dbs:
        db.add(0, 0, _view(bases[0], rng))
    query = _view(bases[0], rng)
    assert abs(dbs[0].scores(query)[0] - dbs[1].scores(query)[0]) > 1e-3


def test_incremental_adds_equal_batch_build():
    rng = np.random.default_rng(4)
    centroids, bases = _places(32, 4, seed=5)
    images = [_view(bases[i % 4], rng) for i in range(8)]
    query = _view(bases[1], rng)
    incremental = RetrievalDatabase(centroids, RetrievalConfig())
    history = []
    for i, x in enumerate(images):
        incremental.add(0, i, x)
        assert len(incremental) == i + 1
        history.append(incremental.scores(query))
    # Earlier images keep their scores as later ones arrive (binary kernel, no IDF).
    for before, after in zip(history, history[1:]):
        np.testing.assert_allclose(after[: len(before)], before, atol=1e-12)
    rebuilt = RetrievalDatabase(centroids, RetrievalConfig())
    for i, x in enumerate(images):
        rebuilt.add(0, i, x)
    np.testing.assert_allclose(rebuilt.scores(query), history[-1], atol=1e-12)
    assert incremental.keys == [(0, i) for i in range(8)]


@pytest.fixture
def team_db() -> tuple[RetrievalDatabase, list[np.ndarray], np.random.Generator]:
    """Three agents x three keyframes; keyframe f of every agent shows place f."""
    rng = np.random.default_rng(6)
    centroids, bases = _places(32, 3, seed=7, k_words=64, n_desc=20)
    db = RetrievalDatabase(centroids, RetrievalConfig())
    for agent in range(3):
        for keyframe in range(3):
            db.add(agent, keyframe, _view(bases[keyframe], rng))
    return db, bases, rng


def _brute_force(db, scores, k, threshold, keep):
    ranked = sorted((i for i, key in enumerate(db.keys) if keep(key)), key=lambda i: -scores[i])
    return [Hit(*db.keys[i], scores[i]) for i in ranked[:k] if scores[i] > threshold]


def test_query_filters_by_agent_k_and_threshold(team_db):
    db, bases, rng = team_db
    query = _view(bases[2], rng)
    scores = db.scores(query)

    everything = db.query(query, k=len(db), min_similarity=-1.0)
    assert everything == _brute_force(db, scores, len(db), -1.0, lambda key: True)
    assert [h.similarity for h in everything] == sorted(scores, reverse=True)

    others = db.query(query, k=2, min_similarity=0.0, exclude_agent=1)
    assert others == _brute_force(db, scores, 2, 0.0, lambda key: key[0] != 1)
    own = db.query(query, k=2, min_similarity=0.0, agent=1)
    assert own == _brute_force(db, scores, 2, 0.0, lambda key: key[0] == 1)
    assert own[0][:2] == (1, 2)  # the same place wins

    excluded = {(0, 2), (2, 2)}
    rest = db.query(query, k=3, min_similarity=0.0, exclude_keyframes=excluded)
    assert rest == _brute_force(db, scores, 3, 0.0, lambda key: key not in excluded)

    second = sorted(scores, reverse=True)[1]
    assert db.query(query, k=5, min_similarity=second) == everything[:1]  # strictly greater

    defaults = db.query(query)  # config.k_nn = 3, config.min_similarity = 5e-3
    assert defaults == _brute_force(db, scores, 3, 5e-3, lambda key: True)


def test_same_place_is_retrieved_across_agents(team_db):
    db, bases, rng = team_db
    for place in range(3):
        hits = db.query(_view(bases[place], rng), k=2, min_similarity=0.0, exclude_agent=0)
        assert [h.keyframe for h in hits] == [place, place]
        assert {h.agent for h in hits} == {1, 2}


def test_query_and_add_equals_query_then_add():
    rng = np.random.default_rng(8)
    centroids, bases = _places(32, 3, seed=9)
    frames = [(i % 2, i, _view(bases[i % 3], rng)) for i in range(7)]
    combined = RetrievalDatabase(centroids, RetrievalConfig())
    separate = RetrievalDatabase(centroids, RetrievalConfig())
    for agent, keyframe, x in frames:
        hits = combined.query_and_add(agent, keyframe, x, k=3, min_similarity=0.0, scope="others")
        want = separate.query(x, k=3, min_similarity=0.0, exclude_agent=agent) if separate else []
        separate.add(agent, keyframe, x)
        assert hits == want
        assert all(h.agent != agent for h in hits)
    assert len(combined) == len(separate) == 7
    np.testing.assert_allclose(combined.scores(frames[0][2]), separate.scores(frames[0][2]))
    own = combined.query_and_add(1, 99, _view(bases[0], rng), k=5, min_similarity=-1.0, scope="own")
    assert own and all(h.agent == 1 for h in own)


@pytest.mark.parametrize("name", list(CONFIGS))
def test_quantized_once_equals_quantized_per_call(name):
    """Descriptors quantised once (query's and build's words from one search) score, query
    and index as descriptors quantised by each call; the nearest-first words are the
    independent reference's."""
    config = CONFIGS[name]
    rng = np.random.default_rng(12)
    centroids, bases = _places(32, 3, seed=13)
    once, per_call = (RetrievalDatabase(centroids, config) for _ in range(2))
    for i in range(6):
        x = _view(bases[i % 3], rng)
        quantized = once.quantize(torch.from_numpy(x))
        ma = max(config.multiple_assignment_query, config.multiple_assignment_build)
        np.testing.assert_array_equal(quantized.words, _ref_words(x, centroids, ma))
        np.testing.assert_array_equal(once.scores(quantized), per_call.scores(x))
        assert once.query(quantized, k=3, min_similarity=-1.0) == per_call.query(
            x, k=3, min_similarity=-1.0
        )
        once.add(0, i, quantized, np.ones(len(x)))
        per_call.add(0, i, x)
    np.testing.assert_array_equal(once.scores(bases[0]), per_call.scores(bases[0]))
    assert once.query_and_add(1, 0, once.quantize(bases[1])) == per_call.query_and_add(
        1, 0, bases[1]
    )


@pytest.mark.parametrize("ma", [1, 5])
def test_nearest_words_are_the_nearest_centroids_in_order(device, ma):
    """The device-side search (MASt3R-SLAM's GPU quantisation), on every device here."""
    rng = np.random.default_rng(14)
    centroids, bases = _places(64, 2, seed=15, k_words=256, n_desc=40)
    x = np.concatenate([_view(b, rng) for b in bases])
    words = nearest_words(
        torch.from_numpy(x).to(device), torch.from_numpy(centroids).to(device), ma
    )
    assert words.device.type == device.type and words.dtype == torch.int64
    np.testing.assert_array_equal(words.cpu().numpy(), _ref_words(x, centroids, ma))


def test_quantize_on_the_descriptors_device(device):
    """Descriptors on a device are quantised there (faiss on the CPU): the same words."""
    centroids, bases = _places(32, 1, seed=16, k_words=64)
    db = RetrievalDatabase(centroids, RetrievalConfig())
    x = _view(bases[0], np.random.default_rng(17))
    quantized = db.quantize(torch.from_numpy(x).to(device))
    np.testing.assert_array_equal(quantized.words, db.quantize(x).words)
    np.testing.assert_array_equal(quantized.descriptors, x)


def test_quantized_words_too_few_or_mismatched_rejected(team_db):
    db, bases, rng = team_db
    x = _view(bases[0], rng)
    words = db.quantize(x).words
    with pytest.raises(InputError, match="expected"):
        db.scores(Quantized(x, words[:, :2]))  # the query needs 5 words per descriptor
    with pytest.raises(InputError, match="expected"):
        db.add(7, 0, Quantized(x[:-1], words))
    with pytest.raises(InputError, match="attention"):
        db.add(7, 0, db.quantize(x), np.ones(len(x) + 1))
    with pytest.raises(InputError, match=r"integers in \[0, 64\)"):
        db.add(7, 0, Quantized(x, words + 64))  # another codebook's words
    with pytest.raises(InputError, match="d = 31"):
        db.add(7, 0, Quantized(np.zeros((5, 31), np.float32), words[:5]))
    assert len(db) == 9


def test_torch_inputs_and_attention_accepted(team_db):
    db, bases, rng = team_db
    query = _view(bases[0], rng)
    np.testing.assert_allclose(db.scores(torch.from_numpy(query)), db.scores(query))
    db.add(5, 0, torch.from_numpy(query), torch.ones(len(query)))
    assert db.query(query, k=1, min_similarity=0.0)[0][:2] == (5, 0)


@pytest.mark.parametrize(
    "descriptors, attention, message",
    [
        (np.zeros((5, 31), np.float32), None, "d = 31"),
        (np.zeros((0, 32), np.float32), None, "non-empty"),
        (np.full((3, 32), np.nan, np.float32), None, "non-finite"),
        (np.zeros((4, 32), np.float32), np.ones(5), "attention"),
    ],
)
def test_bad_inputs_raise_input_error(team_db, descriptors, attention, message):
    db, _, _ = team_db
    with pytest.raises(InputError, match=message):
        db.add(7, 0, descriptors, attention)
    assert len(db) == 9


def test_duplicate_keyframe_and_bad_arguments_rejected(team_db):
    db, bases, rng = team_db
    with pytest.raises(InputError, match="agent 1 keyframe 2 already added"):
        db.query_and_add(1, 2, _view(bases[0], rng))
    with pytest.raises(InputError, match="scope"):
        db.query_and_add(1, 50, _view(bases[0], rng), scope="mine")
    with pytest.raises(InputError, match="k = -1"):
        db.query(_view(bases[0], rng), k=-1)
    assert len(db) == 9
    with pytest.raises(ConfigError, match="multiple_assignment"):
        RetrievalDatabase(bases[0], RetrievalConfig(multiple_assignment_query=0))


def test_empty_database_returns_no_hits():
    centroids, bases = _places(8, 1, seed=10)
    db = RetrievalDatabase(centroids, RetrievalConfig())
    assert db.query(bases[0], k=3, min_similarity=-1.0) == []
    assert db.query_and_add(0, 0, bases[0]) == [] and len(db) == 1


def test_multiple_assignment_larger_than_codebook():
    rng = np.random.default_rng(11)
    centroids = rng.standard_normal((3, 8)).astype(np.float32)
    db = RetrievalDatabase(centroids, RetrievalConfig(multiple_assignment_query=5))
    x = rng.standard_normal((6, 8)).astype(np.float32)
    db.add(0, 0, x)
    want = _ref_score(_ref_image(x, centroids, 3), _ref_image(x, centroids, 1), 8, 3.0, 0.0)
    np.testing.assert_allclose(db.scores(x), [want], atol=1e-6)


# --- agreement with the asmk package's own pipeline (spec §8.3 parameters) ------------


def _write_asmk_codebook(path: Path, centroids: np.ndarray, size) -> None:
    """Write a codebook exactly as ``asmk`` does (Codebook.state_dict + save_pickle)."""
    from asmk import codebook, index, io_helpers

    book = codebook.Codebook(index.FaissL2Index(), size=size)
    book.index(centroids)
    io_helpers.save_pickle(str(path), book.state_dict())


def test_scores_match_asmk_method_with_retriever_parameters(tmp_path):
    from asmk import ASMKMethod

    rng = np.random.default_rng(12)
    centroids, bases = _places(64, 3, seed=13)
    path = tmp_path / "codebook.pkl"
    _write_asmk_codebook(path, centroids, K_WORDS)
    params = {
        "index": {"gpu_id": None},
        "train_codebook": {"codebook": {"size": K_WORDS}},
        "build_ivf": {
            "kernel": {"binary": True},
            "ivf": {"use_idf": False},
            "quantize": {"multiple_assignment": 1},
            "aggregate": {},
        },
        "query_ivf": {
            "quantize": {"multiple_assignment": 5},
            "aggregate": {},
            "search": {"topk": None},
            "similarity": {"similarity_threshold": 0.0, "alpha": 3.0},
        },
    }
    stored = [_view(bases[i % 3], rng) for i in range(5)]
    queries = [_view(b, rng) for b in bases]
    method = ASMKMethod.initialize_untrained(params).train_codebook(None, cache_path=str(path))
    method = method.build_ivf(
        np.vstack(stored), np.concatenate([np.full(len(x), i) for i, x in enumerate(stored)])
    )
    _, _, ranks, ranked = method.query_ivf(
        np.vstack(queries), np.concatenate([np.full(len(q), i) for i, q in enumerate(queries)])
    )

    db = RetrievalDatabase(load_codebook(path), RetrievalConfig())
    for i, x in enumerate(stored):
        db.add(0, i, x)
    for q, rank, score in zip(queries, ranks, ranked):
        expected = np.empty(len(stored))
        expected[rank] = score
        np.testing.assert_allclose(db.scores(q), expected, atol=1e-12)


# --- codebook files --------------------------------------------------------------------


@pytest.mark.parametrize("size", [K_WORDS, "1k"])
def test_load_codebook_written_by_asmk(tmp_path, size):
    rows = K_WORDS if size == K_WORDS else 1024
    centroids = np.random.default_rng(14).standard_normal((rows, 8)).astype(np.float32)
    path = tmp_path / "codebook.pkl"
    _write_asmk_codebook(path, centroids, size)
    loaded = load_codebook(path)
    assert loaded.dtype == np.float32 and loaded.flags.c_contiguous
    np.testing.assert_array_equal(loaded, centroids)


@pytest.mark.parametrize("protocol", [2, 3, 4, 5])
def test_load_codebook_any_pickle_protocol(tmp_path, protocol):
    centroids = np.random.default_rng(15).standard_normal((K_WORDS, 8))  # float64 on disk
    state = {"type": "Codebook", "params": {"size": K_WORDS}, "state": {"centroids": centroids}}
    path = tmp_path / "codebook.pkl"
    path.write_bytes(pickle.dumps(state, protocol=protocol))
    np.testing.assert_allclose(load_codebook(path), centroids.astype(np.float32))


class _Payload:
    """Unpickling this object calls ``function(*args)``."""

    def __init__(self, function, *args):
        self.function, self.args = function, args

    def __reduce__(self):
        return self.function, self.args


PAYLOADS = {
    "os.system": (lambda marker: _Payload(os.system, f"touch {marker}"), "posix.system"),
    "builtins.eval": (
        lambda marker: _Payload(eval, f"open({str(marker)!r}, 'w').close()"),
        "builtins.eval",
    ),
    "subprocess.Popen": (
        lambda marker: _Payload(subprocess.Popen, ["touch", str(marker)]),
        "subprocess.Popen",
    ),
}


@pytest.mark.parametrize("name", list(PAYLOADS))
def test_malicious_codebook_refused_without_running(tmp_path, name):
    make, refused = PAYLOADS[name]
    marker = tmp_path / "pwned"
    centroids = np.zeros((2, 4), np.float32)
    state = {"type": "Codebook", "params": {"size": 2}, "state": {"centroids": centroids}}
    state["params"]["extra"] = make(marker)
    path = tmp_path / "evil_codebook.pkl"
    path.write_bytes(pickle.dumps(state))

    with pytest.raises(CheckpointError) as info:
        load_codebook(path)
    assert str(path) in str(info.value) and refused in str(info.value)
    assert not marker.exists()


def _state_pickle(centroids, size=None, kind="Codebook") -> bytes:
    size = len(centroids) if size is None else size
    return pickle.dumps({"type": kind, "params": {"size": size}, "state": {"centroids": centroids}})


MALFORMED = {
    "missing file": (None, "cannot read"),
    "truncated": (_state_pickle(np.ones((4, 4), np.float32))[:-40], "not a valid codebook"),
    "garbage": (b"\x80\x04garbage", "not a valid codebook"),
    "not a dict": (pickle.dumps([1, 2, 3]), "not an asmk codebook"),
    "wrong type": (_state_pickle(np.ones((4, 4), np.float32), kind="IVF"), "not an asmk codebook"),
    "no centroids": (
        pickle.dumps({"type": "Codebook", "params": {"size": 4}, "state": {}}),
        "state.centroids",
    ),
    "size mismatch": (_state_pickle(np.ones((4, 4), np.float32), size="1k"), "!= 4 centroids"),
    "bad size": (_state_pickle(np.ones((4, 4), np.float32), size="four"), "params.size"),
    "1-d": (_state_pickle(np.ones(4, np.float32), size=4), "shape"),
    "integer": (_state_pickle(np.ones((4, 4), np.int64)), "dtype"),
    "non-finite": (_state_pickle(np.full((4, 4), np.inf, np.float32)), "non-finite"),
}


@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_codebook_raises_one_line_error(tmp_path, case):
    content, message = MALFORMED[case]
    path = tmp_path / "some_codebook.pkl"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(CheckpointError) as info:
        load_codebook(path)
    text = str(info.value)
    assert str(path) in text and message in text and "\n" not in text


# --- codebook training -----------------------------------------------------------------


def test_train_codebook_is_deterministic_and_converged():
    rng = np.random.default_rng(16)
    centres = rng.standard_normal((8, 16)).astype(np.float32) * 10
    features = np.vstack([c + 0.1 * rng.standard_normal((50, 16)) for c in centres])
    features = features[rng.permutation(len(features))].astype(np.float32)

    first = train_codebook(features, 8, seed=3)
    assert first.shape == (8, 16) and first.dtype == np.float32
    np.testing.assert_array_equal(first, train_codebook(features, 8, seed=3))
    # Lloyd's fixed point: every centroid is the mean of the features nearest to it ...
    nearest = np.linalg.norm(features[:, None] - first[None], axis=-1).argmin(axis=1)
    for j in range(8):
        np.testing.assert_allclose(first[j], features[nearest == j].mean(0), atol=1e-4)
    # ... and it quantises far better than one global mean (k-means may still merge blobs).
    error = np.mean(np.sum((features - first[nearest]) ** 2, axis=1))
    assert error < 0.2 * np.mean(np.sum((features - features.mean(0)) ** 2, axis=1))

    noise = rng.standard_normal((300, 16)).astype(np.float32)
    assert not np.array_equal(train_codebook(noise, 8, seed=0), train_codebook(noise, 8, seed=1))
    with pytest.raises(InputError, match="k = 400"):
        train_codebook(noise, 400, seed=0)


def test_config_fields_are_the_spec_parameters():
    """RetrievalDatabase reads these fields; their defaults are the §8.3 values."""
    values = dataclasses.asdict(RetrievalConfig())
    assert values["binary"] is True and values["use_idf"] is False
    assert (values["alpha"], values["similarity_threshold_asmk"]) == (3.0, 0.0)
    assert (values["multiple_assignment_build"], values["multiple_assignment_query"]) == (1, 5)


@pytest.mark.parametrize("name", list(CONFIGS))
def test_aggregated_keyframes_give_the_hits_and_similarities_of_their_descriptors(name):
    """A keyframe sent as what binary ASMK reads of it (the per-word sign bits of its
    residual sums, :meth:`RetrievalDatabase.aggregate`, as another process with the same
    codebook makes them) is retrieved, and retrieves, exactly as its descriptors."""
    config = CONFIGS[name]
    rng = np.random.default_rng(21)
    centroids, bases = _places(32, 3, seed=22)
    frames = [(i % 3, i, _view(bases[i % 3], rng)) for i in range(8)]
    sender = RetrievalDatabase(centroids, config)  # the agent's: a codebook, no images
    from_descriptors = RetrievalDatabase(centroids, config)
    from_aggregates = RetrievalDatabase(centroids, config)
    for agent, keyframe, x in frames:
        aggregated = sender.aggregate(x)
        assert isinstance(aggregated, Aggregated)
        assert aggregated.build_words.shape[0] <= aggregated.query_words.shape[0]
        expected = from_descriptors.query_and_add(
            agent, keyframe, x, k=4, min_similarity=-1.0, scope="others"
        )
        hits = from_aggregates.query_and_add(
            agent, keyframe, aggregated, k=4, min_similarity=-1.0, scope="others"
        )
        assert hits == expected
    assert len(expected) > 0 and from_aggregates.keys == from_descriptors.keys
    probe = _view(bases[1], rng)
    np.testing.assert_array_equal(from_aggregates.scores(probe), from_descriptors.scores(probe))
    np.testing.assert_array_equal(
        from_aggregates.scores(sender.aggregate(probe)), from_descriptors.scores(probe)
    )
    # a resumed database adds the stored aggregates (their build half) as the descriptors
    resumed = RetrievalDatabase(centroids, config)
    for agent, keyframe, x in frames:
        resumed.add(agent, keyframe, sender.aggregate(x))
    np.testing.assert_array_equal(resumed.scores(probe), from_descriptors.scores(probe))


def test_malformed_aggregates_rejected(team_db):
    db, bases, rng = team_db
    good = db.aggregate(_view(bases[0], rng))
    replace = dataclasses.replace
    wrong_words = replace(good, query_words=good.query_words[::-1].copy())
    short_bits = replace(good, build_bits=good.build_bits[:, :-1])
    out_of_range = replace(good, build_words=good.build_words + db.codebook_size)
    other_codebook = replace(good, codebook_id="0" * 32)
    for bad, message in (
        (wrong_words, "ascending"),
        (short_bits, "uint32 bits"),
        (out_of_range, "ascending"),
        (other_codebook, "same codebook"),
    ):
        with pytest.raises(InputError, match=message):
            db.query_and_add(5, 0, bad)
        with pytest.raises(InputError, match=message):
            db.add(5, 0, bad) if bad is not wrong_words else db.scores(bad)
    assert len(db) == 9  # nothing added
