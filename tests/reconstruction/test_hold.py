"""The prior term on the unseen directions: what its gradient moves.

Its value and the surrogate's gradient: tests/reconstruction/test_unseen.py.
"""

from __future__ import annotations

import pytest
import torch
from test_unseen import _beam_cov, _change, _maps, _screen_moments

from diffaccel.reconstruction.unseen import (
    UnseenHold,
    place_unseen,
    unseen_directions,
)


def _moments(x: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """Plain moment matrix ``mean(z1 z1^T)`` of ``z1 = (x / scale, 1)``."""
    z1 = torch.cat([x / scale, torch.ones(x.shape[0], 1, dtype=x.dtype)], 1)
    return z1.T @ z1 / x.shape[0]


def _white(n: int, seed: int) -> torch.Tensor:
    """``(n, 6)`` samples of exactly zero mean and unit covariance (N - 1)."""
    w = torch.randn(n, 6, generator=torch.Generator().manual_seed(seed))
    w = w.double() - w.double().mean(0)
    return w @ torch.linalg.cholesky(torch.cov(w.T)).inverse().T


def _off_prior(maps: list[torch.Tensor]) -> torch.Tensor:
    """The test beam moved 0.15 (correlation units) off its prior point along
    both unseen directions."""
    cov = _beam_cov()
    v = unseen_directions(maps, cov)
    prior = place_unseen(cov, v)
    sig = prior.diagonal().sqrt()
    unit = torch.stack([d / (d / (sig[:, None] * sig[None, :])).norm() for d in v])
    return prior + 0.15 * unit.sum(0)


def _held(maps: list[torch.Tensor], cov: torch.Tensor, n: int, weight: float):
    scale = cov.diagonal().sqrt().float().double()  # the hold keeps float32
    x = _white(n, 1) @ torch.linalg.cholesky(cov).T
    hold = UnseenHold(maps, weight, scale, n)
    hold.update(_moments(x, scale))
    return hold, x, scale


def test_prior_term_is_flat_along_every_direction_the_screens_see() -> None:
    """The term depends on the covariance only through its coordinates along
    the unseen directions (correlation units), which are orthogonal to every
    direction the screens see: a change that moves the screens' moments leaves
    the term as it is, so the term decides nothing the images see, and a move
    along an unseen direction changes it one to one."""
    maps = _maps()
    off = _off_prior(maps)
    hold, _, _ = _held(maps, off, 20000, 1.0)

    def t(cov: torch.Tensor) -> torch.Tensor:
        return (hold.q * cov).sum((1, 2)) - hold.b

    sig = off.diagonal().sqrt()
    unit = sig[:, None] * sig[None, :]
    iu = tuple(torch.triu_indices(6, 6))
    v = unseen_directions(maps, off)
    u = torch.stack([(d / unit)[iu] for d in v])  # (2, 21), orthonormal
    assert torch.allclose(u @ u.T, torch.eye(2, dtype=torch.float64), atol=1e-12)
    before = _screen_moments(maps, off)
    for i, j in ((5, 5), (4, 4), (4, 5), (1, 5)):
        c = torch.zeros(6, 6, dtype=torch.float64)
        c[i, j] = 0.15
        c = c[iu] - u.T @ (u @ c[iu])  # its part the screens see
        e = torch.zeros(6, 6, dtype=torch.float64)
        e[iu] = c * unit[iu]
        seen = e + e.T - torch.diag(e.diagonal())
        assert _change(_screen_moments(maps, off + seen), before) > 0.01
        assert float((t(off + seen) - t(off)).abs().max()) < 1e-12
    for k, d in enumerate(v):
        assert float(t(off + 0.1 * d)[k] - t(off)[k]) == pytest.approx(0.1, rel=1e-9)


def test_prior_term_holds_nothing_where_nothing_is_unseen() -> None:
    """A quadrupole scan alone (no cavity, no dipole) sees neither z nor pz:
    their prior widths set them, and the term has no direction to hold."""
    maps = [m.clone() for m in _maps()]
    for m in maps:
        m[:, :4, 4:6] = 0.0  # no dispersion, no streak
        m[:, 4:6, :4] = 0.0
    hold, x, scale = _held(maps, _beam_cov(), 2000, 10.0)
    assert hold.q.shape[0] == 0
    assert float(hold.surrogate(x, _moments(x, scale))) == 0.0
