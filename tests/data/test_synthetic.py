"""Synthetic quad scans: beams, images and noise with the physics they promise."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from diffaccel.data import (
    make_synthetic_quad_scan,
    read_quad_scan,
    write_openpmd_particles,
    write_quad_scan,
)
from diffaccel.data.synthetic import PRESETS, sample_preset_beam

SMALL = {"n_settings": 6, "screen_shape": (32, 32), "pixel_size": (2e-3, 2e-3)}


def _image_moments(ds) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-setting rms (x, y) [m] of the shot-averaged images."""
    img = ds.mean_images().double()
    xs, ys = ds.pixel_centers()
    px, py = img.sum(-2), img.sum(-1)
    mx, my = (px * xs).sum(-1), (py * ys).sum(-1)
    sx = ((px * (xs - mx[:, None]) ** 2).sum(-1)).sqrt()
    sy = ((py * (ys - my[:, None]) ** 2).sum(-1)).sqrt()
    return sx, sy


@pytest.mark.parametrize("preset", PRESETS)
def test_preset_beams_are_centred_6d_with_energy_spread(preset: str) -> None:
    beam = sample_preset_beam(preset, 5000, torch.Generator().manual_seed(0))
    assert beam.shape == (5000, 6) and beam.dtype == torch.float64
    torch.testing.assert_close(beam.mean(0), torch.zeros(6, dtype=torch.float64))
    std = beam.std(0)
    # transverse rms of 0.3-3 mm / 0.1-2 mrad, 0.1-1 % energy spread
    assert ((std[[0, 2]] > 3e-4) & (std[[0, 2]] < 3e-3)).all()
    assert ((std[[1, 3]] > 1e-4) & (std[[1, 3]] < 2e-3)).all()
    assert 1e-3 < std[5] < 1e-2


def test_correlated_preset_has_its_correlations() -> None:
    beam = sample_preset_beam("correlated", 10_000, torch.Generator().manual_seed(1))
    corr = torch.corrcoef(beam.T)
    # sample correlation error ~ (1 - r^2) / sqrt(N) <= 0.01; allow 4 of those
    assert corr[0, 1].item() == pytest.approx(-0.6, abs=0.04)
    assert corr[2, 3].item() == pytest.approx(0.5, abs=0.04)
    assert corr[4, 5].item() == pytest.approx(-0.7, abs=0.04)


def test_nonlinear_preset_is_not_gaussian() -> None:
    beam = sample_preset_beam("nonlinear", 10_000, torch.Generator().manual_seed(2))
    x, px = beam[:, 0], beam[:, 1]
    # x-px curvature: px correlates with x^2 (a Gaussian beam gives ~0 +- 0.01)
    r = torch.corrcoef(torch.stack([px, x**2]))[0, 1]
    assert r.item() > 0.15
    # separated modes: below y = 0 the x histogram has a dip between two peaks
    # (a single Gaussian would peak in the middle)
    hist = torch.histc(x[beam[:, 2] < 0], bins=24, min=-4e-3, max=4e-3)
    left, right = int(hist[:12].argmax()), 12 + int(hist[12:].argmax())
    dip = hist[left:right].min()
    assert dip < 0.5 * torch.minimum(hist[left], hist[right])


@pytest.mark.parametrize("preset", PRESETS)
def test_default_geometry_keeps_beam_on_screen(preset: str) -> None:
    ds = make_synthetic_quad_scan(preset, n_particles=2000)
    assert ds.shape == (20, 1, 64, 64)
    torch.testing.assert_close(
        ds.settings[:, 0], torch.linspace(-25, 15, 20, dtype=torch.float64)
    )
    # the beam is "well inside": essentially all of it lands on the screen
    assert min(ds.metadata["synthetic"]["fraction_on_screen"]) > 0.999
    sx, sy = _image_moments(ds)
    # "a few mm rms at 1 mm pixels" at the largest setting, never over 8 mm
    assert 2e-3 < sx.max() < 8e-3 and 2e-3 < sy.max() < 8e-3


def test_synthetic_scans_record_their_screen_resolution() -> None:
    kw = {"n_particles": 500, "n_settings": 2, "screen_shape": (16, 16)}
    assert make_synthetic_quad_scan(**kw).resolution_pixels == 1.0  # KDE, 1 pixel
    wide = make_synthetic_quad_scan(**kw, bandwidth=2e-3)  # 1 mm pixels
    assert wide.resolution_pixels == pytest.approx(2.0)
    cic = make_synthetic_quad_scan(**kw, image_method="cic")
    # cloud-in-cell: a triangle of one-pixel half-width, variance 1/6 pixel^2
    assert cic.resolution_pixels == pytest.approx(math.sqrt(1 / 6))


def test_image_moments_follow_linear_optics() -> None:
    """Image variance = (R Sigma R^T) + bandwidth^2 for a Gaussian beam."""
    ds = make_synthetic_quad_scan(
        "gaussian", n_particles=5000, n_settings=5, seed=3, dtype=torch.float64
    )
    beam = ds.ground_truth
    sigma = torch.cov(beam.T)
    line = ds.beamline().with_params({"Q1.k1": ds.settings[:, 0]})
    r = line.transfer_map(ds.p0c)[:, :6, :6]  # linear part of the affine map
    cov = r @ sigma @ r.transpose(-1, -2)
    bw = 1e-3  # default KDE bandwidth: one pixel
    expected_x = (cov[:, 0, 0] + bw**2).sqrt()
    expected_y = (cov[:, 2, 2] + bw**2).sqrt()
    sx, sy = _image_moments(ds)
    # same particles on both sides, so no sampling error; what remains is the
    # chromatic part of the exact quad map (kL * sigma_pz ~ 1 % -> < 0.1 % in rms)
    # and sampling the KDE at pixel centres (rms >= 1.4 px -> < 0.5 %)
    torch.testing.assert_close(sx, expected_x, rtol=0.01, atol=0)
    torch.testing.assert_close(sy, expected_y, rtol=0.01, atol=0)


def test_images_sum_normalised_and_ground_truth_kept() -> None:
    beam = sample_preset_beam("gaussian", 1000, torch.Generator().manual_seed(4))
    ds = make_synthetic_quad_scan(particles=beam, shots=2, noise=0.05, **SMALL)
    assert ds.shape == (6, 2, 32, 32)
    torch.testing.assert_close(
        ds.images.sum((-2, -1)), torch.ones(6, 2), rtol=0, atol=1e-5
    )
    assert torch.equal(ds.ground_truth, beam)
    assert ds.metadata["synthetic"]["source"] == {"kind": "tensor"}


@pytest.mark.parametrize("model", ["poisson", "gaussian"])
def test_noise_level(model: str) -> None:
    ds = make_synthetic_quad_scan(
        "gaussian", n_particles=2000, shots=60, noise=0.1, noise_model=model, **SMALL
    )
    clean = make_synthetic_quad_scan("gaussian", n_particles=2000, **SMALL)
    peak = clean.images[:, 0].flatten(-2).argmax(-1)
    k = torch.arange(6)
    at_peak = ds.images.flatten(-2)[k, :, peak]  # (K, S)
    rel = at_peak.std(dim=1) / clean.images.flatten(-2)[k, 0, peak]
    # relative rms 0.1 at the peak pixel; the std of 60 shots is known to ~9 %,
    # sum-normalisation adds < 2 %: allow 25 %
    torch.testing.assert_close(rel.mean(), torch.tensor(0.1), rtol=0.25, atol=0)
    # noise is zero-mean: the shot average approaches the clean image
    mean = ds.images.mean(1)
    err = (mean - clean.images[:, 0]).abs().sum((-2, -1)).mean()
    noisy = (ds.images[:, 0] - clean.images[:, 0]).abs().sum((-2, -1)).mean()
    assert err < 0.3 * noisy  # 1/sqrt(60) = 0.13 expected


def test_seeded() -> None:
    a = make_synthetic_quad_scan("nonlinear", n_particles=500, noise=0.1, **SMALL)
    b = make_synthetic_quad_scan("nonlinear", n_particles=500, noise=0.1, **SMALL)
    c = make_synthetic_quad_scan(
        "nonlinear", n_particles=500, noise=0.1, seed=1, **SMALL
    )
    assert torch.equal(a.images, b.images)
    assert torch.equal(a.ground_truth, b.ground_truth)
    assert not torch.equal(a.ground_truth, c.ground_truth)


def test_file_round_trip(tmp_path: Path) -> None:
    ds = make_synthetic_quad_scan("correlated", n_particles=500, **SMALL)
    back = read_quad_scan(write_quad_scan(ds, tmp_path / "syn.h5"))
    assert torch.equal(back.images, ds.images)
    assert torch.equal(back.ground_truth, ds.ground_truth)
    assert back.metadata == ds.metadata


def test_user_particle_file(tmp_path: Path) -> None:
    beam = sample_preset_beam("correlated", 800, torch.Generator().manual_seed(5))
    path = write_openpmd_particles(tmp_path / "beam.h5", beam, p0c=63e6)
    ds = make_synthetic_quad_scan(particle_file=path, **SMALL)
    assert ds.p0c == pytest.approx(63e6)
    # float64 round trip through openPMD momenta/time: round-off only
    torch.testing.assert_close(ds.ground_truth, beam, rtol=1e-9, atol=1e-15)
    assert ds.metadata["synthetic"]["source"]["kind"] == "openpmd"
    # another reference momentum: the same physical momenta, re-referenced
    other = make_synthetic_quad_scan(particle_file=path, p0c=60e6, **SMALL)
    torch.testing.assert_close(
        (1 + other.ground_truth[:, 5]) * 60e6,
        (1 + beam[:, 5]) * 63e6,
        rtol=1e-12,
        atol=0,
    )
    torch.testing.assert_close(
        other.ground_truth[:, 1] * 60e6, beam[:, 1] * 63e6, rtol=1e-12, atol=1e-9
    )


BAD = [
    (
        "both_beams",
        {"particles": torch.zeros(3, 6), "particle_file": "x.h5"},
        "not both",
    ),
    ("noise", {"noise": -0.1}, "noise: expected"),
    ("shots", {"shots": 0}, "shots: expected"),
    ("shape", {"particles": torch.zeros(10, 4)}, r"particles: expected shape \(N, 6\)"),
    ("preset", {"preset": "flat"}, "preset: expected one of"),
    ("off_screen", {"center": (1.0, 0.0)}, "misses the screen at setting 0"),
    ("noise_too_high", {"noise": 1e3}, "has no signal left; lower the noise"),
]


@pytest.mark.parametrize(
    ("kwargs", "message"), [b[1:] for b in BAD], ids=[b[0] for b in BAD]
)
def test_bad_options(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        make_synthetic_quad_scan(**{"n_particles": 100, **SMALL, **kwargs})


@pytest.mark.parametrize("method", ["kde", "cic", "histogram"])
def test_gpsr_size_screen(method: str) -> None:
    """100 x 100 pixels of 1 mm, as in the GPSR benchmark, with either image model."""
    ds = make_synthetic_quad_scan(
        "correlated",
        n_particles=1000,
        n_settings=3,
        screen_shape=(100, 100),
        image_method=method,
    )
    assert ds.shape == (3, 1, 100, 100)
    assert ds.metadata["synthetic"]["image_method"] == method
    # centred beam: image centroid within a tenth of a pixel of the screen centre
    img = ds.mean_images().double()
    xs, ys = ds.pixel_centers()
    assert (img.sum(-2) * xs).sum(-1).abs().max() < 1e-4
    assert (img.sum(-1) * ys).sum(-1).abs().max() < 1e-4


def test_histogram_counts_particles_in_their_pixel() -> None:
    """Nearest-pixel counts: each particle in the pixel whose centre is nearest."""
    from diffaccel.data.synthetic import _histogram_images

    # 3 x 4 pixels of 1 mm centred at 0: column centres -1.5 ... 1.5 mm, rows -1 ... 1
    at = torch.zeros(1, 5, 6, dtype=torch.float64)
    at[0, :, 0] = torch.tensor([-1.9e-3, -0.6e-3, 0.4e-3, 1.99e-3, 2.1e-3])
    at[0, :, 2] = torch.tensor([-1.4e-3, 0.49e-3, 0.51e-3, 1.4e-3, 0.0])
    img = _histogram_images(at, (3, 4), (1e-3, 1e-3), (0.0, 0.0))
    expected = torch.zeros(1, 3, 4, dtype=torch.float64)
    expected[0, 0, 0] = expected[0, 1, 1] = expected[0, 2, 2] = expected[0, 2, 3] = 0.2
    torch.testing.assert_close(img, expected)  # the fifth is off the screen


def test_histogram_point_spread_is_a_twelfth_pixel_squared() -> None:
    """Counting in pixels adds ps^2 / 12 to the variance of a smooth beam
    (Sheppard's correction, exact to ~exp(-2 pi^2 sigma^2 / ps^2) for a
    Gaussian; CIC adds ps^2 / 6, a KDE its bandwidth^2). 400 000 particles of
    1.5 pixel rms: the sample covariance of position and rounding offset
    scatters the added variance by ~2 %, so 10 % still tells 1/12 from 1/6."""
    g = torch.Generator().manual_seed(0)
    n = 400_000
    beam = torch.zeros(n, 6, dtype=torch.float64)
    beam[:, 0] = 1.5e-3 * torch.randn(n, generator=g, dtype=torch.float64)
    ds = make_synthetic_quad_scan(
        particles=beam,
        settings=torch.zeros(1, 1),
        screen_shape=(4, 20),
        pixel_size=(1e-3, 1e-3),
        image_method="histogram",
    )
    img = ds.mean_images().double()[0]
    xs, _ = ds.pixel_centers()
    px = img.sum(0) / img.sum()
    var = float((px * xs**2).sum() - (px * xs).sum() ** 2)
    inside = beam[:, 0].abs() < 10e-3
    true = float(beam[inside, 0].var())
    assert var - true == pytest.approx(1e-6 / 12, rel=0.1)
    # and the file says so: the reconstruction's default blur for this scan
    assert ds.resolution_pixels == pytest.approx((1 / 12) ** 0.5)


# ------------------------------------------------------------------ AWA 6D layout
def test_awa6d_layout_two_scans_settings_grid() -> None:
    from diffaccel.data import make_synthetic_awa6d

    ms = make_synthetic_awa6d(
        "gaussian", n_particles=4000, k1_values=[-6.0, 0.0, 6.0], screen_shape=(48, 48)
    )
    assert ms.names == ["dipole_off", "dipole_on"] and ms.format_version == 2
    for name, scan in ms:
        assert scan.shape == (6, 1, 48, 48), name
        # (k1, V) in the order (k1_0, 0), (k1_0, 4 MV), (k1_1, 0), ...
        assert scan.settings[:, 0].tolist() == [-6.0, -6.0, 0.0, 0.0, 6.0, 6.0]
        assert scan.settings[:, 1].tolist() == [0.0, 4e6] * 3
        # every image keeps the beam on the screen (the preset is sized for it)
        assert min(scan.metadata["synthetic"]["fraction_on_screen"]) > 0.98
    # the TDC streak: with 4 MV the image second moment about its centroid grows
    # by (R_z * sigma_z)^2 with R_z ~ 3 m/m and sigma_z = 0.8 mm, i.e. several
    # times the unstreaked spot at k1 = 0; allow a factor 2 to be safe
    scan = ms["dipole_off"]
    img = scan.mean_images().double()
    xs, ys = scan.pixel_centers()

    def spread(i: int) -> float:
        p = img[i]
        mx = (p.sum(0) * xs).sum()
        my = (p.sum(1) * ys).sum()
        return float(
            (p.sum(0) * (xs - mx) ** 2).sum() + (p.sum(1) * (ys - my) ** 2).sum()
        )

    assert spread(3) > 2 * spread(2)
