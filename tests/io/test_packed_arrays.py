"""The ``.c3z`` packed arrays (:mod:`como3r.io.packed_arrays`): bit-exact round trips, small
files for smooth maps, one clear error for a damaged file; old run folders' keyframe ``.npz``
and int32-agent ``map.ply`` read as the new ones."""

from __future__ import annotations

import numpy as np
import pytest

from como3r.errors import InputError
from como3r.io.keyframe_data import read_keyframe_data, write_keyframe_data
from como3r.io.packed_arrays import (
    predict_rows,
    read_packed,
    read_packed_header,
    unpredict_rows,
    write_packed,
)
from como3r.io.ply import read_ply, write_ply


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a).view(np.uint8)


def test_every_array_comes_back_bit_for_bit(tmp_path) -> None:
    rng = np.random.default_rng(0)
    odd = rng.standard_normal((7, 5, 3)).astype(np.float32) * 1e3
    odd[0, 0, 0], odd[1, 1, 1], odd[2, 2, 2], odd[3, 3, 0] = np.nan, -0.0, np.inf, 1e-42
    arrays = {
        "odd": odd,
        "plane": rng.standard_normal((4, 1)).astype(np.float32),
        "K": rng.standard_normal((3, 3)),
        "empty": np.zeros((0, 4), np.float32),
        "ids": np.arange(-3, 9, dtype=np.int16).reshape(3, 4),
        "mask": rng.random(10) > 0.5,
    }
    write_packed(tmp_path / "a.c3z", arrays)
    back = read_packed(tmp_path / "a.c3z")
    assert list(back) == list(arrays)
    for name, array in arrays.items():
        assert back[name].dtype == array.dtype and back[name].shape == array.shape, name
        assert np.array_equal(_bits(back[name]), _bits(array)), name
    header = read_packed_header(tmp_path / "a.c3z")
    assert header["odd"] == (np.dtype(np.float32), (7, 5, 3))


def test_the_prediction_inverts_exactly_and_a_smooth_map_packs_small(tmp_path) -> None:
    """A perspective plane's depth (smooth, as the renderer's) packs to under a tenth of its
    raw bytes; random bit patterns still come back exactly."""
    v, u = np.mgrid[0:120, 0:160].astype(np.float64)
    depth = (2.0 / (1.0 + 0.004 * (v - 60) + 0.001 * (u - 80))).astype(np.float32)
    noise = np.random.default_rng(1).integers(0, 2**32, (9, 11), dtype=np.uint64)
    noise = noise.astype(np.uint32).view(np.float32)
    for plane in (depth, noise):
        assert np.array_equal(_bits(unpredict_rows(predict_rows(plane))), _bits(plane))
    write_packed(tmp_path / "d.c3z", {"depth": depth})
    assert (tmp_path / "d.c3z").stat().st_size < depth.nbytes / 10


def test_a_damaged_file_is_one_input_error(tmp_path) -> None:
    path = tmp_path / "a.c3z"
    write_packed(path, {"X": np.ones((6, 8, 3), np.float32)})
    data = path.read_bytes()
    for name, damaged in (
        ("not", b"PK\x03\x04" + data[4:]),
        ("short", data[:-3]),
        ("long", data + b"\0"),
        ("header", data[:12] + b"[" + data[13:]),
    ):
        target = tmp_path / f"{name}.c3z"
        target.write_bytes(damaged)
        with pytest.raises(InputError, match=f"{name}.c3z"):
            read_packed(target)


class _Keyframe:
    def __init__(self, kf_id: int, rng: np.random.Generator) -> None:
        import torch

        self.kf_id = kf_id
        self.X_hat = torch.from_numpy(rng.standard_normal((6, 8, 3)).astype(np.float32))
        self.C = torch.from_numpy(rng.random((6, 8)).astype(np.float32))
        self.K = torch.eye(3, dtype=torch.float64) * 5.0 if kf_id else None
        self.colors = rng.integers(0, 255, (6, 8, 3), dtype=np.uint8)

    def mean_confidence(self):
        return self.C


class _Agent:
    agent = 0

    def __init__(self) -> None:
        rng = np.random.default_rng(2)
        self.keyframes = [_Keyframe(0, rng), _Keyframe(1, rng)]


def test_keyframe_data_of_old_run_folders_reads_as_the_new(tmp_path) -> None:
    """Keyframe data is written as .c3z; a run folder of before (.npz) reads the same."""
    agent = _Agent()
    write_keyframe_data(tmp_path / "new", [agent])
    folder = tmp_path / "new" / "keyframes" / "agent_0"
    assert sorted(p.name for p in folder.iterdir()) == [
        "000000.c3z",
        "000000.png",
        "000001.c3z",
        "000001.png",
    ]
    old = tmp_path / "old" / "keyframes" / "agent_0"
    old.mkdir(parents=True)
    for kf in agent.keyframes:
        arrays = {"X": kf.X_hat.numpy(), "C": kf.C.numpy()}
        if kf.K is not None:
            arrays["K"] = kf.K.numpy()
        np.savez(old / f"{kf.kf_id:06d}.npz", **arrays)
        (old / f"{kf.kf_id:06d}.png").write_bytes((folder / f"{kf.kf_id:06d}.png").read_bytes())
    for kf in agent.keyframes:
        new, before = (read_keyframe_data(tmp_path / r, 0, kf.kf_id) for r in ("new", "old"))
        assert np.array_equal(new.X, before.X) and np.array_equal(new.C, before.C)
        assert (new.K is None) == (before.K is None) == (kf.K is None)
        assert new.K is None or np.array_equal(new.K, before.K)
        assert np.array_equal(new.X, kf.X_hat.numpy())


def test_a_map_of_before_with_int32_agent_ids_reads_as_the_new(tmp_path) -> None:
    rng = np.random.default_rng(3)
    xyz = rng.standard_normal((50, 3)).astype(np.float32)
    rgb = rng.integers(0, 255, (50, 3), dtype=np.uint8)
    agent_id = rng.integers(0, 16, 50).astype(np.int32)
    write_ply(tmp_path / "new.ply", xyz, rgb, agent_id)
    new = read_ply(tmp_path / "new.ply")
    # the layout of before: the same header with "property int agent_id", 19 bytes a point
    old_dtype = np.dtype([*((n, new.dtype.fields[n][0]) for n in "x y z red green blue".split())])
    old_dtype = np.dtype(
        [*((n, old_dtype.fields[n][0]) for n in old_dtype.names), ("agent_id", "<i4")]
    )
    vertices = np.empty(50, old_dtype)
    for name in new.dtype.names:
        vertices[name] = new[name]
    data = (tmp_path / "new.ply").read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].replace(b"property ushort agent_id", b"property int agent_id")
    (tmp_path / "old.ply").write_bytes(header + vertices.tobytes())
    assert len(data) - end == 50 * 17
    old = read_ply(tmp_path / "old.ply")
    assert old.dtype == new.dtype and np.array_equal(old, new)
    assert np.array_equal(new["agent_id"], agent_id)
    with pytest.raises(ValueError, match="agent ids"):
        write_ply(tmp_path / "bad.ply", xyz[:1], rgb[:1], np.array([70000]))
