"""The image term compares images at a resolution set by the data, not the camera."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from scipy.optimize import brentq

from diffaccel.data.synthetic import make_synthetic_quad_scan, sample_preset_beam
from diffaccel.dynamics import Beamline, Drift, Quadrupole, Screen
from diffaccel.dynamics.images import cic_image
from diffaccel.reconstruction import ReconstructionConfig, reconstruct
from diffaccel.reconstruction.forward import ScreenForwardModel
from diffaccel.reconstruction.training import (
    image_rms_pixels,
    loss_smoothing_for,
    pool_images,
    pooled_screen,
    sampling_smoothing,
    scan_smoothing,
    smoothed_for_loss,
)

DATA = Path(__file__).resolve().parents[2] / "data" / "phase_space"

SCREEN_M = 20.48e-3


def _forward(pixels: int, blur: float = 1.0) -> ScreenForwardModel:
    size = SCREEN_M / pixels
    line = Beamline(
        [
            Quadrupole("Q1", length=0.1, k1=0.0),
            Drift("D1", length=1.0),
            Screen("SCREEN", shape=(pixels, pixels), pixel_size=(size, size)),
        ]
    )
    return ScreenForwardModel(line, ["Q1.k1"], 43.36e6, blur_pixels=blur)


def _gaussian_image(pixels: int, sigma_m: float) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    xy = sigma_m * torch.randn(2, 200_000, generator=g, dtype=torch.float64)
    size = SCREEN_M / pixels
    return cic_image(xy[0], xy[1], (pixels, pixels), size)[None]


def test_smoothing_is_fixed_in_metres_and_follows_the_sample_size():
    """The same beam on 64 or 320 pixels is smoothed by the same length, and the
    smoothing shrinks as N^(-1/6) (Scott's rule in two dimensions)."""
    widths = []
    for pixels in (64, 320):
        im = _gaussian_image(pixels, 1.5e-3)
        widths.append(sampling_smoothing(im, 4096)[0] * SCREEN_M / pixels)
    assert widths[1].tolist() == pytest.approx(widths[0].tolist(), rel=0.02)
    assert widths[0].tolist() == pytest.approx(
        [1.5e-3 * 4096 ** (-1 / 6)] * 2, rel=0.02
    )
    im = _gaussian_image(64, 1.5e-3)
    ratio = sampling_smoothing(im, 4096 * 64) / sampling_smoothing(im, 4096)
    assert ratio[0].tolist() == pytest.approx([0.5, 0.5], rel=1e-6)
    plain = sampling_smoothing(im, 4096)[0, 0].item()
    floored = sampling_smoothing(im, 4096, floor=3.0)[0, 0].item()
    assert floored == pytest.approx(math.hypot(3.0, plain), rel=1e-9)


def test_image_rms_ignores_negative_noise():
    im = torch.zeros(1, 9, 9)
    im[0, 4, 2] = im[0, 4, 6] = 0.5
    noisy = im.clone()
    noisy[0, 0, 0] = -0.2
    assert image_rms_pixels(noisy).tolist() == [[2.0, 0.0]]


def test_loss_smoothing_given_or_sized_by_the_data():
    im = _gaussian_image(64, 1.5e-3)
    assert loss_smoothing_for(ReconstructionConfig(loss_smoothing=0.5), [im]) == [0.5]
    assert ReconstructionConfig(dims=4).loss_smoothing == "auto"
    assert loss_smoothing_for(ReconstructionConfig(dims=6), [im]) == [1.0]
    auto4 = ReconstructionConfig(dims=4, n_particles=4096, loss_smoothing="auto")
    [auto] = loss_smoothing_for(auto4, [im])
    assert auto == pytest.approx(float(sampling_smoothing(im, 4096).max()))
    assert loss_smoothing_for(ReconstructionConfig(dims=4, n_particles=4096), [im]) == [
        pytest.approx(auto)
    ]
    auto6 = ReconstructionConfig(dims=6, n_particles=4096, loss_smoothing="auto")
    assert loss_smoothing_for(auto6, [im]) == [pytest.approx(math.hypot(1.0, auto))]
    with pytest.raises(ValueError, match="loss_smoothing"):
        ReconstructionConfig(loss_smoothing="fine")


def test_the_smallest_spot_caps_the_smoothing():
    """A scan with a waist of 0.3 mm rms and a 3 mm wide image: Scott's rule
    for the wide image (3 mm x 4096^(-1/6), 0.75 mm) would blur the waist
    away, so the scan is smoothed by the waist's own rms size."""
    pixels = 128
    wide, waist = _gaussian_image(pixels, 3e-3), _gaussian_image(pixels, 0.3e-3)
    scan = torch.cat([wide, waist])
    per_pixel = SCREEN_M / pixels
    scott = float(sampling_smoothing(wide, 4096).max())
    assert scott * per_pixel == pytest.approx(3e-3 * 4096 ** (-1 / 6), rel=0.02)
    h = scan_smoothing(scan, 4096)
    assert h == pytest.approx(float(image_rms_pixels(waist).min()), rel=1e-9)
    assert h * per_pixel == pytest.approx(0.3e-3, rel=0.1)  # CIC adds 1/6 pixel^2
    assert scan_smoothing(wide, 4096) == pytest.approx(scott, rel=1e-9)
    assert scan_smoothing(scan, 4096, floor=1.0) == pytest.approx(math.hypot(1.0, h))


def test_pool_images_keeps_mass_and_centroid():
    im = _gaussian_image(250, 1.0e-3)
    pooled, before = pool_images(im, 4)
    assert pooled.shape == (1, 63, 63)
    assert float(pooled.sum()) == pytest.approx(float(im.sum()), rel=1e-6)
    fwd = _forward(250)
    shape, pixel, center = pooled_screen(fwd, 4, before)
    assert shape == (63, 63)
    assert pixel == pytest.approx((4 * SCREEN_M / 250,) * 2)
    # the pooled pixels' centres reproduce the fine image's centroid and rms
    xs = center[0] + (torch.arange(63, dtype=torch.float64) - 31) * pixel[0]
    fine = (torch.arange(250, dtype=torch.float64) - 124.5) * (SCREEN_M / 250)
    px_fine, px_pool = im[0].sum(0).double(), pooled[0].sum(0).double()
    mean_f = float((px_fine * fine).sum() / px_fine.sum())
    mean_p = float((px_pool * xs).sum() / px_pool.sum())
    # a misplaced coarse grid would be off by a quarter of a pixel or more
    assert mean_p == pytest.approx(mean_f, abs=0.01 * pixel[0])


def test_smoothed_images_have_equal_second_moments_on_both_sides():
    """The simulated beam's smoothed image (pooled, deposited on the coarse
    screen) and the measured image of the same beam (a fine histogram, pooled
    and smoothed) have the same rms: the comparison adds no bias."""
    fwd = _forward(320)
    g = torch.Generator().manual_seed(1)
    beam = sample_preset_beam("gaussian", 200_000, g, dtype=torch.float32)
    beam[:, :4] *= 0.5
    settings = torch.tensor([[-5.0], [10.0]])
    measured = fwd.images(beam, settings)
    sigma = 9.0
    [fs], [ms] = smoothed_for_loss([fwd], [measured], sigma)
    assert fs.screen.shape == (80, 80)  # pooled 4 x 4
    sim = fs.images(beam, settings)
    pix = fs.screen.pixel_size[0]
    for k in range(2):
        rms = [image_rms_pixels(x[k : k + 1]) * pix for x in (sim, ms.to(sim.dtype))]
        assert rms[0] == pytest.approx(rms[1], rel=3e-3)


def _fit(pixels: int) -> tuple[float, float]:
    g = torch.Generator().manual_seed(2)
    truth = sample_preset_beam("gaussian", 100_000, g)
    truth[:, :4] *= 0.5
    ds = make_synthetic_quad_scan(
        particles=truth,
        n_settings=9,
        k1_range=(-20.0, 20.0),
        screen_shape=(pixels, pixels),
        pixel_size=(SCREEN_M / pixels,) * 2,
        image_method="histogram",
    )
    config = ReconstructionConfig(dims=4, n_particles=2048, steps=150, snapshots=3)
    m = reconstruct(ds, config, uncertainty=False).moments(20_000)
    true = [
        float(torch.linalg.det(torch.cov(truth[:, i : i + 2].T)).sqrt()) for i in (0, 2)
    ]
    return m["emit_x"]["mean"] / true[0] - 1, m["emit_y"]["mean"] / true[1] - 1


def test_same_beam_at_two_resolutions_gives_the_same_emittance():
    """64 and 320 pixels per axis, 2048 particles per step, default settings
    (each scan smoothed by ``scan_smoothing``): compared pixel by pixel
    (``loss_smoothing=0``) the same fits give +8 % at 64 pixels and +22 to
    +150 % at 320."""
    coarse = _fit(64)
    fine = _fit(320)
    for c, f in zip(coarse, fine, strict=True):
        assert abs(f) < 0.04 and abs(c) < 0.04
        assert f == pytest.approx(c, abs=0.03)


def test_each_image_is_smoothed_by_its_own_size():
    """A waist image and a wide one of the same scan get smoothings in
    proportion to their own rms sizes, per axis, and the simulated images get
    the same smoothing as the measured ones, image by image."""
    fwd = _forward(200, math.sqrt(1 / 6))  # the measured images: bare CIC
    sizes = (2.0e-3, 0.3e-3)
    measured = torch.cat([_gaussian_image(200, sc) for sc in sizes])
    sigma = sampling_smoothing(measured, 4096)
    assert (sigma[0] / sigma[1]).tolist() == pytest.approx([2.0 / 0.3] * 2, rel=0.02)
    [fs], [ms] = smoothed_for_loss([fwd], [measured], [sigma])
    assert fs.screen.shape == (200, 200)  # the narrow image keeps the camera pixels
    g = torch.Generator().manual_seed(5)
    unit = torch.zeros(200_000, 6)
    unit[:, [0, 2]] = torch.randn(200_000, 2, generator=g)
    for k, sc in enumerate(sizes):
        one = ScreenForwardModel(
            fs.beamline,
            fs.names,
            fs.p0c,
            blur_pixels=fs.blur_pixels,
            image_smoothing=sigma[k : k + 1],
        )
        sim = one.images(unit * torch.tensor([sc, 1, sc, 1, 1, 1]), torch.zeros(1, 1))
        want = image_rms_pixels(ms[k : k + 1].double())[0]
        got = image_rms_pixels(sim.double())[0]
        assert got.tolist() == pytest.approx(want.tolist(), rel=0.01)


def test_sparse_variance_share_of_a_gaussian_image_is_analytic():
    from diffaccel.reconstruction.evaluation import sparse_variance_share

    # a round Gaussian of 10 pixels rms; N chosen so that one particle is
    # expected at r = 2 rms: the pixels beyond hold the share
    # E[x^2; r > R] / E[x^2] = (R^2 / s^2 + 2) exp(-R^2 / 2 s^2) / 2 = 3 e^-2
    sigma, radius = 10.0, 20.0
    c = torch.arange(161, dtype=torch.float64) - 80.0
    r2 = c[:, None] ** 2 + c[None, :] ** 2
    img = torch.exp(-r2 / (2 * sigma**2))[None]
    img = img / img.sum()
    level = math.exp(-(radius**2) / (2 * sigma**2)) / (2 * math.pi * sigma**2)
    kappa = 0.25
    n = round(kappa / level)
    share, need = sparse_variance_share(img, n, kappa)
    assert share == pytest.approx(3 * math.exp(-2), abs=0.01)
    # 20 % of the variance lies beyond R^2 = u s^2 with (u + 2) exp(-u / 2) = 0.4
    u = brentq(lambda u: (u + 2) * math.exp(-u / 2) - 0.4, 1.0, 20.0)
    assert need == pytest.approx(
        kappa * 2 * math.pi * sigma**2 * math.exp(u / 2), rel=0.03
    )
    # the particles it asks for bring every image's share down to the target
    _, need_01 = sparse_variance_share(img, n, kappa, share=0.1)
    assert need_01 > n
    assert sparse_variance_share(img, math.ceil(need_01), kappa)[0] <= 0.1 + 1e-9


def test_images_finer_than_the_sample_resolves_are_warned():
    from diffaccel.data.synthetic import make_synthetic_quad_scan
    from diffaccel.reconstruction.evaluation import resolution_warnings
    from diffaccel.reconstruction.pipeline import as_scans

    g = torch.Generator().manual_seed(6)
    truth = sample_preset_beam("gaussian", 50_000, g)
    truth[:, :4] *= 0.5
    scans = {}
    for pixels in (64, 320):
        ds = make_synthetic_quad_scan(
            particles=truth,
            n_settings=5,
            k1_range=(-20.0, 20.0),
            screen_shape=(pixels, pixels),
            pixel_size=(SCREEN_M / pixels,) * 2,
            image_method="histogram",
        )
        scans[pixels] = as_scans(ds)
    pixelwise = ReconstructionConfig(dims=4, loss_smoothing=0.0)
    assert resolution_warnings(pixelwise, scans[64], {}) == []
    [line] = resolution_warnings(pixelwise, scans[320], {})
    assert "--loss-smoothing auto" in line
    assert f"{pixelwise.n_particles} particles" in line
    auto = ReconstructionConfig(dims=4)
    assert resolution_warnings(auto, scans[320], {}) == []
    few = ReconstructionConfig(dims=4, n_particles=16)  # Scott's 4x the waist
    [line] = resolution_warnings(few, scans[320], {})
    assert "smallest spot" in line and "--particles" in line


@pytest.mark.parametrize(
    ("name", "dims"),
    [
        ("gpsr_4d_synthetic.h5", 4),
        ("awa_quad_scan_train.h5", 4),
        ("sixd_synthetic_train.h5", 6),
    ],
)
def test_the_shared_scans_are_resolved_at_the_defaults(name: str, dims: int):
    from diffaccel.data import read_scans
    from diffaccel.reconstruction.evaluation import resolution_warnings
    from diffaccel.reconstruction.pipeline import as_scans

    # the default fits of these files meet the benchmarks' limits: no warning
    scans = as_scans(read_scans(DATA / name))
    assert resolution_warnings(ReconstructionConfig(dims=dims), scans, {}) == []
    # a 64th of the particles leaves them unresolved
    few = ReconstructionConfig(
        dims=dims, n_particles=ReconstructionConfig(dims=dims).n_particles // 64
    )
    assert len(resolution_warnings(few, scans, {})) == len(scans.names)


def test_spots_below_the_point_spread_are_noted():
    from diffaccel.data import read_quad_scan
    from diffaccel.reconstruction.evaluation import point_spread_notes
    from diffaccel.reconstruction.pipeline import as_scans

    gpsr = as_scans(read_quad_scan(DATA / "gpsr_4d_synthetic.h5"))
    config = ReconstructionConfig(dims=4)  # 1-pixel point spread
    [line] = point_spread_notes(config, gpsr, {})
    spot = float(line.split("spot (")[1].split(" pixels")[0])
    assert 0.4 < spot < 0.8 and "point spread's shape" in line  # a 0.6-pixel waist
    # the same images with a point spread below the waist: nothing to warn
    assert point_spread_notes(replace(config, blur_pixels=0.5), gpsr, {}) == []
