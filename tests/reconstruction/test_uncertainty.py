from __future__ import annotations

import copy

import pytest
import torch

from diffaccel.reconstruction import ReconstructionConfig, beam_moments, reconstruct
from diffaccel.reconstruction.ensemble import _recolour
from diffaccel.reconstruction.screen_moments import covariance_design, pair_indices
from diffaccel.reconstruction.uncertainty import (
    MomentUncertainty,
    covariance_moments,
    image_moments,
    linear_posterior,
)

F64 = torch.float64


def _random_cov(d: int, g: torch.Generator) -> torch.Tensor:
    a = torch.randn(d, d, generator=g, dtype=F64)
    return a @ a.T + d * torch.eye(d, dtype=F64)


def test_posterior_identifies_the_constrained_directions_exactly() -> None:
    # A sees parameters 0 and 1 only (orthogonal rows), parameter 2 never: the
    # posterior of 2 is its prior, those of 0 and 1 shrink to r^2 / n.
    g = torch.Generator().manual_seed(1)
    n = 40
    a = torch.zeros(n, 3, dtype=F64)
    a[: n // 2, 0] = 1.0
    a[n // 2 :, 1] = 1.0
    noise = 0.01 * torch.randn(n, generator=g, dtype=F64)
    prior = torch.tensor([1e3, 1e3, 7.0], dtype=F64)  # broad on 0 and 1
    cov, shift, r, dof = linear_posterior(a, noise, torch.ones(n, dtype=F64), prior)
    assert float(cov[2, 2].sqrt()) == pytest.approx(7.0, rel=1e-12)
    assert float(cov[0, 2]) == pytest.approx(0.0, abs=1e-15)
    # two fitted parameters: dof = n - 2 up to the prior's 1e-3 / 1e6 pull
    assert float(dof[0]) == pytest.approx(n - 2, abs=1e-6)
    # the error scale is the rms of what the fit leaves: each half's noise
    # about its own mean (the fitted shift), over n - 2 degrees of freedom
    left = torch.cat(
        [
            noise[: n // 2] - noise[: n // 2].mean(),
            noise[n // 2 :] - noise[n // 2 :].mean(),
        ]
    )
    r_want = float((left.square().sum() / (n - 2)).sqrt())
    assert float(r[0]) == pytest.approx(r_want, rel=1e-6)
    assert float(cov[0, 0]) == pytest.approx(r_want**2 / (n // 2), rel=1e-6)
    assert float(shift[0]) == pytest.approx(float(noise[: n // 2].mean()), rel=1e-6)


def test_a_systematic_offset_is_bias_not_noise() -> None:
    # Residuals = a parameter shift the design explains + small noise (a
    # reconstruction that is 3 % too large everywhere). The error scale must be
    # the noise's, the shift must be recovered; counting the offset as noise
    # (fitted_residuals=False) inflates the scale ~ offset / noise times.
    g = torch.Generator().manual_seed(3)
    n = 60
    a = torch.randn(n, 3, generator=g, dtype=F64)
    delta = torch.tensor([0.03, -0.02, 0.01], dtype=F64)
    noise = 1e-4 * torch.randn(n, generator=g, dtype=F64)
    prior = torch.ones(3, dtype=F64)
    _, shift, r, _ = linear_posterior(
        a, a @ delta + noise, torch.ones(n, dtype=F64), prior
    )
    # r estimates the noise std 1e-4 from 57 dof: within ~3/sqrt(2*57) = 30 %
    assert float(r[0]) == pytest.approx(1e-4, rel=0.3)
    torch.testing.assert_close(shift, delta, rtol=0, atol=1e-4)
    _, _, r_raw, _ = linear_posterior(
        a, a @ delta + noise, torch.ones(n, dtype=F64), prior, fitted_residuals=False
    )
    assert float(r_raw[0]) > 50 * float(r[0])


def test_thin_quad_scan_cannot_see_one_cross_term() -> None:
    # thin quad (kl) + drift L: x = (1 - u) x0 + L px0, y = (1 + u) y0 + L py0
    # with u = L kl, so <xy> = C_xy (1 - u^2) + L (1 - u) C_xpy + L (1 + u) C_pxy
    # + L^2 C_pxpy: three functions of u for four cross terms. The direction
    # C_xpy = C_pxy = 1, C_pxpy = -2 / L is invisible at every setting, so the
    # posterior must keep its prior width there.
    length = 2.0
    maps = []
    for kl in torch.linspace(-3, 3, 15, dtype=F64):
        quad = torch.eye(6, dtype=F64)
        quad[1, 0], quad[3, 2] = -kl, kl
        drift = torch.eye(6, dtype=F64)
        drift[0, 1] = drift[2, 3] = length
        maps.append(drift @ quad)
    a = covariance_design(torch.stack(maps), 4)
    sv = torch.linalg.svdvals(a)
    assert int((sv > 1e-9 * sv[0]).sum()) == 9  # 10 parameters, rank 9
    pairs = pair_indices(4)
    null = torch.zeros(10, dtype=F64)
    null[pairs.index((0, 3))] = null[pairs.index((1, 2))] = 1.0
    null[pairs.index((1, 3))] = -2.0 / length
    assert float((a @ null).abs().max()) < 1e-12
    e = 1e-3 * torch.randn(a.shape[0], generator=torch.Generator().manual_seed(2))
    cov, *_ = linear_posterior(
        a, e.double(), torch.ones(a.shape[0]).double(), torch.ones(10, dtype=F64)
    )
    u = null / null.norm()
    assert float(u @ cov @ u) == pytest.approx(1.0, rel=1e-6)  # prior kept
    seen = torch.zeros(10, dtype=F64)
    seen[pairs.index((0, 0))] = 1.0
    assert float(seen @ cov @ seen) < 1e-4


def test_covariance_moments_equal_beam_moments(gaussian_beam) -> None:
    x = gaussian_beam.clone()
    x[:, 4:] = (
        torch.randn(
            x.shape[0], 2, generator=torch.Generator().manual_seed(4), dtype=F64
        )
        * 1e-3
    )
    want = beam_moments(x)
    got = covariance_moments(want["centroid"], want["cov"])
    for key, val in want.items():
        torch.testing.assert_close(got[key], val, rtol=1e-10, atol=0)


def test_image_moments_of_a_point_grid() -> None:
    xs = torch.linspace(-2, 2, 5, dtype=F64)
    ys = torch.linspace(-1, 1, 3, dtype=F64)
    img = torch.zeros(1, 3, 5, dtype=F64)
    img[0, 0, 0] = img[0, 2, 4] = 1.0  # (x, y) = (-2, -1) and (2, 1)
    m = image_moments(img, xs, ys)[0]
    torch.testing.assert_close(m, torch.tensor([0.0, 0.0, 4.0, 2.0, 1.0], dtype=F64))


def test_recolour_gives_the_drawn_covariance(gaussian_beam) -> None:
    g = torch.Generator().manual_seed(5)
    cov = torch.zeros(2, 6, 6, dtype=F64)
    for k in range(2):
        cov[k, :4, :4] = _random_cov(4, g) * 1e-7
    mu = torch.randn(2, 6, generator=g, dtype=F64) * 1e-4
    out = _recolour(gaussian_beam, 4, mu, cov)
    for k in range(2):
        m = beam_moments(out[k])
        torch.testing.assert_close(m["cov"][:4, :4], cov[k, :4, :4], rtol=1e-9, atol=0)
        torch.testing.assert_close(m["centroid"][:4], mu[k, :4], rtol=0, atol=1e-12)
    assert torch.equal(out[:, :, 4:], gaussian_beam[None, :, 4:].expand(2, -1, -1))


def test_uncertainty_round_trips_through_json() -> None:
    g = torch.Generator().manual_seed(6)
    u = MomentUncertainty(
        4,
        torch.zeros(6, dtype=F64),
        torch.eye(6, dtype=F64),
        _random_cov(10, g),
        _random_cov(4, g),
        {"a": 1},
    )
    back = MomentUncertainty.from_dict(u.to_dict())
    torch.testing.assert_close(back.theta_cov, u.theta_cov, rtol=0, atol=0)
    assert back.diagnostics == {"a": 1}


FAST6 = {"dims": 6, "n_particles": 1024, "steps": 12, "snapshots": 3}


@pytest.fixture(scope="module")
def six_d(small_scan):
    return reconstruct(small_scan, ReconstructionConfig(**FAST6))


def test_unconstrained_coordinates_get_a_large_relative_std(six_d) -> None:
    # a quad-only scan never sees z (nor pz, to first order): their rms must
    # carry a relative std of at least 20 %, the transverse sizes much less
    m = six_d.moments(n=2000)
    rel = [s / v for s, v in zip(m["rms"]["std"], m["rms"]["mean"], strict=True)]
    assert set(six_d.unconstrained_coordinates()) == {"z", "pz"}
    assert rel[4] >= 0.2 and rel[5] >= 0.2
    assert max(rel[:4]) < 0.2
    assert m["emit_z"]["std"] / m["emit_z"]["mean"] >= 0.2
    assert m["rms"]["std_posterior"] is not None


def test_predict_images_returns_a_per_pixel_spread(six_d, small_scan) -> None:
    s = small_scan.settings[:2]
    mean, std = six_d.predict_images(s, n_particles=2000, return_std=True, n_draws=2)
    plain = six_d.predict_images(s, n_particles=2000)
    assert torch.equal(mean, plain)
    assert std.shape == mean.shape
    assert float(std.min()) >= 0 and float(std.max()) > 0


def test_image_spread_has_no_shot_noise_from_the_draws(six_d, small_scan) -> None:
    # With a posterior of zero width every draw is the member itself: the
    # draws of a member share particles, so the spread must equal the
    # ensemble-only spread (not grow by the draws' shot noise).
    s = small_scan.settings[:2]
    _, with_draws = six_d.predict_images(s, n_particles=2000, return_std=True)
    _, members = six_d.predict_images(s, n_particles=2000, return_std=True, n_draws=0)
    assert float((with_draws - members).min()) >= -1e-7
    assert float(with_draws.max()) > float(members.max())  # the posterior widens
    flat = copy.copy(six_d)
    flat.info = dict(six_d.info)
    unc = six_d.uncertainty
    unc.theta_cov = torch.zeros_like(unc.theta_cov)
    unc.centroid_cov = torch.zeros_like(unc.centroid_cov)
    flat.info["uncertainty"] = unc.to_dict()
    _, zero = flat.predict_images(s, n_particles=2000, return_std=True)
    # float32 images of ~1e-2 per pixel; the recolouring maps round-trip to ~1e-6
    torch.testing.assert_close(zero, members, rtol=0, atol=2e-5)


def test_linear_posterior_survives_an_exactly_fitted_group() -> None:
    # 3 rows, 10 parameters: the residual lies in the design's column space, so
    # the fitted error scale collapses (weights ~1e12 and more) and I + A^T W A
    # is singular to machine precision at that scale: an LU inverse failed
    # (a 3-step reconstruction hit it) or lost the prior of the unseen
    # directions (3.9997 here). The posterior must stay finite, the 7 unseen
    # directions keep their prior exactly and the 3 seen ones shrink.
    g = torch.Generator().manual_seed(0)
    a = torch.randn(3, 10, generator=g, dtype=torch.float64)
    residual = a @ torch.randn(10, generator=g, dtype=torch.float64)
    prior = torch.full((10,), 2.0, dtype=torch.float64)
    cov, shift, *_ = linear_posterior(
        a, residual, torch.ones(3, dtype=torch.float64), prior
    )
    assert torch.isfinite(cov).all() and torch.isfinite(shift).all()
    assert torch.allclose(cov, cov.T)
    vals = torch.linalg.eigvalsh(cov)
    assert vals.min() > -1e-9  # positive semi-definite up to round-off
    unseen = torch.full((7,), 4.0, dtype=torch.float64)
    assert torch.allclose(vals[-7:], unseen, rtol=1e-9)
    assert vals[:3].max() < 1e-6


def test_psf_excess_is_what_the_model_images_add_over_a_histogram(small_scan) -> None:
    # physics: a point spread adds its variance to an image's second moments.
    # The forward model deposits with cloud-in-cell (1/6 pixel^2) even when
    # blur_pixels asks for the 1/12 pixel^2 of nearest-pixel histograms, so
    # its images of the SAME particles are wider than a histogram by exactly
    # psf_excess (what analyse_moments removes before comparing moments).
    from diffaccel.reconstruction import ScreenForwardModel
    from diffaccel.reconstruction.pipeline import psf_excess

    fwd = ScreenForwardModel.from_dataset(small_scan, blur_pixels=(1 / 12) ** 0.5)
    g = torch.Generator().manual_seed(5)
    beam = torch.randn(200_000, 6, generator=g, dtype=F64) * 1e-3
    sets = small_scan.settings[:3]
    model = fwd.images(beam, sets)
    at = fwd.track_to_screen(beam, sets)
    xs, ys = fwd.screen.pixel_centers(dtype=F64)
    psx, psy = fwd.screen.pixel_size
    ix = torch.round((at[..., 0] - xs[0]) / psx).long()
    iy = torch.round((at[..., 2] - ys[0]) / psy).long()
    h, w = len(ys), len(xs)
    keep = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
    hist = torch.zeros(len(sets), h * w, dtype=F64)
    for k in range(len(sets)):
        hist[k].index_add_(
            0, (iy[k] * w + ix[k])[keep[k]], torch.ones(int(keep[k].sum()), dtype=F64)
        )
    hist = hist.reshape(-1, h, w)
    dm = image_moments(model, xs, ys) - image_moments(hist, xs, ys)
    ex, ey = psf_excess(fwd)
    assert ex == pytest.approx(psx**2 / 12) and ey == pytest.approx(psy**2 / 12)
    # spots of 1-2.4 pixels: the histogram's rounding error e adds 1/12 plus
    # 2 cov(x, e), which scatters by ~2 sigma 0.29 / sqrt(N) ~ 4 % of 1/12
    # at N = 200k (12 % at 20k): 15 % is 3.5 of that scatter; a wrong excess
    # (0 or 1/6 pixel^2) is 100 % off
    want = torch.full((3,), 1.0, dtype=F64)
    torch.testing.assert_close(dm[:, 2] / ex, want, rtol=0.15, atol=0)
    torch.testing.assert_close(dm[:, 4] / ey, want, rtol=0.15, atol=0)
    fwd1 = ScreenForwardModel.from_dataset(small_scan, blur_pixels=1.0)
    assert psf_excess(fwd1) == (0.0, 0.0)
