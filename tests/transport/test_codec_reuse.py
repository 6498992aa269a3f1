"""A coded field's decoded map is taken again for the very value, unchanged, inside
``codec_reuse.reusing`` only (the session store's writes of what the ingest decoded)."""

from __future__ import annotations

import gc
import threading

import numpy as np
import torch

from como3r.frontend.pairs import DirectedMatches
from como3r.transport import codec_reuse
from como3r.transport.codec_arrays import Budget
from como3r.transport.codec_compact import coded_from_wire, coded_to_wire


def _decoded(coding: str, value: object) -> tuple[object, dict]:
    wire = coded_to_wire(coding, value)
    assert wire is not None
    return coded_from_wire(wire, "test", Budget(2**40)), wire


def _pointmap() -> torch.Tensor:
    gen = torch.Generator().manual_seed(0)
    return torch.rand(12, 16, 3, generator=gen) + torch.tensor([0.0, 0.0, 1.0])


def test_a_decoded_value_takes_its_map_inside_reusing_only() -> None:
    X, wire = _decoded("pointmap", _pointmap())
    assert coded_to_wire("pointmap", X) is not wire  # a message that leaves: coded afresh
    with codec_reuse.reusing() as reuse:
        assert coded_to_wire("pointmap", X) is wire
        assert coded_to_wire("confidence", X[..., 0]) is not wire  # another value
        assert coded_to_wire("pointmap", X) is not wire  # taken once: the taker keeps it
    assert (reuse.taken, reuse.coded, reuse.complete) == (1, 2, False)
    assert torch.equal(coded_from_wire(wire, "test", Budget(2**40)), X)


def test_a_value_changed_in_place_is_coded_afresh() -> None:
    X, wire = _decoded("pointmap", _pointmap())
    X[0, 0] *= 2  # through a view: the tensor's version counter moves too
    with codec_reuse.reusing() as reuse:
        again = coded_to_wire("pointmap", X)
    assert again is not wire and reuse.coded == 1 and not reuse.complete
    assert torch.equal(coded_from_wire(again, "test", Budget(2**40))[0, 0], X[0, 0])


def test_only_read_only_arrays_and_matches_of_unchanged_tensors_are_taken() -> None:
    image = np.random.default_rng(0).integers(0, 256, (12, 16, 3), dtype=np.uint8)
    decoded, wire = _decoded("image", image)
    assert isinstance(decoded, np.ndarray) and not decoded.flags.writeable
    gen = torch.Generator().manual_seed(1)
    n = 12 * 16
    matches = DirectedMatches(
        torch.randint(n, (n,), generator=gen), torch.rand(n, generator=gen) > 0.3, torch.rand(n)
    )
    got, matches_wire = _decoded("matches", matches)
    changed, changed_wire = _decoded("matches", matches)
    changed.q.mul_(2)
    writeable = decoded.copy()
    with codec_reuse.reusing() as reuse:
        assert coded_to_wire("image", decoded) is wire
        assert coded_to_wire("matches", got) is matches_wire
        assert coded_to_wire("inter_matches", got) is not matches_wire  # another coding
        assert coded_to_wire("image", writeable) is not wire  # writeable: never taken
        assert coded_to_wire("matches", changed) is not changed_wire
    assert (reuse.taken, reuse.coded) == (2, 3)


def test_a_value_no_longer_held_is_forgotten_and_unremembered_decodes_keep_nothing() -> None:
    X, wire = _decoded("pointmap", _pointmap())
    key = id(X)
    assert key in codec_reuse._DECODED
    del X
    gc.collect()
    assert key not in codec_reuse._DECODED
    with codec_reuse.unremembered():
        Y = coded_from_wire(wire, "test", Budget(2**40))
    assert id(Y) not in codec_reuse._DECODED


def test_an_inference_tensor_is_never_taken() -> None:
    with torch.inference_mode():
        X, wire = _decoded("pointmap", _pointmap())
    with codec_reuse.reusing() as reuse:
        assert coded_to_wire("pointmap", X) is not wire
    assert (reuse.taken, reuse.coded) == (0, 1)


def test_store_reads_keep_their_maps_only_while_the_value_read_is_held() -> None:
    """A paged keyframe's pointmap read back from the session store again and again (as
    its keyframe is paged in and out) leaves no map behind once the value read is gone:
    the maps held stay bounded by the values held (issue 41: the coordinator's memory)."""
    from como3r.store import coded

    gc.collect()
    before = len(codec_reuse._DECODED)
    X = _pointmap()
    blob, back = coded.pack_pointmap(X)
    assert back is not X  # not its own coding: the store wrote its coded value
    held = [coded.unpack_one(blob, "keyframe 0 X_hat") for _ in range(3)]
    assert len(codec_reuse._DECODED) == before + 3  # one map per value held
    for _ in range(50):
        coded.unpack_one(blob, "keyframe 0 X_hat")  # read and dropped
    del held
    gc.collect()
    assert len(codec_reuse._DECODED) == before


def test_a_value_decoded_on_another_thread_is_taken_on_this_one() -> None:
    """The pipes' readers decode (transport/pipe_readers.py) and the coordinator's thread
    takes: several decoding at once, every map is there for the very value."""
    decoded: list[tuple[object, dict]] = []

    def decode() -> None:
        for _ in range(20):
            decoded.append(_decoded("pointmap", _pointmap()))

    threads = [threading.Thread(target=decode) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert len(decoded) == 80
    assert all(codec_reuse.held("pointmap", X) for X, _ in decoded)
    with codec_reuse.reusing() as reuse:
        assert all(coded_to_wire("pointmap", X) is wire for X, wire in decoded)
    assert (reuse.taken, reuse.coded) == (80, 0)


def test_a_value_forgotten_inside_the_registrys_own_lock_does_not_deadlock() -> None:
    """A weak reference's callback runs on the thread that drops the value's last
    reference, which may hold the registry's lock already (a garbage collection started
    by an allocation under it): the lock is reentrant."""
    finished = threading.Event()

    def drop_under_the_lock() -> None:
        X, _ = _decoded("pointmap", _pointmap())
        with codec_reuse._LOCK:
            del X  # its callback forgets it here
        finished.set()

    thread = threading.Thread(target=drop_under_the_lock, daemon=True)
    thread.start()
    assert finished.wait(60.0), "deadlocked in the registry's lock"
