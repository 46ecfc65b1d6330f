from __future__ import annotations

import math

import pytest
import torch

from diffaccel.reconstruction import (
    cyclic_cosine_lr,
    gaussian_entropy,
    image_distance,
    penalty_schedule,
    robust_covariance,
)
from diffaccel.reconstruction.losses import image_penalty, off_screen_allowance


def _gauss(n: int = 20_000, d: int = 4, seed: int = 0) -> torch.Tensor:
    return torch.randn(n, d, generator=torch.Generator().manual_seed(seed))


def test_entropy_of_gaussian_equals_half_logdet() -> None:
    a = torch.tensor([[2.0, 0, 0, 0], [0.5, 1.0, 0, 0], [0, 0, 3.0, 0], [0, 0, 1, 0.5]])
    x = _gauss() @ a.T
    expected = 0.5 * torch.logdet(a @ a.T).item()
    # sampling error of log det ~ sqrt(2 d / N) / 2 = 0.01 at N = 20k: allow 4x
    assert gaussian_entropy(x, radius=None).item() == pytest.approx(expected, abs=0.04)


def test_robust_entropy_shifts_by_log_scale() -> None:
    x = _gauss()
    h1 = gaussian_entropy(x).item()
    h2 = gaussian_entropy(3.0 * x).item()
    assert h2 - h1 == pytest.approx(4 * math.log(3.0), abs=1e-9)  # round-off only


def test_far_halo_does_not_raise_the_robust_entropy() -> None:
    x = _gauss()
    halo = x.clone()
    halo[:200] *= 1000.0  # 1 % of the beam pushed 1000 sigma out
    plain = gaussian_entropy(halo, radius=None) - gaussian_entropy(x, radius=None)
    robust = gaussian_entropy(halo) - gaussian_entropy(x)
    assert plain > 10.0  # the Gaussian bound is gamed ...
    assert abs(float(robust)) < 0.05  # ... the robust one is not (the core is kept)


def test_far_halo_gets_no_entropy_gradient() -> None:
    x = _gauss(n=2000).double()
    x[:10] *= 1000.0
    x.requires_grad_(True)
    gaussian_entropy(x).backward()
    assert x.grad[:10].abs().max() < 1e-12 * x.grad[10:].abs().max()


def test_entropy_gradcheck_float64() -> None:
    x = _gauss(n=12, d=3, seed=1).double().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: gaussian_entropy(t, radius=None), (x,))
    # robust weights are constants for the gradient: check the function they define
    w_fixed = robust_covariance(x.detach())
    assert torch.isfinite(w_fixed).all()


@pytest.mark.parametrize("kind", ["l1", "l2", "kl"], ids=["l1", "l2", "kl"])
def test_image_distance_zero_for_identical_and_positive_otherwise(kind: str) -> None:
    m = torch.rand(3, 8, 8, generator=torch.Generator().manual_seed(0)) + 0.1
    m = m / m.sum((-2, -1), keepdim=True)
    s = m.roll(1, dims=-1)
    assert torch.allclose(image_distance(m, m, kind), torch.zeros(3), atol=1e-6)
    assert (image_distance(s, m, kind) > 1e-3).all()


def test_image_distance_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match="differ in shape"):
        image_distance(torch.zeros(2, 4, 4), torch.zeros(2, 4, 5))
    with pytest.raises(ValueError, match="image loss must be"):
        image_distance(torch.zeros(1, 4, 4), torch.zeros(1, 4, 4), "l3")  # type: ignore[arg-type]


def test_image_penalty_counts_mass_off_screen() -> None:
    m = torch.full((1, 4, 4), 1 / 16)
    # same shape, 30 % of the beam missing: penalty is exactly the missing fraction
    assert image_penalty(0.7 * m, m).item() == pytest.approx(0.3, abs=1e-6)
    allow = torch.tensor([0.1])
    assert image_penalty(0.7 * m, m, allowance=allow).item() == pytest.approx(0.2)


def test_off_screen_allowance_from_border() -> None:
    img = torch.zeros(2, 10, 10)
    img[0, 4:6, 4:6] = 0.25  # contained beam
    img[1, :, :] = 0.01  # flat: 64 % of the mass in the 2-pixel ring -> capped
    a = off_screen_allowance(img)
    assert a.tolist() == pytest.approx([0.0, 0.05])


def test_schedules() -> None:
    assert penalty_schedule(50, 100, 10.0, 1000.0) == pytest.approx(100.0)
    assert penalty_schedule(500, 100, 10.0, 1000.0) == 1000.0
    assert cyclic_cosine_lr(5, 10, 1.0, 0.0) == pytest.approx(0.5)
    assert cyclic_cosine_lr(9, 10, 1.0, 0.0) < 0.03
    with pytest.raises(ValueError, match="penalty weights"):
        penalty_schedule(0, 10, 0.0, 1.0)
