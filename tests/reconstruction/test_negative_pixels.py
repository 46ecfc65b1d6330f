"""Background-subtracted images keep their negative noise: the KL image term and
the image moments stay unbiased."""

from __future__ import annotations

import torch

from diffaccel.reconstruction.losses import ImagePenalty
from diffaccel.reconstruction.uncertainty import image_moments

H = W = 48
GRID = torch.arange(H, dtype=torch.float64) - (H - 1) / 2


def _gauss(sigma: float) -> torch.Tensor:
    g = torch.exp(-0.5 * (GRID / sigma) ** 2)
    img = g[:, None] * g[None, :]
    return img / img.sum()


def _noisy(seed: int = 0, sigma: float = 4.0, noise: float = 0.02) -> torch.Tensor:
    """Unit-sum beam plus zero-mean noise of ``noise`` times its peak, (1, H, W)."""
    gen = torch.Generator().manual_seed(seed)
    truth = _gauss(sigma)
    img = truth + noise * truth.max() * torch.randn(
        H, W, generator=gen, dtype=truth.dtype
    )
    return (img / img.sum())[None]


def _best_sigma(measured: torch.Tensor, offset: float) -> float:
    penalty = ImagePenalty(measured, "kl", offset=offset)
    sigmas = torch.linspace(3.0, 6.0, 301, dtype=torch.float64)
    values = torch.stack([penalty(_gauss(float(s))[None]) for s in sigmas])
    return float(sigmas[values.argmin()])


def test_kl_term_of_signed_images_is_finite_and_its_gradient_exact() -> None:
    m = _noisy()
    assert bool((m < 0).any())
    sim = (_gauss(4.5) + 1e-5)[None].requires_grad_(True)
    for offset in (0.0, 1e-6):
        penalty = ImagePenalty(m, "kl", offset=offset)
        value = penalty(sim)
        assert torch.isfinite(value)
        (grad,) = torch.autograd.grad(value, sim)
        # the same function written with autograd
        total = sim.sum((-2, -1), keepdim=True)
        s = sim / total
        s = s + offset if offset > 0 else s.clamp_min(1e-12)
        ref = -(m * s.log()).sum() + penalty.m_log_m + penalty.constants["kl_shift"]
        ref = ref + (1.0 - total.sum()).clamp_min(0.0)
        (ref_grad,) = torch.autograd.grad(ref, sim)
        torch.testing.assert_close(value, ref, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(grad, ref_grad, rtol=1e-9, atol=1e-12)


def test_non_negative_images_give_the_plain_kl() -> None:
    m = _gauss(4.0)[None]
    sim = _gauss(4.4)[None]
    value = ImagePenalty(m, "kl")(sim)
    mc, sc = m.clamp_min(1e-12), sim.clamp_min(1e-12)
    torch.testing.assert_close(value, (mc * (mc / sc).log()).sum(), rtol=1e-12, atol=0)


def test_signed_noise_leaves_the_fitted_width_unbiased() -> None:
    """Noise of 2 % of the peak: the signed image's best width is the beam's
    (within 1 %, over seeds); the same image clipped at 0 fits a wider beam."""
    signed, clipped = [], []
    for seed in range(4):
        m = _noisy(seed)
        signed.append(_best_sigma(m, 1e-6))
        c = m.clamp_min(0.0)
        clipped.append(_best_sigma(c / c.sum(), 1e-6))
    mean_signed = sum(signed) / len(signed)
    mean_clipped = sum(clipped) / len(clipped)
    assert abs(mean_signed / 4.0 - 1.0) < 0.01, signed
    assert mean_clipped / 4.0 - 1.0 > 0.05, clipped


def test_image_moments_keep_the_negative_noise() -> None:
    """Second moments of signed noisy images average to the beam's (linear in
    the image); clipped at 0 they come out far too wide."""
    xs = ys = GRID * 1e-4  # [m]
    truth = image_moments(_gauss(4.0)[None], xs, ys)[0]
    signed = torch.stack([image_moments(_noisy(s), xs, ys)[0] for s in range(20)])
    clipped = torch.stack(
        [image_moments(_noisy(s).clamp_min(0), xs, ys)[0] for s in range(20)]
    )
    assert abs(float(signed[:, 2].mean() / truth[2]) - 1.0) < 0.05
    assert float(clipped[:, 2].mean() / truth[2]) - 1.0 > 0.3
