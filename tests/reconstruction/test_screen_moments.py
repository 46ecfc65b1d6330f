"""The moment design: covariance to screen moments, shared by the initial fit,
the unseen directions, the prior report, the posterior and the design."""

from __future__ import annotations

import pytest
import torch

from diffaccel.reconstruction import ScreenForwardModel
from diffaccel.reconstruction import screen_moments as sm
from diffaccel.reconstruction.screen_moments import covariance_design, pair_indices
from diffaccel.reconstruction.unseen import unseen_directions

F64 = torch.float64


def _random_cov(d: int, g: torch.Generator) -> torch.Tensor:
    a = torch.randn(d, d, generator=g, dtype=F64)
    return a @ a.T + d * torch.eye(d, dtype=F64)


def _beam() -> torch.Tensor:
    rms = torch.tensor([1e-3, 1e-3, 1.2e-3, 0.8e-3, 1e-3, 2e-3], dtype=F64)
    corr = torch.eye(6, dtype=F64)
    corr[0, 1] = corr[1, 0] = -0.5
    corr[2, 3] = corr[3, 2] = 0.3
    corr[4, 5] = corr[5, 4] = 0.4
    return corr * rms[:, None] * rms[None, :]


@pytest.mark.parametrize("dims", [4, 6], ids=["4d", "6d"])
def test_covariance_design_equals_r_sigma_rt(dims: int) -> None:
    # physics: screen second moments of any beam are (R Sigma R^T) at (x, y)
    g = torch.Generator().manual_seed(0)
    r = torch.randn(5, 6, 6, generator=g, dtype=F64)
    sigma = torch.zeros(6, 6, dtype=F64)
    sigma[:dims, :dims] = _random_cov(dims, g)
    theta = torch.stack([sigma[i, j] for i, j in pair_indices(dims)])
    got = (covariance_design(r, dims) @ theta).reshape(5, 3)
    full = r @ sigma @ r.transpose(-1, -2)
    want = torch.stack([full[:, 0, 0], full[:, 0, 2], full[:, 2, 2]], -1)
    # float64 round-off of sums of a few hundred terms
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


def test_one_moment_design_for_the_guess_the_unseen_directions_and_the_posterior(
    small_awa6d,
):
    """The design of all 21 entries, its columns for a subset of coordinates
    (the initial fit's seen ones), and the unseen directions in its null space."""
    maps = [
        ScreenForwardModel.from_dataset(scan).transfer_maps(scan.settings).double()
        for _, scan in small_awa6d
    ]
    d = sm.moment_design(maps)
    per_scan = [sm.covariance_design(m[:, :6, :6], 6) for m in maps]
    assert torch.equal(d, torch.cat(per_scan))
    seen = [0, 1, 2, 3, 5]
    cols = [sm.ENTRIES.index(p) for p in sm.pair_indices(seen)]
    assert torch.equal(sm.covariance_design(maps[0], seen), per_scan[0][:, cols])
    cov = _beam()
    scaled, moments = sm.scaled_design(d, cov)
    largest = float(torch.linalg.svdvals(scaled)[0])
    directions = unseen_directions(maps, cov)
    assert directions.shape[0] == 2  # px-pz / pz-pz and py-z / z-z
    k = moments.reshape(-1, 3)
    scale = torch.stack([k[:, 0], (k[:, 0] * k[:, 2]).sqrt(), k[:, 2]], -1).reshape(-1)
    for direction in directions:
        # a unit step along it (correlation units) moves every screen moment by
        # less than the tolerance times what the best-seen direction moves
        moved = (d @ sm.theta_of(direction) / scale).abs().max()
        assert moved < 0.02 * largest
        iu = torch.tensor(sm.ENTRIES).T
        sym = sm.symmetric(sm.theta_of(direction), iu, 6)
        torch.testing.assert_close(sym, direction, rtol=0, atol=1e-18)
