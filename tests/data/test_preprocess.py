"""Tests of como3r.data.preprocess against MAST3R_SPEC.md §2.1-2.2 (hand-computed sizes)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from PIL import Image

from como3r.data.agent_input import Frame
from como3r.data.preprocess import (
    ImageTransform,
    compute_transform,
    frame_ground_truth,
    make_view,
    resize_crop,
)
from como3r.errors import InputError


def random_image(width: int, height: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (height, width, 3), dtype=np.uint8)


def blob_image(width: int, height: int, u: float, v: float, sigma: float) -> np.ndarray:
    """A grey Gaussian blob centred on the sub-pixel location (u, v) (pixel centres at integers)."""
    x, y = np.meshgrid(np.arange(width), np.arange(height))
    g = 255.0 * np.exp(-((x - u) ** 2 + (y - v) ** 2) / (2.0 * sigma**2))
    return np.repeat(np.round(g).astype(np.uint8)[..., None], 3, axis=-1)


def centroid(image: np.ndarray) -> tuple[float, float]:
    weight = image[..., 0].astype(np.float64)
    y, x = np.mgrid[: weight.shape[0], : weight.shape[1]]
    return float((weight * x).sum() / weight.sum()), float((weight * y).sum() / weight.sum())


# Hand-computed from the spec: resize = round(side * 512 / long side); crop to
# halfw = ((2 * (W // 2)) // 16) * 8; a square becomes 512x384.
@pytest.mark.parametrize(
    "size, resized, output",
    [
        ((640, 480), (512, 384), (512, 384)),
        ((1280, 720), (512, 288), (512, 288)),
        ((1920, 1080), (512, 288), (512, 288)),
        ((752, 480), (512, 327), (512, 320)),  # EuRoC row of the spec's table
        ((512, 512), (512, 512), (512, 384)),
        ((1000, 1000), (512, 512), (512, 384)),
        ((480, 640), (384, 512), (384, 512)),  # portrait stays portrait
        ((1080, 1920), (288, 512), (288, 512)),
        ((32, 24), (512, 384), (512, 384)),  # enlarged
        ((1241, 376), (512, 155), (512, 144)),  # KITTI-like: 376 * 512 / 1241 = 155.1
    ],
)
def test_sizes_follow_the_spec(size, resized, output):
    transform = compute_transform(*size)
    assert transform.resized == resized and transform.output == output
    assert transform.original == size
    assert transform.scale_w == size[0] / resized[0] and transform.scale_h == size[1] / resized[1]
    assert transform.half_crop_w == (resized[0] - output[0]) / 2
    assert transform.half_crop_h == (resized[1] - output[1]) / 2
    image, same = resize_crop(random_image(*size))
    assert same == transform
    assert image.shape == (output[1], output[0], 3) and image.dtype == np.uint8


def test_odd_crop_offset_is_integer_division():
    # 752x480 -> 512x327: cy = 163, halfh = 160, rows 3..322 are kept (not 3.5).
    transform = compute_transform(752, 480)
    assert (transform.crop_left, transform.crop_top) == (0, 3)
    assert transform.half_crop_h == 3.5


def test_square_ok_keeps_squares():
    assert compute_transform(1000, 1000, square_ok=True).output == (512, 512)
    assert compute_transform(640, 480, square_ok=True).output == (512, 384)


@pytest.mark.parametrize("long_side", [224, 256, 512])
def test_other_long_sides_give_multiples_of_16(long_side):
    for width in range(40, 1400, 37):
        for height in (width, width * 3 // 4, width * 9 // 16, width * 4 // 3 + 1):
            transform = compute_transform(width, height, long_side)
            out_w, out_h = transform.output
            assert out_w % 16 == 0 and out_h % 16 == 0 and out_w > 0 and out_h > 0
            assert max(transform.resized) == long_side
            assert out_w <= transform.resized[0] and out_h <= transform.resized[1]
    assert compute_transform(640, 480, 256).output == (256, 192)
    assert compute_transform(640, 480, 224).output == (224, 160)  # 224x168 cropped to 16s
    assert compute_transform(300, 300, 256).output == (256, 192)


def test_filters_are_lanczos_when_shrinking_and_bicubic_when_enlarging():
    cases = (((700, 500), Image.Resampling.LANCZOS), ((300, 200), Image.Resampling.BICUBIC))
    for size, resample in cases:
        image = random_image(*size, seed=1)
        out, transform = resize_crop(image)
        expected = np.asarray(Image.fromarray(image).resize(transform.resized, resample))
        top, left = transform.crop_top, transform.crop_left
        np.testing.assert_array_equal(
            out, expected[top : top + out.shape[0], left : left + out.shape[1]]
        )


def test_long_side_already_512_is_not_resampled():
    image = random_image(512, 400, seed=2)
    out, transform = resize_crop(image)
    assert transform.resized == (512, 400) and transform.output == (512, 400)
    np.testing.assert_array_equal(out, image)


def test_too_elongated_image_is_an_input_error():
    with pytest.raises(InputError, match="2000x10"):
        compute_transform(2000, 10)


def test_bad_image_array_is_rejected():
    with pytest.raises(ValueError):
        resize_crop(np.zeros((10, 10, 3), np.float32))
    with pytest.raises(ValueError):
        resize_crop(np.zeros((10, 10), np.uint8))


@pytest.mark.parametrize(
    "size, uv, sigma",
    [
        ((32, 24), (13.3, 10.7), 1.5),  # enlarged 16x: a half-pixel slip would be 7.5 px
        ((752, 480), (300.3, 200.6), 4.0),  # odd crop: rows start at 3, not 3.5
        ((480, 640), (200.2, 300.7), 4.0),
        ((512, 512), (250.3, 260.4), 4.0),
        ((1920, 1080), (900.4, 500.3), 8.0),
    ],
)
def test_intrinsics_project_onto_the_same_content(size, uv, sigma, dtype):
    # A 3-D point projected with K lands on a blob; after the transform the point
    # projected with K' must land on the blob's new centre.
    cx, cy = size[0] / 2 - 3.0, size[1] / 2 + 2.0
    K = np.array([[400.0, 0.0, cx], [0.0, 410.0, cy], [0.0, 0.0, 1.0]])
    ray = np.linalg.solve(K, np.array([uv[0], uv[1], 1.0]))
    point = 2.5 * ray
    out, transform = resize_crop(blob_image(*size, *uv, sigma))
    K_out = transform.intrinsics(torch.as_tensor(K, dtype=dtype))
    assert K_out.dtype == dtype and K_out.shape == (3, 3)
    projected = K_out.double().numpy() @ point
    np.testing.assert_allclose(projected[:2] / projected[2], centroid(out), atol=0.05)
    np.testing.assert_allclose(transform.intrinsics(K), K_out.double().numpy(), rtol=1e-6)


def test_intrinsics_accept_batches():
    transform = compute_transform(752, 480)
    K = np.stack([np.eye(3), 2 * np.eye(3)])
    K[1, 2, 2] = 1.0
    batched = transform.intrinsics(K)
    np.testing.assert_allclose(batched[1], transform.intrinsics(K[1]))


@pytest.mark.parametrize("size", [(32, 24), (752, 480), (512, 512), (301, 677)])
def test_apply_nearest_agrees_with_intrinsics(size):
    width, height = size
    u, v = np.meshgrid(np.arange(width), np.arange(height))
    coords = np.stack([u, v], -1).astype(np.float32)
    transform = compute_transform(width, height)
    sampled = transform.apply_nearest(coords)
    out_w, out_h = transform.output
    assert sampled.shape == (out_h, out_w, 2) and sampled.dtype == np.float32
    # Each output pixel reads the input pixel whose centre maps within half an input pixel.
    A = transform.intrinsics(np.eye(3))
    mapped_u = A[0, 0] * sampled[..., 0] + A[0, 2]
    mapped_v = A[1, 1] * sampled[..., 1] + A[1, 2]
    x, y = np.meshgrid(np.arange(out_w), np.arange(out_h))
    assert np.all(np.abs(mapped_u - x) <= 0.5 / transform.scale_w + 1e-4)
    assert np.all(np.abs(mapped_v - y) <= 0.5 / transform.scale_h + 1e-4)


def test_apply_nearest_keeps_values_exact():
    rng = np.random.default_rng(3)
    depth = rng.uniform(1.0, 5.0, (480, 640)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.3] = 0.0
    labels = rng.integers(-1, 50, (480, 640, 3)).astype(np.int32)
    transform = compute_transform(640, 480)
    out_depth = transform.apply_nearest(depth)
    assert np.isin(out_depth, depth).all() and (out_depth == 0).any()
    assert transform.apply_nearest(labels).dtype == np.int32
    with pytest.raises(ValueError):
        transform.apply_nearest(depth.T)


def test_to_network_normalisation():
    image = np.zeros((16, 32, 3), np.uint8)
    image[..., 0], image[..., 1], image[..., 2] = 0, 255, 51
    tensor = ImageTransform.to_network(image)
    assert tensor.shape == (3, 16, 32) and tensor.dtype == torch.float32
    assert torch.all(tensor[0] == -1.0) and torch.all(tensor[1] == 1.0)
    torch.testing.assert_close(tensor[2], torch.full((16, 32), 2 * 51 / 255 - 1))
    values = torch.arange(256, dtype=torch.uint8).reshape(16, 16, 1).expand(16, 16, 3).numpy()
    torch.testing.assert_close(
        ImageTransform.to_network(values)[0].flatten(), torch.arange(256) * 2 / 255.0 - 1
    )


#: intrinsics of the 640x480 frame of :func:`_frame_with_truth`
CALIB = (500.0, 505.0, 320.0, 240.0)


def _frame_with_truth() -> Frame:
    """A 640x480 frame with depth, surface keys and a ground-truth pose."""
    rng = np.random.default_rng(4)
    depth = rng.uniform(1, 3, (480, 640)).astype(np.float32)
    surface = rng.normal(size=(480, 640, 3)).astype(np.float32)
    T_WC = torch.tensor([1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0, 1.0], dtype=torch.float64)
    return Frame(7, 0.5, "0007", random_image(640, 480), depth, surface, T_WC)


def test_make_view_carries_no_ground_truth():
    frame, calib = _frame_with_truth(), CALIB
    view = make_view(frame, agent=2, long_side=256, calib=calib)
    assert {f.name for f in dataclasses.fields(view)} == {"image", "agent", "index", "K"}
    assert view.agent == 2 and view.index == 7 and view.shape == (192, 256)
    image, transform = resize_crop(frame.image, 256)
    torch.testing.assert_close(view.image, ImageTransform.to_network(image))
    K = np.array([[500.0, 0, 320.0], [0, 505.0, 240.0], [0, 0, 1]])
    assert view.K.dtype == torch.float32
    torch.testing.assert_close(view.K, torch.from_numpy(transform.intrinsics(K)).float())
    assert make_view(frame, agent=2, long_side=256).K is None  # uncalibrated: no K at all


def test_frame_ground_truth_follows_the_view():
    frame, calib = _frame_with_truth(), CALIB
    truth = frame_ground_truth(frame, long_side=256, calib=calib)
    _, transform = resize_crop(frame.image, 256)
    torch.testing.assert_close(truth.depth, torch.from_numpy(transform.apply_nearest(frame.depth)))
    assert truth.surface.shape == (192, 256, 3) and truth.depth.dtype == torch.float32
    assert truth.T_WC is frame.T_WC_gt
    torch.testing.assert_close(truth.K, make_view(frame, 2, 256, calib).K)
    bare = frame_ground_truth(Frame(0, 0.0, "0", random_image(64, 48)), long_side=256)
    assert bare.depth is None and bare.surface is None and bare.K is None and bare.T_WC is None


def test_enlarged_depth_and_keys_follow_the_surface_not_a_staircase() -> None:
    """320x240 -> 512x384: a tilted plane's inverse depth is affine in the pixel, so the
    enlarged map must equal the plane at every output pixel; nearest sampling repeats
    values in blocks (the simulated prior then finds no key steps and loses track)."""
    width, height = 320, 240
    transform = compute_transform(width, height, 512)
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    inverse = 0.2 + 1e-4 * u + 2e-4 * v  # 1 / z of a plane
    depth = (1.0 / inverse).astype(np.float32)
    surface = np.stack([np.full_like(u, 7.0), 0.01 * u, 0.02 * v], -1).astype(np.float32)
    surface[:, :20, 0] = -1.0  # sky: no key, no depth
    depth[:, :20] = 0.0
    out_depth, out_surface = transform.apply_geometry(depth, surface)
    assert out_depth.shape == (384, 512) and out_surface.shape == (384, 512, 3)
    ov, ou = np.mgrid[0:384, 0:512].astype(np.float64)
    src_u = (ou + transform.crop_left + 0.5) * transform.scale_w - 0.5
    src_v = (ov + transform.crop_top + 0.5) * transform.scale_h - 0.5
    interior = (src_u > 21) & (src_u < width - 1) & (src_v > 0) & (src_v < height - 1)
    expected = 1.0 / (0.2 + 1e-4 * src_u + 2e-4 * src_v)
    assert np.abs(out_depth - expected)[interior].max() < 1e-5 * expected.max()
    assert np.abs(out_surface[..., 1] - 0.01 * src_u)[interior].max() < 1e-5
    steps = np.diff(out_depth[interior.any(1)][:, 200:300], axis=1)
    assert (np.abs(steps) > 0).mean() > 0.99  # no repeated values
    assert (out_depth[:, :10] == 0).all() and (out_surface[:, :10, 0] == -1).all()
    # shrinking keeps exact input values (nearest sampling)
    small = compute_transform(width, height, 160)
    small_depth, _ = small.apply_geometry(depth, surface)
    assert np.isin(small_depth, depth).all()
