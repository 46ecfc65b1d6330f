"""Quadratic holds on the covariance: the whole covariance held at a target."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from diffaccel.reconstruction import ReconstructionConfig, reconstruct
from diffaccel.reconstruction.hold import CovarianceHold
from diffaccel.reconstruction.initial import fit_gaussian
from diffaccel.reconstruction.pipeline import refit_members
from diffaccel.reconstruction.unseen import member_moments


def _moments(x: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """Plain moment matrix ``mean(z1 z1^T)`` of ``z1 = (x / scale, 1)``."""
    z1 = torch.cat([x / scale, torch.ones(x.shape[0], 1, dtype=x.dtype)], 1)
    return z1.T @ z1 / x.shape[0]


def _chirped_cov() -> torch.Tensor:
    """A beam with an x-px correlation, an x-z tilt and a strong z-pz chirp
    (correlation 0.95) [Bmad units]."""
    # x = a, px = -0.9 a + 0.44 b, y = c, py = 0.5 c + d, z = 0.4 a + 0.9 e,
    # pz = 3 z + f (unit-variance a ... f)
    m = torch.tensor(
        [
            [1.0, 0, 0, 0, 0, 0],
            [-0.9, 0.44, 0, 0, 0, 0],
            [0, 0, 1.0, 0, 0, 0],
            [0, 0, 0.5, 1.0, 0, 0],
            [0.4, 0, 0, 0, 0.9, 0],
            [1.2, 0, 0, 0, 2.7, 1.0],
        ],
        dtype=torch.float64,
    )
    sig = torch.tensor([1e-3, 2e-4, 8e-4, 1e-4, 1e-3, 5e-3], dtype=torch.float64)
    return (m @ m.T) * sig[:, None] * sig[None, :]


def _white(n: int, seed: int) -> torch.Tensor:
    """``(n, 6)`` samples of exactly zero mean and unit covariance (N - 1)."""
    w = torch.randn(n, 6, generator=torch.Generator().manual_seed(seed))
    w = w.double() - w.double().mean(0)
    return w @ torch.linalg.cholesky(torch.cov(w.T)).inverse().T


def test_covariance_hold_is_zero_at_the_target_and_whitened() -> None:
    target = _chirped_cov()
    scale = target.diagonal().sqrt().float().double()  # the hold keeps float32
    n = 20000
    white = _white(n, 0)
    chol = torch.linalg.cholesky(target)
    hold = CovarianceHold(target, 100.0, scale, n)
    assert hold.ready and not hold.refreshes
    assert float(hold.penalty(_moments(white @ chol.T, scale))) < 1e-16
    # every size 1 % larger (covariance x 1.0201): W S W = 1.0201 I, six
    # diagonal entries of 0.0201
    grown = white @ chol.T * 1.01
    assert float(hold.penalty(_moments(grown, scale))) == pytest.approx(
        100.0 * 6 * 0.0201**2, rel=1e-9
    )

    # whitened by the beam: the same 0.01 change of the z-pz correlation
    # weighs (1 - r^2)^-1 ~ 10x more at r = 0.95 than at r = 0 (where the
    # whitened deviation is the correlation's change itself)
    def moved(cov: torch.Tensor) -> float:
        c = cov.clone()
        c[4, 5] = c[5, 4] = c[4, 5] + 0.01 * (c[4, 4] * c[5, 5]).sqrt()
        h = CovarianceHold(cov, 1.0, scale, n)
        return float(h.penalty(_moments(white @ torch.linalg.cholesky(c).T, scale)))

    plain = torch.diag(target.diagonal())
    assert moved(plain) == pytest.approx(0.01**2, rel=1e-6)
    assert moved(target) > 50 * moved(plain)


def test_covariance_hold_surrogate_has_the_penalty_gradient() -> None:
    target = _chirped_cov()
    scale = target.diagonal().sqrt().float().double()
    n = 3000
    x = _white(n, 1) @ torch.linalg.cholesky(target * 1.02).T
    hold = CovarianceHold(target, 10.0, scale, n)
    x.requires_grad_(True)
    (exact,) = torch.autograd.grad(hold.penalty(_moments(x, scale)), x)
    (grad,) = torch.autograd.grad(hold.surrogate(x, _moments(x, scale)), x)
    assert float(exact.abs().max()) > 0
    tol = 1e-10 * float(exact.abs().max())
    assert torch.allclose(grad, exact, rtol=1e-8, atol=tol)
    # split across two "processes": the shares' gradients add up to the whole
    m = _moments(x.detach(), scale)
    parts = [
        torch.autograd.grad(hold.surrogate(x[s], m), x)[0]
        for s in (slice(0, 1000), slice(1000, n))
    ]
    assert torch.allclose(parts[0] + parts[1], exact, rtol=1e-8, atol=tol)


@pytest.mark.parametrize(
    ("target", "weight", "message"),
    [
        (torch.eye(5), 1.0, r"\(6, 6\)"),
        (torch.full((6, 6), float("nan")), 1.0, "finite"),
        (-torch.eye(6), 1.0, "positive definite"),
        (torch.eye(6), -1.0, "weight"),
        (torch.eye(6), float("inf"), "weight"),
    ],
    ids=["shape", "nan", "not-positive", "negative-weight", "inf-weight"],
)
def test_covariance_hold_refuses_bad_input(target, weight, message) -> None:
    with pytest.raises(ValueError, match=message):
        CovarianceHold(target, weight, torch.ones(6), 100)


@pytest.fixture(scope="module")
def placed(small_awa6d):
    """A small AWA 6D run's placed members (no refit) and its training inputs."""
    data = small_awa6d
    cfg = ReconstructionConfig(
        dims=6,
        n_particles=1024,
        steps=60,
        snapshots=1,
        burn_in=0,
        refit_steps=0,
        polish_moments=False,  # the members as placed: the refit's input
    )
    result = reconstruct(data, cfg, uncertainty=False)
    names = result.scan_names
    forwards = [result.forwards[n] for n in names]
    measured = [data[n].mean_images() for n in names]
    settings = [data[n].settings for n in names]
    maps = [f.transfer_maps(s) for f, s in zip(forwards, settings, strict=True)]
    guess = fit_gaussian(forwards, measured, settings, maps=maps)
    return result, forwards, measured, settings, guess, maps


def _whitened_change(after: dict, before: dict) -> float:
    """Largest entry of ``W (S_after - S_before) W``, ``W = S_before^-1/2``."""
    _, s0 = member_moments(before, 6, 48, 2, 20000, 0)
    _, s1 = member_moments(after, 6, 48, 2, 20000, 0)
    w, v = torch.linalg.eigh(s0)
    root = v @ torch.diag(w.rsqrt()) @ v.T
    return float((root @ (s1 - s0) @ root).abs().max())


def test_the_refit_keeps_the_placed_covariance(placed) -> None:
    result, forwards, measured, settings, guess, maps = placed
    change = {}
    for w in (0.0, 1e4):
        # the probe (a separate move along px-pz) off: the hold alone
        cfg = replace(result.config, refit_steps=40, refit_hold=w, probe_unseen=0.0)
        refit = refit_members(
            result.snapshots, forwards, measured, settings, guess, cfg, maps
        )
        change[w] = _whitened_change(refit[0], result.snapshots[0])
    # 40 steps: a free refit moves the covariance 0.056-0.071 (whitened units,
    # by CPU) from the placed one, the held refit 0.0037-0.0038 (data seeds 3,
    # 4: 0.045 -> 0.0034, 0.065 -> 0.0025)
    assert change[0.0] > 0.03, change
    assert change[1e4] < 0.2 * change[0.0], change
