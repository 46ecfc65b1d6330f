"""Unseen longitudinal directions of the AWA 6D layout and their prior point."""

from __future__ import annotations

import pytest
import torch

from diffaccel.data.synthetic import AWA6D_BEAMLINES
from diffaccel.dynamics import Beamline
from diffaccel.reconstruction import ScreenForwardModel
from diffaccel.reconstruction.unseen import (
    UnseenHold,
    place_unseen,
    traded_pairs,
    transport_map,
    unseen_directions,
)

NAMES = ["SCAN_QUAD.k1", "SCAN_TDC.voltage"]


def _maps() -> list[torch.Tensor]:
    k1 = torch.tensor([-12.0, -6.0, 0.0, 6.0, 12.0], dtype=torch.float64)
    sets = torch.stack(
        torch.meshgrid(
            k1, torch.tensor([0.0, 4e6], dtype=torch.float64), indexing="ij"
        ),
        -1,
    )
    sets = sets.reshape(-1, 2).to(torch.float64)
    out = []
    for spec in AWA6D_BEAMLINES.values():
        spec = [dict(e) for e in spec]
        spec[-1].update(shape=[32, 32], pixel_size=[1e-3, 1e-3])
        fwd = ScreenForwardModel(Beamline.from_spec(spec), NAMES, 43.36e6)
        out.append(fwd.transfer_maps(sets))
    return out


def _beam_cov() -> torch.Tensor:
    """A correlated 6D covariance in the AWA 6D scale (chirp, x-z tilt)."""
    sig = torch.tensor([5e-4, 2.6e-4, 5e-4, 2.6e-4, 8e-4, 2e-3], dtype=torch.float64)
    c = torch.eye(6, dtype=torch.float64)
    for (i, j), r in {(0, 1): -0.5, (2, 3): 0.6, (4, 5): 0.7, (0, 4): 0.3}.items():
        c[i, j] = c[j, i] = r
    return c * sig[:, None] * sig[None, :]


def _screen_moments(maps: list[torch.Tensor], cov: torch.Tensor) -> torch.Tensor:
    r = torch.cat(maps)[:, :6, :6]
    m = r @ cov @ r.transpose(1, 2)
    return torch.stack([m[:, 0, 0], m[:, 2, 2], m[:, 0, 2]])


def _change(after: torch.Tensor, before: torch.Tensor) -> float:
    """Largest change of a screen moment relative to the spot size^2 there."""
    size = torch.stack([before[0], before[1], (before[0] * before[1]).sqrt()])
    return float(((after - before).abs() / size).max())


def test_awa6d_has_two_unseen_directions_that_leave_the_moments() -> None:
    maps, cov = _maps(), _beam_cov()
    v = unseen_directions(maps, cov)
    # pz variance against the px-pz covariance, z variance against py-z
    assert v.shape == (2, 6, 6)
    sig = cov.diagonal().sqrt()
    entries = [(i, j) for i in range(6) for j in range(i, 6)]

    def trade(d: torch.Tensor) -> frozenset:
        size = {e: abs(float(d[e] / (sig[e[0]] * sig[e[1]]))) for e in entries}
        return frozenset(sorted(entries, key=lambda e: -size[e])[:2])

    assert {trade(d) for d in v} == {
        frozenset({(1, 5), (5, 5)}),
        frozenset({(3, 4), (4, 4)}),
    }
    before = _screen_moments(maps, cov)
    for d in v:
        # 0.2 in correlation units along the direction
        step = 0.2 / float((d / (sig[:, None] * sig[None, :])).abs().max())
        after = _screen_moments(maps, cov + step * d)
        # second-order terms of the thick quadrupole only: 1e-4 .. 4e-3 of what
        # the moments see (singular values), a 20 % correlation change moves
        # no moment by more than 0.5 % of the spot size^2 (0.23 % measured)
        assert _change(after, before) < 5e-3
    # a direction the scans see (the pz variance alone) changes them 20x more
    e = torch.zeros(6, 6, dtype=torch.float64)
    e[5, 5] = 0.2 * float(cov[5, 5])
    seen = _screen_moments(maps, cov + e)
    assert _change(seen, before) > 0.05


def _partial(cov: torch.Tensor, i: int, j: int) -> float:
    """Partial correlation of coordinates i, j given the other four."""
    p = torch.linalg.inv(cov)
    return float(p[i, j] / (p[i, i] * p[j, j]).sqrt())


def test_pair_placement_is_unique_and_zeroes_the_traded_partial_correlations() -> None:
    maps, cov = _maps(), _beam_cov()
    cov[1, 5] = cov[5, 1] = 0.3 * float((cov[1, 1] * cov[5, 5]).sqrt())  # px-pz
    v = unseen_directions(maps, cov)
    assert sorted(traded_pairs(v, cov)) == [(1, 5), (3, 4)]  # px-pz, py-z
    assert abs(_partial(cov, 1, 5)) > 0.1
    placed = place_unseen(cov, v)  # the default prior
    assert abs(_partial(placed, 1, 5)) < 1e-9
    assert abs(_partial(placed, 3, 4)) < 1e-9
    # a move along the directions only: every screen moment kept (see above)
    before = _screen_moments(maps, cov)
    assert _change(_screen_moments(maps, placed), before) < 5e-3
    sig = cov.diagonal().sqrt()
    moved = cov + 0.2 / float((v[1] / (sig[:, None] * sig[None, :])).abs().max()) * v[1]
    again = place_unseen(moved, v)
    assert ((again - placed) / (sig[:, None] * sig[None, :])).abs().max() < 1e-6


def test_pair_prior_keeps_a_chirped_beam_that_has_no_traded_correlation() -> None:
    """A strong chirp (z-pz 0.9) with pz independent of px and z of py given
    the rest is a fixed point of the prior: the seen z-pz partial correlation
    is not weighed in."""
    maps, cov = _maps(), _beam_cov()
    sig = cov.diagonal().sqrt()
    cov[4, 5] = cov[5, 4] = 0.9 * float(sig[4] * sig[5])
    # zero px-pz and py-z partial correlations: pz and z regressed on the rest
    v = unseen_directions(maps, cov)
    cov = place_unseen(cov, v)
    assert abs(_partial(cov, 1, 5)) < 1e-9 and abs(_partial(cov, 3, 4)) < 1e-9
    assert abs(_partial(cov, 4, 5)) > 0.5
    v = unseen_directions(maps, cov)
    unit = sig[:, None] * sig[None, :]
    assert ((place_unseen(cov, v) - cov) / unit).abs().max() < 1e-6


def _quad_scan_maps() -> list[torch.Tensor]:
    """A quadrupole scan alone (no cavity, no dispersion): 5 settings."""
    spec = [
        {"type": "Quadrupole", "name": "Q", "length": 0.1, "k1": 0.0},
        {"type": "Drift", "name": "D", "length": 1.0},
        {"type": "Screen", "name": "S", "shape": [32, 32], "pixel_size": [1e-3, 1e-3]},
    ]
    fwd = ScreenForwardModel(Beamline.from_spec(spec), ["Q.k1"], 43e6)
    return [fwd.transfer_maps(torch.linspace(-10, 10, 5, dtype=torch.float64)[:, None])]


def test_no_directions_without_dispersion_or_cavity() -> None:
    assert unseen_directions(_quad_scan_maps(), _beam_cov()).shape[0] == 0


def test_transport_map_reaches_the_target() -> None:
    cov = _beam_cov()
    target = cov.clone()
    target[5, 5] *= 1.3
    target[1, 5] = target[5, 1] = 0.2 * float((cov[1, 1] * cov[5, 5]).sqrt())
    a = transport_map(cov, target)
    assert torch.allclose(
        a @ cov @ a.T, target, rtol=1e-10, atol=1e-12 * float(target.abs().max())
    )
    # optimal transport between Gaussians: symmetric in whitened units
    d = cov.diagonal().sqrt()
    w = a * (d[None, :] / d[:, None])
    assert torch.allclose(w, w.T, atol=1e-10)


def _moments(x: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    z1 = torch.cat([x / scale, torch.ones(x.shape[0], 1, dtype=x.dtype)], 1)
    return z1.T @ z1 / x.shape[0]


def test_unseen_hold_is_zero_at_the_prior_and_measures_the_displacement() -> None:
    maps = _maps()
    cov = _beam_cov()
    directions = unseen_directions(maps, cov)
    prior = place_unseen(cov, directions)
    scale = cov.diagonal().sqrt().float().double()  # the hold keeps float32
    g = torch.Generator().manual_seed(2)
    n = 20000
    white = torch.randn(n, 6, generator=g, dtype=torch.float64)
    white = (white - white.mean(0)) @ torch.linalg.cholesky(
        torch.cov(white.T)
    ).inverse().T  # exactly unit covariance (N - 1)
    x = white @ torch.linalg.cholesky(prior).T
    hold = UnseenHold(maps, 100.0, scale, n)
    hold.update(_moments(x, scale))
    assert hold.q.shape[0] == 2
    assert float(hold.penalty(_moments(x, scale))) < 1e-16
    # a move of 0.05 (correlation units) along one of the prior's directions
    moved = prior + 0.05 * unseen_directions(maps, prior)[0]
    y = white @ torch.linalg.cholesky(moved).T
    assert float(hold.penalty(_moments(y, scale))) == pytest.approx(
        100.0 * 0.05**2, rel=1e-6
    )


def test_unseen_hold_surrogate_has_the_penalty_gradient() -> None:
    maps = _maps()
    cov = _beam_cov()
    scale = cov.diagonal().sqrt().float().double()
    g = torch.Generator().manual_seed(3)
    n = 3000
    x = (
        torch.randn(n, 6, generator=g, dtype=torch.float64)
        @ torch.linalg.cholesky(cov).T
    )
    hold = UnseenHold(maps, 50.0, scale, n)
    hold.update(_moments(x, scale) * 1.01)  # some other prior point
    x.requires_grad_(True)
    (exact,) = torch.autograd.grad(hold.penalty(_moments(x, scale)), x)
    (grad,) = torch.autograd.grad(hold.surrogate(x, _moments(x, scale)), x)
    assert float(exact.abs().max()) > 0
    assert torch.allclose(grad, exact, rtol=1e-8, atol=1e-10 * float(exact.abs().max()))
    # split across two "processes": the shares' gradients are the whole one's
    m = _moments(x.detach(), scale)
    parts = [
        torch.autograd.grad(hold.surrogate(x[s], m), x)[0]
        for s in (slice(0, 1200), slice(1200, n))
    ]
    tol = 1e-10 * float(exact.abs().max())
    assert torch.allclose(parts[0] + parts[1], exact, rtol=1e-8, atol=tol)


def test_unseen_hold_refuses_a_bad_weight() -> None:
    for w in (-1.0, float("nan")):
        with pytest.raises(ValueError, match="weight"):
            UnseenHold(_maps(), w, torch.ones(6), 100)
