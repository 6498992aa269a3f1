"""Tests of opening agent inputs (como3r.data.agent): discovery, parsing and validation of the
agent layout (data/readers/agent, data/input_files) and frame loading (data/agent_input)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from PIL import Image

from como3r.data.agent import open_agent
from como3r.data.agent_input import DEPTH_PNG_PER_METRE, load_float_map
from como3r.data.input_files import associate_timestamps, check_map_header
from como3r.errors import InputError
from como3r.io.packed_arrays import write_packed
from como3r.io.tum import write_tum

WIDTH, HEIGHT = 32, 24


def frame_pixels(i: int, width: int = WIDTH, height: int = HEIGHT) -> np.ndarray:
    """A distinct deterministic ``(H, W, 3)`` uint8 image per index."""
    rng = np.random.default_rng(i)
    return rng.integers(0, 256, size=(height, width, 3), dtype=np.uint8)


def poses(n: int, seed: int = 0) -> torch.Tensor:
    """``(n, 8)`` float64 random poses with unit quaternions and s = 1."""
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return torch.from_numpy(np.concatenate([rng.normal(size=(n, 3)), q, np.ones((n, 1))], 1))


def write_agent(
    root: Path,
    n: int = 6,
    *,
    stems: list[str] | None = None,
    depth: str | None = None,
    surface: bool = False,
    calib: str | None = None,
    timestamps: list[float] | None = None,
    groundtruth: bool = False,
    odometry: bool = False,
) -> Path:
    """Write a small agent folder: ``rgb/`` plus the requested side files.

    Depth of frame i is ``1 + i + 0.01 * u`` metres (u the column); surface keys are
    ``(i, u, v)``; ground truth / odometry hold one pose per frame at the frame timestamps.
    """
    stems = stems or [f"{i:04d}" for i in range(n)]
    (root / "rgb").mkdir(parents=True)
    for i, stem in enumerate(stems):
        Image.fromarray(frame_pixels(i)).save(root / "rgb" / f"{stem}.png")
    u, v = np.meshgrid(np.arange(WIDTH), np.arange(HEIGHT))
    if depth is not None:
        (root / "depth").mkdir()
        for i, stem in enumerate(stems):
            metres = (1.0 + i + 0.01 * u).astype(np.float32)
            if depth == "png":
                units = np.round(metres * DEPTH_PNG_PER_METRE).astype(np.uint16)
                Image.fromarray(units).save(root / "depth" / f"{stem}.png")
            else:
                np.save(root / "depth" / f"{stem}.npy", metres)
    if surface:
        (root / "surface").mkdir()
        for i, stem in enumerate(stems):
            keys = np.stack([np.full_like(u, i), u, v], -1).astype(np.float32)
            np.save(root / "surface" / f"{stem}.npy", keys)
    if calib is not None:
        (root / "calib.txt").write_text(calib)
    stamps = np.asarray(timestamps if timestamps is not None else np.arange(n) / 30.0)
    if timestamps is not None:
        (root / "timestamps.txt").write_text("".join(f"{t!r}\n" for t in timestamps))
    if groundtruth:
        write_tum(root / "groundtruth.txt", stamps, poses(n, seed=1))
    if odometry:
        write_tum(root / "odometry.txt", stamps, poses(n, seed=2))
    return root


def write_video(path: Path, n: int = 5, fps: float = 10.0) -> list[int]:
    """An MJPG video of flat grey frames; returns each frame's grey level."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (WIDTH, HEIGHT))
    assert writer.isOpened()
    levels = [20 + 40 * i for i in range(n)]
    for level in levels:
        writer.write(np.full((HEIGHT, WIDTH, 3), level, np.uint8))
    writer.release()
    return levels


def assert_input_error(match: str, func, *args) -> None:
    with pytest.raises(InputError) as info:
        func(*args)
    message = str(info.value)
    assert match in message, message
    assert "\n" not in message


# ---------------------------------------------------------------------------------- images


def test_image_folder_defaults(tmp_path):
    agent = open_agent(write_agent(tmp_path / "seq", n=6), fps=20.0)
    assert agent.name == "seq"
    assert agent.num_frames == len(agent) == 6
    assert agent.image_size == (WIDTH, HEIGHT)
    np.testing.assert_allclose(agent.timestamps, np.arange(6) / 20.0)
    assert agent.timestamps.dtype == np.float64
    assert agent.calib is None and agent.groundtruth is None and agent.odometry is None
    assert not agent.has_depth and not agent.has_surface
    frames = list(agent)
    assert [f.index for f in frames] == list(range(6))
    for i, frame in enumerate(frames):
        assert frame.image.dtype == np.uint8 and frame.image.shape == (HEIGHT, WIDTH, 3)
        np.testing.assert_array_equal(frame.image, frame_pixels(i))
        assert frame.depth is None and frame.surface is None and frame.T_WC_gt is None
    np.testing.assert_array_equal(agent.load_frame(3).image, frame_pixels(3))


def test_images_sorted_by_name_and_other_formats(tmp_path):
    rgb = tmp_path / "a" / "rgb"
    rgb.mkdir(parents=True)
    Image.fromarray(frame_pixels(0)).save(rgb / "b.bmp")
    Image.fromarray(frame_pixels(1)).save(rgb / "a.jpg", quality=95)
    Image.fromarray(frame_pixels(2).mean(-1).astype(np.uint8)).save(rgb / "c.png")  # grey
    (rgb / "notes.txt").write_text("not an image")
    agent = open_agent(tmp_path / "a")
    assert agent.stems == ("a", "b", "c")
    np.testing.assert_array_equal(agent.load_frame(1).image, frame_pixels(0))
    grey = agent.load_frame(2).image
    assert grey.shape == (HEIGHT, WIDTH, 3)
    np.testing.assert_array_equal(grey[..., 0], grey[..., 2])


def test_timestamps_one_per_line(tmp_path):
    stamps = [10.0, 10.5, 10.75, 11.0]
    agent = open_agent(write_agent(tmp_path / "a", n=4, timestamps=stamps))
    np.testing.assert_array_equal(agent.timestamps, stamps)
    assert [f.timestamp for f in agent] == stamps


def test_timestamps_tum_style_pair_by_stem(tmp_path):
    stems = ["1305031102.175304", "1305031102.211214", "1305031102.243211"]
    root = write_agent(tmp_path / "a", n=3, stems=stems)
    lines = ["# color images", "# file: 'rgbd_dataset_freiburg1_xyz.bag'", "# timestamp filename"]
    lines += [f"{s} rgb/{s}.png" for s in reversed(stems)]  # listed out of order on purpose
    (root / "timestamps.txt").write_text("\n".join(lines) + "\n")
    agent = open_agent(root)
    np.testing.assert_array_equal(agent.timestamps, [float(s) for s in stems])


def test_calib(tmp_path):
    agent = open_agent(write_agent(tmp_path / "a", calib="# fx fy cx cy\n500 510.5 15.5 11.5\n"))
    assert agent.calib == (500.0, 510.5, 15.5, 11.5)


@pytest.mark.parametrize("kind", ["png", "npy"])
def test_depth_metres(tmp_path, kind):
    agent = open_agent(write_agent(tmp_path / "a", n=3, depth=kind))
    assert agent.has_depth
    u = np.arange(WIDTH)[None, :]
    for i, frame in enumerate(agent):
        assert frame.depth.dtype == np.float32 and frame.depth.shape == (HEIGHT, WIDTH)
        # A 16-bit PNG holds 5000 units per metre: 0.2 mm resolution.
        expected = np.broadcast_to(1.0 + i + 0.01 * u, (HEIGHT, WIDTH))
        np.testing.assert_allclose(frame.depth, expected, atol=1.1e-4)


def test_depth_npy_non_finite_is_invalid(tmp_path):
    root = write_agent(tmp_path / "a", n=2, depth="npy")
    depth = np.ones((HEIGHT, WIDTH), np.float32)
    depth[0, 0], depth[1, 1] = np.nan, np.inf
    np.save(root / "depth" / "0001.npy", depth)
    frame = open_agent(root).load_frame(1)
    assert frame.depth[0, 0] == 0 and frame.depth[1, 1] == 0 and frame.depth[2, 2] == 1


def test_surface(tmp_path):
    frame = open_agent(write_agent(tmp_path / "a", n=3, surface=True)).load_frame(2)
    assert frame.surface.dtype == np.float32 and frame.surface.shape == (HEIGHT, WIDTH, 3)
    assert np.all(frame.surface[..., 0] == 2)
    assert frame.surface[5, 7, 1] == 7 and frame.surface[5, 7, 2] == 5


def test_groundtruth_and_odometry_association(tmp_path):
    stamps = [0.0, 0.1, 0.2, 0.3, 0.4, 0.5]
    root = write_agent(tmp_path / "a", n=6, odometry=True, timestamps=stamps)
    # GT poses at frames 0 and 5, and around frame 2 (54 ms apart: bridged); frames 1, 3
    # and 4 lie in gaps wider than 0.1 s.
    gt_stamps = np.array([0.0, 0.15, 0.204, 0.5])
    gt = poses(4, seed=3)
    write_tum(root / "groundtruth.txt", gt_stamps, gt)
    agent = open_agent(root, fps=100.0)
    assert len(agent.odometry) == 6 and len(agent.groundtruth) == 4
    frames = list(agent)
    assert [f.T_WC_gt is not None for f in frames] == [True, False, True, False, False, True]
    alpha = (0.2 - 0.15) / (0.204 - 0.15)
    torch.testing.assert_close(
        frames[2].T_WC_gt[:3], (1 - alpha) * gt[1, :3] + alpha * gt[2, :3], atol=1e-6, rtol=0
    )
    assert frames[2].T_WC_gt.shape == (8,) and frames[2].T_WC_gt.dtype == torch.float64
    torch.testing.assert_close(frames[5].T_WC_gt, gt[3], atol=1e-6, rtol=0)
    indices, trajectory = agent.gt_for_frames()
    np.testing.assert_array_equal(indices, [0, 2, 5])
    np.testing.assert_allclose(trajectory.timestamps, [0.0, 0.2, 0.5])
    torch.testing.assert_close(trajectory.T_WC[[0, 2]], gt[[0, 3]], atol=1e-6, rtol=0)
    assert agent.missing_gt_warning().endswith(
        "3 of 6 frames have no ground-truth pose (3 in gaps wider than 0.1 s)"
    )


def test_associate_timestamps_nearest_within_tolerance():
    reference = np.array([1.0, 2.0, 3.0])
    stamps = np.array([0.5, 0.96, 1.49, 1.51, 2.97, 3.2])
    assert associate_timestamps(stamps, reference, 0.05).tolist() == [-1, 0, -1, -1, 2, -1]
    assert associate_timestamps(stamps, reference, 0.6).tolist() == [0, 0, 0, 1, 2, 2]
    assert associate_timestamps(stamps, np.array([1.0]), 0.5).tolist() == [0, 0, 0, -1, -1, -1]


def test_no_groundtruth_gives_empty_association(tmp_path):
    indices, trajectory = open_agent(write_agent(tmp_path / "a")).gt_for_frames()
    assert indices.size == 0 and len(trajectory) == 0 and trajectory.T_WC.shape == (0, 8)


# ---------------------------------------------------------------------------------- videos


@pytest.mark.parametrize("as_file", [True, False])
def test_video_input(tmp_path, as_file):
    folder = tmp_path / "cam"
    folder.mkdir()
    levels = write_video(folder / "clip.avi", n=5, fps=10.0)
    write_tum(folder / "groundtruth.txt", np.arange(5) / 10.0, poses(5))
    agent = open_agent(folder / "clip.avi" if as_file else folder)
    assert agent.name == ("clip" if as_file else "cam")
    assert agent.num_frames == 5 and agent.image_size == (WIDTH, HEIGHT)
    np.testing.assert_allclose(agent.timestamps, np.arange(5) / 10.0)  # container rate
    assert agent.stems == tuple(f"{i:06d}" for i in range(5))
    frames = list(agent.frames())
    assert len(frames) == 5
    for frame, level in zip(frames, levels):
        assert frame.image.shape == (HEIGHT, WIDTH, 3) and frame.image.dtype == np.uint8
        assert abs(float(frame.image.mean()) - level) < 3  # MJPG is lossy
        assert frame.T_WC_gt is not None
    np.testing.assert_array_equal(agent.load_frame(3).image, frames[3].image)


def test_video_with_timestamps_file(tmp_path):
    folder = tmp_path / "cam"
    folder.mkdir()
    write_video(folder / "clip.avi", n=4)
    (folder / "timestamps.txt").write_text("5.0\n5.2\n5.3\n5.9\n")
    np.testing.assert_array_equal(open_agent(folder).timestamps, [5.0, 5.2, 5.3, 5.9])


def test_rgb_folder_takes_precedence_over_video(tmp_path):
    root = write_agent(tmp_path / "a", n=3)
    write_video(root / "clip.avi", n=5)
    agent = open_agent(root)
    assert agent.video is None and agent.num_frames == 3


# ---------------------------------------------------------------------------------- bad inputs


def test_missing_folder(tmp_path):
    assert_input_error("nowhere", open_agent, tmp_path / "nowhere")


def test_empty_folder(tmp_path):
    (tmp_path / "empty").mkdir()
    assert_input_error("empty", open_agent, tmp_path / "empty")


def test_rgb_without_images(tmp_path):
    (tmp_path / "a" / "rgb").mkdir(parents=True)
    (tmp_path / "a" / "rgb" / "readme.txt").write_text("x")
    assert_input_error("rgb", open_agent, tmp_path / "a")


def test_corrupt_image_header(tmp_path):
    root = write_agent(tmp_path / "a", n=3)
    (root / "rgb" / "0001.png").write_bytes(b"this is not a png")
    assert_input_error("0001.png", open_agent, root)


def test_truncated_image_fails_on_load(tmp_path):
    root = write_agent(tmp_path / "a", n=3)
    data = (root / "rgb" / "0002.png").read_bytes()
    (root / "rgb" / "0002.png").write_bytes(data[: len(data) // 2])
    agent = open_agent(root)  # the header is intact
    agent.load_frame(1)
    assert_input_error("0002.png", agent.load_frame, 2)
    with pytest.raises(InputError, match="0002.png"):
        list(agent)


def test_images_of_different_sizes(tmp_path):
    root = write_agent(tmp_path / "a", n=3)
    Image.fromarray(frame_pixels(9, width=20)).save(root / "rgb" / "0001.png")
    assert_input_error("0001.png", open_agent, root)


def test_duplicate_image_stems(tmp_path):
    root = write_agent(tmp_path / "a", n=3)
    Image.fromarray(frame_pixels(0)).save(root / "rgb" / "0001.jpg")
    assert_input_error("0001", open_agent, root)


def test_timestamps_count_mismatch(tmp_path):
    root = write_agent(tmp_path / "a", n=4)
    (root / "timestamps.txt").write_text("0.0\n0.1\n0.2\n")
    assert_input_error("timestamps.txt", open_agent, root)


@pytest.mark.parametrize(
    "text",
    [
        "0.0\n0.1\n0.1\n0.3\n",
        "0.0\n0.2\n0.1\n0.3\n",
        "0.0\nabc\n0.2\n0.3\n",
        "0 a b\n1\n2\n3\n",
        "0.0\n0.1 rgb/0001.png\n0.2\n0.3\n",
        "0.0\nnan\n0.2\n0.3\n",
    ],
    ids=["repeated", "decreasing", "not-a-number", "three-fields", "mixed", "nan"],
)
def test_bad_timestamps(tmp_path, text):
    root = write_agent(tmp_path / "a", n=4)
    (root / "timestamps.txt").write_text(text)
    assert_input_error("timestamps.txt", open_agent, root)


def test_tum_timestamps_missing_an_image(tmp_path):
    root = write_agent(tmp_path / "a", n=3)
    (root / "timestamps.txt").write_text("1 rgb/0000.png\n2 rgb/0001.png\n3 rgb/9999.png\n")
    assert_input_error("0002", open_agent, root)


@pytest.mark.parametrize(
    "text",
    [
        "500 500 16\n",
        "500 500 16 12 0.1\n",
        "500 x 16 12\n",
        "-500 500 16 12\n",
        "500 0 16 12\n",
        "500 500 nan 12\n",
        "500 500 16 12\n500 500 16 12\n",
        "",
    ],
    ids=["three", "five", "word", "negative-fx", "zero-fy", "nan", "two-lines", "empty"],
)
def test_bad_calib(tmp_path, text):
    root = write_agent(tmp_path / "a", calib=text)
    assert_input_error("calib.txt", open_agent, root)


@pytest.mark.parametrize("name", ["groundtruth.txt", "odometry.txt"])
def test_bad_trajectory_line(tmp_path, name):
    root = write_agent(tmp_path / "a")
    (root / name).write_text("0.0 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 1\n")
    assert_input_error(f"{name}:2", open_agent, root)


@pytest.mark.parametrize("kind", ["png", "npy"])
def test_depth_missing_for_a_stem(tmp_path, kind):
    root = write_agent(tmp_path / "a", n=3, depth=kind)
    (root / "depth" / f"0001.{kind}").unlink()
    assert_input_error("0001", open_agent, root)


def test_depth_png_wrong_size(tmp_path):
    root = write_agent(tmp_path / "a", n=3, depth="png")
    Image.fromarray(np.zeros((HEIGHT, WIDTH - 1), np.uint16)).save(root / "depth" / "0002.png")
    assert_input_error("0002.png", open_agent, root)


def test_depth_png_not_16_bit(tmp_path):
    root = write_agent(tmp_path / "a", n=3, depth="png")
    Image.fromarray(frame_pixels(0)).save(root / "depth" / "0002.png")
    assert_input_error("0002.png", open_agent, root)


def test_depth_npy_wrong_shape(tmp_path):
    root = write_agent(tmp_path / "a", n=3, depth="npy")
    np.save(root / "depth" / "0000.npy", np.ones((WIDTH, HEIGHT), np.float32))
    assert_input_error("0000.npy", open_agent, root)


def test_depth_npy_negative_fails_on_load(tmp_path):
    root = write_agent(tmp_path / "a", n=3, depth="npy")
    np.save(root / "depth" / "0001.npy", -np.ones((HEIGHT, WIDTH), np.float32))
    assert_input_error("0001.npy", open_agent(root).load_frame, 1)


def test_corrupt_npy(tmp_path):
    root = write_agent(tmp_path / "a", n=3, surface=True)
    (root / "surface" / "0001.npy").write_bytes(b"garbage")
    assert_input_error("0001.npy", open_agent, root)


@pytest.mark.parametrize("shape", [(HEIGHT, WIDTH), (HEIGHT, WIDTH, 2), (HEIGHT + 1, WIDTH, 3)])
def test_surface_wrong_shape(tmp_path, shape):
    root = write_agent(tmp_path / "a", n=3, surface=True)
    np.save(root / "surface" / "0002.npy", np.zeros(shape, np.float32))
    assert_input_error("0002.npy", open_agent, root)


def test_surface_missing_for_a_stem(tmp_path):
    root = write_agent(tmp_path / "a", n=3, surface=True)
    (root / "surface" / "0000.npy").unlink()
    assert_input_error("0000", open_agent, root)


def test_video_that_cannot_be_opened(tmp_path):
    (tmp_path / "cam").mkdir()
    (tmp_path / "cam" / "clip.mp4").write_bytes(b"\x00" * 100)
    assert_input_error("clip.mp4", open_agent, tmp_path / "cam")
    assert_input_error("clip.mp4", open_agent, tmp_path / "cam" / "clip.mp4")


def test_folder_with_two_videos(tmp_path):
    (tmp_path / "cam").mkdir()
    write_video(tmp_path / "cam" / "one.avi")
    write_video(tmp_path / "cam" / "two.avi")
    assert_input_error("two.avi", open_agent, tmp_path / "cam")


def test_file_that_is_not_a_video(tmp_path):
    (tmp_path / "frame.png").write_bytes(b"x")
    assert_input_error("frame.png", open_agent, tmp_path / "frame.png")


@pytest.mark.parametrize(
    "stems, expected",
    [
        (
            ["1305031102.175304", "1305031102.211214", "1305031102.243211"],
            [1305031102.175304, 1305031102.211214, 1305031102.243211],
        ),
        (
            ["1403636579763555584", "1403636579813555456", "1403636579863555584"],
            [1403636579.763555584, 1403636579.813555456, 1403636579.863555584],
        ),
    ],
)
def test_images_named_by_timestamp_give_the_timestamps(tmp_path, stems, expected):
    agent = open_agent(write_agent(tmp_path / "a", n=3, stems=stems))
    np.testing.assert_allclose(agent.timestamps, expected, rtol=0, atol=1e-6)


@pytest.mark.parametrize(
    "stems",
    [["000001", "000002", "000003"], ["1", "2", "3"], ["1305031102.1", "frame", "1305031102.3"]],
)
def test_frame_numbers_are_not_timestamps(tmp_path, stems):
    agent = open_agent(write_agent(tmp_path / "a", n=3, stems=stems), fps=10.0)
    np.testing.assert_allclose(agent.timestamps, [0.0, 0.1, 0.2])


def test_timestamp_names_out_of_time_order_are_refused(tmp_path):
    # 999999999.5 sorts after 1000000000.0 by name but is earlier
    folder = write_agent(tmp_path / "a", n=2, stems=["999999999.5", "1000000000.0"])
    with pytest.raises(InputError, match="do not sort in time"):
        open_agent(folder)


def test_timestamp_names_of_one_instant_are_refused(tmp_path):
    folder = write_agent(tmp_path / "a", n=2, stems=["1305031102.1", "1305031102.10"])
    with pytest.raises(InputError, match="name the same instant"):
        open_agent(folder)


def test_a_packed_map_without_the_array_asked_for_is_named(tmp_path) -> None:
    """A ``.c3z`` depth file holding other arrays: the header check and the reader both say
    which arrays it holds."""
    path = tmp_path / "000000.c3z"
    write_packed(path, {"surface": np.ones((4, 6, 3), np.float32)})
    message = rf"{path.name}: holds no 'depth' array \(it holds surface\)"
    with pytest.raises(InputError, match=message):
        check_map_header(path, (6, 4), "depth")
    with pytest.raises(InputError, match=message):
        load_float_map(path, "depth")
