"""Stage timing: exclusive nesting, the remainder stage, the timed prior."""

from __future__ import annotations

import time

import pytest

from como3r.frontend.timing import StageTimer, TimedPrior, with_remainder


def test_nested_stages_are_exclusive_and_add_up() -> None:
    seconds: dict[str, float] = {}
    timer = StageTimer(seconds)
    start = time.perf_counter()
    with timer.stage("outer"):
        time.sleep(0.02)
        with timer.stage("inner"):
            time.sleep(0.03)
        with timer.stage("outer"):  # re-entering a stage accumulates
            time.sleep(0.01)
    total = time.perf_counter() - start
    assert timer.seconds is seconds
    assert seconds["inner"] == pytest.approx(0.03, abs=0.02)
    assert seconds["outer"] == pytest.approx(0.03, abs=0.02)
    # every second inside is charged to exactly one stage (double counting would add 30 ms;
    # the context managers' own overhead is microseconds, more on a loaded machine)
    assert sum(seconds.values()) == pytest.approx(total, abs=2e-3)


def test_a_stage_left_by_an_exception_is_still_charged() -> None:
    timer = StageTimer()
    with pytest.raises(RuntimeError):
        with timer.stage("failing"):
            raise RuntimeError("boom")
    with timer.stage("next"):
        pass
    assert set(timer.seconds) == {"failing", "next"}


def test_remainder_makes_the_stages_sum_to_the_total() -> None:
    stages = with_remainder({"a": 1.0, "b": 0.5}, 2.0)
    assert stages == {"a": 1.0, "b": 0.5, "other": 0.5}
    assert with_remainder({"a": 1.0, "other": 0.25}, 1.5)["other"] == pytest.approx(0.5)
    assert with_remainder({"a": 3.0}, 2.0)["other"] == 0.0


class _Prior:
    name = "stub"

    def encode(self, view):
        return ("enc", view)

    def decode(self, enc_i, enc_j):
        return (enc_i, enc_j)

    def decode_pairs(self, pairs):
        return list(pairs)

    def decode_symmetric(self, pairs):
        return [(p, p[::-1]) for p in pairs]

    def retrieval_features(self, enc):
        return enc


def test_timed_prior_charges_the_prior_stages_and_passes_everything_else() -> None:
    timer = StageTimer()
    prior = TimedPrior(_Prior(), timer)
    enc = prior.encode("view")
    assert prior.decode(enc, enc) == (enc, enc)
    assert prior.decode_symmetric([(1, 2)]) == [((1, 2), (2, 1))]
    assert prior.decode_pairs([(1, 2), (3, 4)]) == [(1, 2), (3, 4)]
    assert prior.retrieval_features(enc) == enc
    assert prior.name == "stub"
    assert set(timer.seconds) == {"prior_encode", "prior_decode", "prior_retrieval"}


def test_timed_prior_counts_the_ordered_pairs_it_decodes() -> None:
    counted: list[int] = []
    prior = TimedPrior(_Prior(), StageTimer(), counted.append)
    prior.decode(1, 2)
    prior.decode_pairs([(1, 2), (3, 4), (5, 6)])
    prior.decode_symmetric([(1, 2), (3, 4)])
    prior.encode("view")
    assert counted == [1, 3, 4]
