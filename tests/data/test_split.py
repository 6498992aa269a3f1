"""Tests of como3r.data.split: the C-Sec. B.4 / C.4 overlapping sub-sequence protocol."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from como3r.data.agent import open_agent
from como3r.data.odometry_declaration import (
    ODOMETRY_KIND_FILE,
    OdometryKind,
    read_odometry_kind,
    write_odometry_kind,
)
from como3r.data.split import MIN_FRAMES_PER_AGENT, chunk_length, chunk_ranges, split_sequence
from como3r.errors import InputError

from .readers.layouts import write_euroc
from .test_agent import frame_pixels, write_agent, write_video


@pytest.mark.parametrize("frames", [10, 37, 100, 1001])
@pytest.mark.parametrize("agents", [1, 2, 3, 4])
@pytest.mark.parametrize("overlap", [0.0, 0.1, 0.25, 0.5])
def test_chunk_ranges_cover_with_the_requested_overlap(frames, agents, overlap):
    ranges = chunk_ranges(frames, agents, overlap)
    assert len(ranges) == agents
    assert ranges[0][0] == 0 and ranges[-1][1] == frames
    lengths = [stop - start for start, stop in ranges]
    assert max(lengths) - min(lengths) <= 1
    ideal = chunk_length(frames, agents, overlap)
    assert ideal + (agents - 1) * ideal * (1 - overlap) == pytest.approx(frames)
    assert all(abs(length - ideal) <= 1 for length in lengths)
    for (start, stop), (next_start, next_stop) in zip(ranges, ranges[1:]):
        assert start < next_start and stop < next_stop  # contiguous, in order
        shared = stop - next_start
        assert shared >= 0  # no gap
        assert abs(shared - overlap * ideal) <= 1
        if overlap == 0.0:
            assert shared == 0


@pytest.mark.parametrize("agents", [2, 3, 5])
def test_chunks_are_long_enough_whenever_the_ideal_length_is(agents):
    for frames in range(2, 40):
        for overlap in (0.0, 0.1, 0.3, 0.6, 0.9):
            if chunk_length(frames, agents, overlap) >= MIN_FRAMES_PER_AGENT:
                lengths = [b - a for a, b in chunk_ranges(frames, agents, overlap)]
                assert min(lengths) >= MIN_FRAMES_PER_AGENT


def test_split_images_with_every_side_file(tmp_path):
    stamps = [0.1 * i for i in range(20)]
    src = write_agent(
        tmp_path / "seq",
        n=20,
        depth="png",
        surface=True,
        calib="500 500 16 12\n",
        timestamps=stamps,
        groundtruth=True,
        odometry=True,
    )
    source = open_agent(src)
    folders = split_sequence(src, tmp_path / "out", agents=3, overlap=0.2)
    assert folders == [tmp_path / "out" / f"agent_{a}" for a in range(3)]
    expected = chunk_ranges(20, 3, 0.2)
    covered = set()
    for folder, (start, stop) in zip(folders, expected):
        agent = open_agent(folder)
        assert agent.num_frames == stop - start
        assert agent.stems == source.stems[start:stop]
        np.testing.assert_array_equal(agent.timestamps, source.timestamps[start:stop])
        assert agent.has_depth and agent.has_surface and agent.calib == source.calib
        # Hard links (or copies) of the same files: identical content.
        first = folder / "rgb" / f"{agent.stems[0]}.png"
        assert first.read_bytes() == source.image_paths[start].read_bytes()
        for k, frame in enumerate(agent):
            i = start + k
            original = source.load_frame(i)
            np.testing.assert_array_equal(frame.image, frame_pixels(i))
            np.testing.assert_array_equal(frame.depth, original.depth)
            np.testing.assert_array_equal(frame.surface, original.surface)
            torch.testing.assert_close(frame.T_WC_gt, original.T_WC_gt, atol=1e-8, rtol=0)
            covered.add(i)
        assert len(agent.odometry) == stop - start
    assert covered == set(range(20))
    shared = set(open_agent(folders[0]).stems) & set(open_agent(folders[1]).stems)
    assert len(shared) == expected[0][1] - expected[1][0] > 0


def test_split_with_stride(tmp_path):
    src = write_agent(tmp_path / "seq", n=13)
    folders = split_sequence(src, tmp_path / "out", agents=2, overlap=0.0, stride=3)
    kept = [f"{i:04d}" for i in range(0, 13, 3)]  # 0, 3, 6, 9, 12
    stems = [open_agent(f).stems for f in folders]
    assert list(stems[0] + stems[1]) == kept


@pytest.mark.parametrize(
    "declared, later",
    [
        # a VIO's later pieces start converged: no start discount, the rest as declared
        (OdometryKind("vio"), OdometryKind("vio", start_scale_error=0.0)),
        (
            OdometryKind("vio", start_scale_error=0.2, start_depths=0.5),
            OdometryKind("vio", start_scale_error=0.0, start_depths=0.5),
        ),
        (OdometryKind("metric"), OdometryKind("metric")),
    ],
)
def test_split_hands_each_piece_its_odometry_declaration(tmp_path, declared, later):
    src = write_agent(tmp_path / "seq", n=12, odometry=True)
    write_odometry_kind(src, declared)
    folders = split_sequence(src, tmp_path / "out", agents=3, overlap=0.1)
    assert [read_odometry_kind(f) for f in folders] == [declared, later, later]


def test_split_of_an_undeclared_source_declares_nothing(tmp_path):
    src = write_agent(tmp_path / "seq", n=6, odometry=True)
    folders = split_sequence(src, tmp_path / "out", agents=2, overlap=0.0)
    assert not any((f / ODOMETRY_KIND_FILE).exists() for f in folders)


def test_split_of_a_bad_declaration_writes_nothing(tmp_path):
    src = write_agent(tmp_path / "seq", n=6, odometry=True)
    (src / ODOMETRY_KIND_FILE).write_text('{"kind": "lio"}')
    with pytest.raises(InputError, match=ODOMETRY_KIND_FILE):
        split_sequence(src, tmp_path / "out", agents=2, overlap=0.0)
    assert not (tmp_path / "out").exists()


def test_split_video(tmp_path):
    (tmp_path / "cam").mkdir()
    levels = write_video(tmp_path / "cam" / "clip.avi", n=6, fps=10.0)
    folders = split_sequence(tmp_path / "cam", tmp_path / "out", agents=2, overlap=0.4)
    (a0, b0), (a1, b1) = chunk_ranges(6, 2, 0.4)
    for folder, (start, stop) in zip(folders, [(a0, b0), (a1, b1)]):
        agent = open_agent(folder)
        np.testing.assert_allclose(agent.timestamps, np.arange(start, stop) / 10.0)
        for frame, level in zip(agent, levels[start:stop]):
            assert abs(float(frame.image.mean()) - level) < 3


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"agents": 0}, "agents"),
        ({"agents": 2.0}, "agents"),
        ({"overlap": 1.0}, "overlap"),
        ({"overlap": -0.1}, "overlap"),
        ({"stride": 0}, "stride"),
        ({"agents": 4}, "too few"),
        ({"agents": 2, "stride": 5}, "too few"),
    ],
)
def test_split_rejects_bad_arguments(tmp_path, kwargs, match):
    src = write_agent(tmp_path / "seq", n=6)
    args = {"agents": 2, "overlap": 0.1, "stride": 1} | kwargs
    with pytest.raises(InputError, match=match):
        split_sequence(src, tmp_path / "out", **args)
    assert not (tmp_path / "out").exists()


def test_split_refuses_to_overwrite(tmp_path):
    src = write_agent(tmp_path / "seq", n=6)
    split_sequence(src, tmp_path / "out", agents=2, overlap=0.0)
    with pytest.raises(InputError, match="agent_0"):
        split_sequence(src, tmp_path / "out", agents=2, overlap=0.0)


def test_split_of_a_missing_source(tmp_path):
    with pytest.raises(InputError, match="nowhere"):
        split_sequence(tmp_path / "nowhere", tmp_path / "out", agents=2, overlap=0.1)


def test_split_of_a_distorted_sequence_writes_the_undistorted_frames(tmp_path):
    # EuRoC frames are undistorted as they are read: linking the raw files would pair
    # distorted images with the calib.txt of the undistorted camera
    write_euroc(tmp_path / "seq", n=6, distortion=(-0.3, 0.08, 0.001, -0.001))
    source = open_agent(tmp_path / "seq")
    assert not source.frames_are_files
    folders = split_sequence(tmp_path / "seq", tmp_path / "out", agents=2, overlap=0.0)
    for folder, (start, _stop) in zip(folders, chunk_ranges(6, 2, 0.0)):
        agent = open_agent(folder)
        assert agent.calib == source.calib
        for k, frame in enumerate(agent):
            undistorted = source.load_frame(start + k).image
            np.testing.assert_array_equal(frame.image, undistorted)
            raw = np.asarray(Image.open(source.image_paths[start + k]).convert("RGB"))
            assert np.abs(raw.astype(int) - undistorted).max() > 0


def test_split_links_the_files_of_an_undistorted_sequence(tmp_path):
    write_euroc(tmp_path / "seq", n=4)
    source = open_agent(tmp_path / "seq")
    assert source.frames_are_files
    folders = split_sequence(tmp_path / "seq", tmp_path / "out", agents=2, overlap=0.0)
    first = open_agent(folders[0]).image_paths[0]
    assert first.read_bytes() == source.image_paths[0].read_bytes()
