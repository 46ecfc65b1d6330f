from __future__ import annotations

import math

import pytest
import torch

from diffaccel.reconstruction import (
    beam_moments,
    image_errors,
    moment_errors,
    sliced_wasserstein,
)


def _beam(seed: int = 0, n: int = 10_000) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    sig = torch.tensor([1e-3, 2e-4, 2e-3, 1e-4, 1e-3, 1e-3], dtype=torch.float64)
    return torch.randn(n, 6, generator=g, dtype=torch.float64) * sig


def test_moments_of_an_uncorrelated_beam() -> None:
    m = beam_moments(_beam())
    # emittance = sigma_x sigma_px for an uncorrelated beam; sampling: ~1 % at 10k
    assert float(m["emit_x"]) == pytest.approx(2e-7, rel=0.03)
    assert float(m["emit_y"]) == pytest.approx(2e-7, rel=0.03)
    assert float(m["beta_x"]) == pytest.approx(5.0, rel=0.03)
    assert abs(float(m["alpha_x"])) < 0.05


def test_moment_errors_vanish_for_identical_beams() -> None:
    b = _beam()
    e = moment_errors(b, b)
    assert all(abs(v) < 1e-12 for k, v in e.items() if not math.isnan(v))


def test_moment_errors_of_a_scaled_beam() -> None:
    b = _beam()
    e = moment_errors(b * 1.1, b)
    assert e["rms_x"] == pytest.approx(0.1, abs=1e-9)
    assert e["emit_x"] == pytest.approx(0.21, abs=1e-9)  # emittance ~ scale^2


def test_sliced_wasserstein() -> None:
    a, b = _beam(0), _beam(1)
    g = torch.Generator().manual_seed(0)
    same = float(sliced_wasserstein(a, b, generator=g))
    shifted = b.clone()
    shifted[:, 0] += 1e-3  # one sigma in x
    far = float(sliced_wasserstein(shifted, b, generator=g))
    assert same < 0.05  # two 10k samples of one distribution
    assert far > 5 * same
    with pytest.raises(ValueError, match="clouds"):
        sliced_wasserstein(a, b[:, :4])


def test_image_errors() -> None:
    m = torch.full((2, 4, 4), 1 / 16)
    p = m.clone()
    p[0, 0, 0] += 0.1
    e = image_errors(p, m)
    assert e["relative_l1_per_setting"] == pytest.approx([0.1, 0.0])
    with pytest.raises(ValueError, match="must both be"):
        image_errors(p[0], m[0])


def test_bad_particles() -> None:
    with pytest.raises(ValueError, match="shape"):
        beam_moments(torch.zeros(10, 4))
    bad = _beam(n=10)
    bad[0, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        beam_moments(bad)


def test_sorted_quantiles_equal_torch_quantile() -> None:
    from diffaccel.reconstruction.metrics import _sorted_quantiles

    g = torch.Generator().manual_seed(0)
    v = torch.randn(999, 7, generator=g, dtype=torch.float64).sort(0).values
    q = torch.linspace(0.0, 1.0, 1001, dtype=torch.float64)
    assert torch.allclose(
        _sorted_quantiles(v, q), torch.quantile(v, q, dim=0), rtol=0, atol=1e-14
    )


def test_prediction_noise_l1_matches_the_l1_of_a_sampled_image():
    """The predicted L1 of an N-particle cloud-in-cell image against its
    expectation (an image of 200 times more particles) is the measured one."""
    from diffaccel.dynamics.images import cic_image
    from diffaccel.reconstruction.metrics import prediction_noise_l1

    g = torch.Generator().manual_seed(3)
    big = torch.randn(2, 2_000_000, generator=g, dtype=torch.float64)
    expected = cic_image(big[0], big[1], (60, 60), 0.15)[None]
    expected = expected / expected.sum()
    n = 10_000
    small = torch.randn(2, n, generator=g, dtype=torch.float64)
    image = cic_image(small[0], small[1], (60, 60), 0.15)[None]
    measured_l1 = float((image / image.sum() - expected).abs().sum())
    predicted = float(prediction_noise_l1(expected, 4.0 / 9.0, n)[0])
    assert predicted == pytest.approx(measured_l1, rel=0.05)


def test_shot_noise_l1_is_the_floor_of_the_shot_mean():
    """Five Poisson shots of a known image: the estimated floor equals the L1
    between their mean and the noise-free image."""
    from diffaccel.reconstruction.metrics import shot_noise_l1

    g = torch.Generator().manual_seed(4)
    y, x = torch.meshgrid(torch.arange(80.0), torch.arange(80.0), indexing="ij")
    truth = torch.exp(-((x - 40) ** 2 + (y - 38) ** 2) / (2 * 9.0**2))
    truth = truth / truth.sum()
    shots = torch.poisson((2e5 * truth).expand(3, 5, 80, 80).contiguous(), generator=g)
    floor = shot_noise_l1(shots)
    mean = shots.mean(1)
    actual = (mean / mean.sum((-2, -1), keepdim=True) - truth).abs().sum((-2, -1))
    assert floor.shape == (3,)
    assert floor.double().mean() == pytest.approx(float(actual.mean()), rel=0.05)
    assert shot_noise_l1(shots[:, :1]) is None
