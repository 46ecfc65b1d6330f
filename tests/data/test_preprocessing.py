"""Preprocessing of raw screen images: each step does what it says, on numbers."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from diffaccel.data import QuadScanDataset
from diffaccel.data.preprocessing import (
    average_shots,
    center_centroids,
    crop_to_beam,
    image_centroids,
    median_filter,
    normalize,
    pool,
    subtract_background,
    threshold,
    triangle_threshold,
)


def _blob(h: int, w: int, ci: float, cj: float, si: float, sj: float) -> torch.Tensor:
    i = torch.arange(h, dtype=torch.float64)[:, None]
    j = torch.arange(w, dtype=torch.float64)[None, :]
    return torch.exp(-0.5 * ((i - ci) / si) ** 2 - 0.5 * ((j - cj) / sj) ** 2)


def _with_images(ds: QuadScanDataset, images: torch.Tensor) -> QuadScanDataset:
    settings = ds.settings[: images.shape[0]]
    return QuadScanDataset(
        images=images,
        settings=settings,
        setting_names=ds.setting_names,
        setting_units=ds.setting_units,
        p0c=ds.p0c,
        species=ds.species,
        beamline_spec=ds.beamline_spec,
        pixel_size=ds.pixel_size,
        center=ds.center,
        metadata={},
    )


def _physical_centroid(ds: QuadScanDataset) -> torch.Tensor:
    """(K, S, 2) centroid (y, x) [m] from pixel centres."""
    xs, ys = ds.pixel_centers()
    img = ds.images.double()
    total = img.sum((-2, -1))
    y = (img.sum(-1) * ys).sum(-1) / total
    x = (img.sum(-2) * xs).sum(-1) / total
    return torch.stack([y, x], -1)


@pytest.fixture
def raw(dataset) -> QuadScanDataset:
    """2 settings x 2 shots of 32 x 40 pixels: off-centre blob + background 0.25."""
    blob = _blob(32, 40, 13.3, 22.6, 2.0, 3.0)
    images = torch.stack([torch.stack([blob, 0.5 * blob])] * 2) + 0.25
    return _with_images(dataset, images.float())


def test_background_edge_estimate_removes_known_level(raw) -> None:
    out = subtract_background(raw, edge_pixels=3)
    expected = raw.images - 0.25
    # the blob is < 1e-6 of its peak in the 3-pixel border band; float32 round-off
    torch.testing.assert_close(out.images, expected, rtol=0, atol=2e-6)
    step = out.metadata["preprocessing"][-1]
    assert step["method"] == "edge" and step["mean_level"] == pytest.approx(0.25)
    assert "preprocessing" not in raw.metadata  # input untouched


def test_background_dark_frame(raw) -> None:
    dark = torch.full((32, 40), 0.25)
    dark[0, 0] = 0.3  # a warm pixel in the dark frame: over-subtracted by 0.05
    out = subtract_background(raw, dark=dark)
    # kept signed by default (unbiased); clamped at 0 only with clip=True
    assert out.images[0, 0, 0, 0].item() == pytest.approx(-0.05, abs=1e-6)
    assert out.metadata["preprocessing"][-1]["clip"] is False
    clipped = subtract_background(raw, dark=dark, clip=True)
    assert clipped.images[0, 0, 0, 0].item() == 0.0
    assert clipped.metadata["preprocessing"][-1]["clip"] is True
    torch.testing.assert_close(
        out.images[..., 5:, 5:], (raw.images - 0.25)[..., 5:, 5:], rtol=0, atol=1e-7
    )


def test_background_dark_shape_error(raw) -> None:
    with pytest.raises(ValueError, match=r"dark: shape \(3, 3\) does not broadcast"):
        subtract_background(raw, dark=torch.zeros(3, 3))


def test_triangle_threshold_separates_noise_from_beam() -> None:
    g = torch.Generator().manual_seed(3)
    noise = 0.02 * torch.rand(64, 64, generator=g, dtype=torch.float64)
    image = _blob(64, 64, 30.0, 34.0, 4.0, 4.0) + noise
    level = float(triangle_threshold(image))
    # the threshold sits above the noise floor (max 0.02) and far below the peak
    assert 0.02 <= level < 0.2


def test_threshold_zeroes_noise(raw) -> None:
    ds = subtract_background(raw, edge_pixels=3)
    g = torch.Generator().manual_seed(0)
    noisy = ds.images + 0.01 * torch.rand(ds.images.shape, generator=g)
    out = threshold(_with_images(ds, noisy), method="fraction", value=0.05)
    far = out.images[..., :, :8]  # > 4 sigma from the blob in x: noise only
    assert far.abs().max().item() == 0.0
    peak = out.images.flatten(-2).amax(-1)
    torch.testing.assert_close(peak, noisy.flatten(-2).amax(-1))  # beam kept


def test_threshold_all_zero_raises(raw) -> None:
    with pytest.raises(ValueError, match="all zero afterwards"):
        threshold(raw, method="absolute", value=10.0)


def test_median_filter_removes_hot_pixel(dataset) -> None:
    i = torch.arange(24, dtype=torch.float32)[:, None]
    j = torch.arange(28, dtype=torch.float32)[None, :]
    ramp = 1.0 + 0.01 * i + 0.02 * j  # a plane: its 3x3 median is the centre value
    hot = ramp.clone()
    hot[10, 12] = 100.0
    ds = _with_images(dataset, torch.stack([hot, ramp])[:, None])
    out = median_filter(ds, size=3)
    # the hot pixel is replaced by a neighbour's value: within one ramp step
    assert abs(out.images[0, 0, 10, 12].item() - ramp[10, 12].item()) <= 0.03 + 1e-6
    # away from the hot pixel and the reflected border the plane is unchanged
    far = torch.ones(24, 28, dtype=torch.bool)
    far[9:12, 11:14] = False
    far[0, :] = far[-1, :] = far[:, 0] = far[:, -1] = False
    torch.testing.assert_close(out.images[0, 0][far], ramp[far], rtol=0, atol=1e-6)
    torch.testing.assert_close(out.images[1, 0][1:-1, 1:-1], ramp[1:-1, 1:-1])


def test_center_centroids_each(raw) -> None:
    ds = subtract_background(raw, edge_pixels=3)
    out = center_centroids(ds, mode="each")
    cent = image_centroids(out.images.double())
    # bilinear resampling of a >= 2-pixel-wide blob: centroid exact to 1e-3 px
    torch.testing.assert_close(
        cent,
        torch.tensor([15.5, 19.5], dtype=torch.float64).expand_as(cent),
        rtol=0,
        atol=1e-3,
    )
    # intensity is conserved (the blob stays far from the border)
    torch.testing.assert_close(
        out.images.sum((-2, -1)), ds.images.sum((-2, -1)), rtol=1e-5, atol=0
    )


def test_center_centroids_common_keeps_relative_motion(dataset) -> None:
    a = _blob(32, 32, 12.0, 14.0, 2.0, 2.0)
    b = _blob(32, 32, 18.0, 16.0, 2.0, 2.0)
    ds = _with_images(dataset, torch.stack([a, b])[:, None].float())
    out = center_centroids(ds, mode="common")
    cent = image_centroids(out.images.double())[:, 0]
    torch.testing.assert_close(
        cent[1] - cent[0], torch.tensor([6.0, 2.0]).double(), rtol=0, atol=1e-3
    )
    torch.testing.assert_close(
        cent.mean(0), torch.tensor([15.5, 15.5]).double(), rtol=0, atol=1e-3
    )


def test_crop_keeps_beam_and_physical_position(raw) -> None:
    ds = subtract_background(raw, edge_pixels=3)
    out = crop_to_beam(ds, n_rms=5.0)
    assert out.screen_shape[0] < 32 and out.screen_shape[1] < 40
    # 5 rms in each plane keeps all but ~1e-6 of a Gaussian
    torch.testing.assert_close(
        out.images.sum((-2, -1)), ds.images.sum((-2, -1)), rtol=1e-5, atol=0
    )
    # tails beyond 5 rms (~1e-6 of the intensity) and float32 sums: 1e-4 pixel
    torch.testing.assert_close(
        _physical_centroid(out), _physical_centroid(ds), rtol=0, atol=1e-7
    )


def test_crop_explicit_shape(raw) -> None:
    out = crop_to_beam(subtract_background(raw, edge_pixels=3), shape=(16, 20))
    assert out.screen_shape == (16, 20)
    assert (
        out.metadata["preprocessing"][-1]["window"][1]
        - out.metadata["preprocessing"][-1]["window"][0]
        == 16
    )


@pytest.mark.parametrize("factor", [2, 3, (2, 4)], ids=["2", "3", "2x4"])
def test_pool_conserves_sum_and_position(raw, factor) -> None:
    ds = subtract_background(raw, edge_pixels=3)
    out = pool(ds, factor=factor)
    fy, fx = (factor, factor) if isinstance(factor, int) else factor
    assert out.screen_shape == (-(-32 // fy), -(-40 // fx))
    assert out.pixel_size == pytest.approx(
        (ds.pixel_size[0] * fx, ds.pixel_size[1] * fy)
    )
    # summing blocks conserves the total exactly up to float32 round-off
    torch.testing.assert_close(
        out.images.sum((-2, -1)), ds.images.sum((-2, -1)), rtol=1e-6, atol=0
    )
    # block sums move the centroid only through the asymmetry inside a block:
    # < 1e-3 of an original pixel (1e-3 m) for a blob with sigma >= 2 px
    torch.testing.assert_close(
        _physical_centroid(out), _physical_centroid(ds), rtol=0, atol=1e-6
    )


def test_pool_carries_the_screen_resolution_into_the_new_pixels(raw) -> None:
    assert pool(raw, 2).resolution_pixels is None  # unknown stays unknown
    ds = replace(raw, resolution_pixels=1.0)
    # variance in old pixels 1 + (4 - 1) / 12 = 1.25, in new (2x) pixels / 4
    assert pool(ds, 2).resolution_pixels == pytest.approx(math.sqrt(1.25) / 2)
    assert pool(ds, 1).resolution_pixels == pytest.approx(1.0)


def test_normalize_and_average(raw) -> None:
    out = average_shots(normalize(raw))
    assert out.shape == (2, 1, 32, 40)
    torch.testing.assert_close(
        out.images.sum((-2, -1)), torch.ones(2, 1), rtol=0, atol=1e-6
    )
    steps = [s["step"] for s in out.metadata["preprocessing"]]
    assert steps == ["normalize", "average_shots"]


def test_chain_records_every_step(raw) -> None:
    out = subtract_background(raw)
    out = median_filter(out)
    out = threshold(out)
    out = crop_to_beam(out)
    out = pool(out)
    out = normalize(out)
    steps = [s["step"] for s in out.metadata["preprocessing"]]
    assert steps == [
        "subtract_background",
        "median_filter",
        "threshold",
        "crop_to_beam",
        "pool",
        "normalize",
    ]


def test_chain_on_measured_awa_images(reference_file) -> None:
    from diffaccel.data import read_quad_scan

    ds = read_quad_scan(reference_file("awa_quad_scan_train.h5"))
    out = normalize(pool(center_centroids(ds), factor=2))
    assert out.shape == (11, 3, 42, 42)
    assert out.pixel_size == pytest.approx((2 * 124.86e-6, 2 * 124.86e-6))
    torch.testing.assert_close(
        out.images.sum((-2, -1)), torch.ones(11, 3), rtol=0, atol=1e-5
    )
    # every shot sits at the screen centre (0, 0): the iterated shift reaches
    # 1e-4 px; float32 images and the block sums of pooling leave < 0.01 px
    cent = _physical_centroid(out)
    assert cent.abs().max().item() < 0.01 * out.pixel_size[0]
    assert [s["step"] for s in out.metadata["preprocessing"]] == [
        "center_centroids",
        "pool",
        "normalize",
    ]
