from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from diffaccel.dynamics import Beamline
from diffaccel.reconstruction import (
    ScreenForwardModel,
    cyclic_cosine_lr,
    gaussian_entropy,
    image_distance,
    penalty_schedule,
    robust_covariance,
)
from diffaccel.reconstruction.losses import (
    ImagePenalty,
    MomentMatch,
    image_penalty,
    off_screen_allowance,
)


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


def _offset_kl(sim: torch.Tensor, meas: torch.Tensor, eps: float) -> torch.Tensor:
    """The offset KL penalty written with autograd: the reference."""
    total = sim.sum((-2, -1))
    s = sim / total.clamp_min(1e-6)[..., None, None] + eps
    m = meas.clamp_min(1e-12)
    shift = m.sum((-2, -1)) * math.log1p(m.shape[-2] * m.shape[-1] * eps)
    return (m * (m / s).log()).sum((-2, -1)) + shift + (1.0 - total).clamp_min(0.0)


def test_image_penalty_offset_value_and_gradient() -> None:
    g = torch.Generator().manual_seed(3)
    meas = torch.rand(3, 12, 10, generator=g, dtype=torch.float64) ** 3
    meas[:, :3] = 0.0
    meas = meas / meas.sum((-2, -1), keepdim=True)
    sim = meas + torch.rand(3, 12, 10, generator=g, dtype=torch.float64) / 300
    sim[:, :, :4] = 0.0  # zeros get a gradient through the offset
    sim = sim / sim.sum((-2, -1), keepdim=True)
    sim[1] *= 0.8  # 20 % off the screen
    eps = 2e-3
    sa = sim.clone().requires_grad_()
    ref = _offset_kl(sa, meas, eps).sum() / 3
    ref.backward()
    sb = sim.clone().requires_grad_()
    ours = ImagePenalty(meas, "kl", weight=1 / 3, offset=eps)(sb)
    ours.backward()
    assert float(ours.detach()) == pytest.approx(float(ref.detach()), rel=1e-12)
    torch.testing.assert_close(sb.grad, sa.grad, rtol=1e-10, atol=1e-14)
    assert (sb.grad[:, :, :4] != 0).all()  # no dead zeros with an offset
    # the shifted value stays >= 0 (Gibbs' inequality: s + eps sums to
    # 1 + H W eps) and is 0 where s + eps is proportional to m
    assert float(ImagePenalty(meas, "kl", offset=eps)(meas)) > 0.0
    flat = torch.full((1, 12, 10), 1 / 120, dtype=torch.float64)
    assert abs(float(ImagePenalty(flat, "kl", offset=eps)(flat))) < 1e-14


@pytest.mark.parametrize(
    ("kind", "offset", "match"),
    [
        ("kl", -1e-6, "finite and >= 0"),
        ("kl", math.nan, "finite"),
        ("l1", 1e-6, "'kl'"),
    ],
    ids=["negative", "nan", "not-kl"],
)
def test_image_penalty_offset_bad_input(kind: str, offset: float, match: str) -> None:
    meas = torch.full((1, 4, 4), 1 / 16)
    with pytest.raises(ValueError, match=match):
        ImagePenalty(meas, kind, offset=offset)


def test_offset_kl_puts_a_sampled_beam_at_its_true_size() -> None:
    # The KL distance of images of N sampled particles is biased towards wider
    # beams (E[log s_hat] < log s); the offset c kappa / N (training's
    # sampling_offset, c = 0.25) removes most of it. A 3 x 2 pixel Gaussian,
    # 2000 particles, measured with 400 000: least expected distance over
    # scale factors of the same 24 draws.
    line = Beamline.from_spec(
        [
            {"type": "Drift", "name": "D1", "length": 1.0},
            {"type": "Screen", "name": "S", "shape": [40, 40], "pixel_size": 1e-4},
        ]
    )
    fwd = ScreenForwardModel(line, ["D1.length"], 43e6, blur_pixels=1.0)
    g = torch.Generator().manual_seed(0)
    sig = torch.tensor([3e-4, 0, 2e-4, 0, 0, 0], dtype=torch.float64)
    setting = torch.tensor([[1.0]], dtype=torch.float64)

    def beam(n: int) -> torch.Tensor:
        return torch.randn(n, 6, generator=g, dtype=torch.float64) * sig

    meas = fwd.images(beam(400_000), setting)
    meas = meas / meas.sum()
    n = 2000
    draws = [beam(n) for _ in range(24)]
    scales = torch.linspace(0.96, 1.06, 11, dtype=torch.float64)

    def best_scale(offset: float) -> float:
        pen = ImagePenalty(meas, "kl", offset=offset)
        v = [sum(float(pen(fwd.images(r * b, setting))) for b in draws) for r in scales]
        a, b, _ = np.polyfit(scales.numpy(), np.array(v), 2)
        return float(-b / (2 * a))

    plain = best_scale(0.0)
    offset = best_scale(0.25 * fwd.pixel_kernel_sum_sq() / n)
    # seeds 0-3 (measured): plain 1.005-1.012, offset 0.994-1.001
    assert plain > 1.004
    assert abs(offset - 1.0) < 0.007
    assert abs(offset - 1.0) < abs(plain - 1.0)


def _gaussian_images(sx: float, sy: float, rho: float, n: int = 48) -> torch.Tensor:
    """One sum-normalised Gaussian image ``(1, n, n)``, rms in pixels, centred."""
    c = torch.arange(n, dtype=torch.float64) - (n - 1) / 2
    x, y = c[None, :], c[:, None]
    q = (x / sx) ** 2 - 2 * rho * x * y / (sx * sy) + (y / sy) ** 2
    img = torch.exp(-q / (2 * (1 - rho**2)))
    return (img / img.sum())[None]


def test_moment_term_is_zero_at_the_measured_images_and_quadratic_off_them() -> None:
    measured = _gaussian_images(4.0, 3.0, 0.5)
    match = MomentMatch(measured, torch.ones_like(measured), 2.0)
    sxx, syy, sxy = match.target[0].tolist()
    assert sxx == pytest.approx(16.0, rel=1e-3) and syy == pytest.approx(9.0, rel=1e-3)
    assert sxy == pytest.approx(0.5 * 12.0, rel=1e-3)
    assert float(match(measured)) < 1e-20
    # x 2 % wider: S_xx 4.04 % larger, S_xy 2 % larger (relative to sqrt(Sxx Syy))
    wider = _gaussian_images(4.08, 3.0, 0.5)
    expect = 2.0 * ((1.02**2 - 1) ** 2 + (0.02 * 0.5) ** 2)
    assert float(match(wider)) == pytest.approx(expect, rel=0.02)


def test_moment_term_counts_only_its_window_and_has_a_gradient() -> None:
    measured = _gaussian_images(4.0, 3.0, 0.0)
    window = torch.zeros_like(measured)
    window[:, 6:42, 6:42] = 1.0
    match = MomentMatch(measured, window, 1.0)
    noisy = measured.clone()
    noisy[:, 0, 0] += 0.05  # far outside the window: not counted
    assert float(match(noisy)) < 1e-20
    sim = _gaussian_images(4.2, 3.0, 0.0).requires_grad_(True)
    (grad,) = torch.autograd.grad(match(sim), sim)
    assert float(grad.abs().max()) > 0 and float(grad[:, 0, 0].abs()) == 0.0


def test_moment_term_gradient_is_the_derivative_of_its_value() -> None:
    # the written-out backward against finite differences (float64)
    g = torch.Generator().manual_seed(3)
    measured = torch.rand(3, 9, 11, generator=g, dtype=torch.float64)
    window = (torch.rand(3, 9, 11, generator=g) > 0.2).double()
    match = MomentMatch(measured, window, 1.7)
    sim = torch.rand(3, 9, 11, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(match, (sim,))
    # and equal to autograd through the moments themselves
    (written,) = torch.autograd.grad(match(sim), sim)
    r = (match.moments(sim) - match.target) / match.scale
    (auto,) = torch.autograd.grad(1.7 * (r * r).sum(), sim)
    assert torch.allclose(written, auto, rtol=1e-10, atol=1e-14)


@pytest.mark.parametrize(
    ("weight", "shape", "match"),
    [(-1.0, None, "moment weight"), (float("nan"), None, "moment weight"),
     (1.0, (1, 4, 4), "differ in shape")],
)  # fmt: skip
def test_moment_term_refuses_bad_input(weight, shape, match) -> None:
    measured = _gaussian_images(4.0, 3.0, 0.0)
    window = torch.ones(shape or measured.shape, dtype=measured.dtype)
    with pytest.raises(ValueError, match=match):
        MomentMatch(measured, window, weight)
