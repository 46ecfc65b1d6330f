from __future__ import annotations

import pytest
import torch

from diffaccel.dynamics.linalg import lstsq


def _rank_deficient(seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(24, 19, generator=g, dtype=torch.float64)
    # 21 unknowns, two columns repeating combinations of the others (rank 19)
    a = torch.cat([a, a[:, :2] - a[:, 2:4], 0.5 * a[:, 5:6]], 1)
    return a, torch.randn(24, 1, generator=g, dtype=torch.float64)


def test_lstsq_gives_the_same_bits_on_every_call() -> None:
    # torch's default CPU driver (gelsy) returned 8 different bit patterns in
    # 8 calls on these inputs (torch 2.13, MKL)
    a, b = _rank_deficient(0)
    first = lstsq(a, b)
    for _ in range(8):
        assert torch.equal(lstsq(a.clone(), b.clone()), first)


def test_lstsq_is_the_minimum_norm_solution() -> None:
    a, b = _rank_deficient(1)
    x = lstsq(a, b)
    expected = torch.linalg.pinv(a) @ b
    assert torch.allclose(x, expected, rtol=0, atol=1e-10 * float(expected.abs().max()))
    # and an exact solution of a consistent full-rank system
    g = torch.Generator().manual_seed(2)
    full = torch.randn(30, 6, generator=g, dtype=torch.float64)
    truth = torch.randn(6, 2, generator=g, dtype=torch.float64)
    assert torch.allclose(lstsq(full, full @ truth), truth, rtol=0, atol=1e-12)


def test_lstsq_refuses_non_finite_systems() -> None:
    a, b = _rank_deficient(3)
    a[0, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN or infinite"):
        lstsq(a, b)
    with pytest.raises(ValueError, match="NaN or infinite"):
        lstsq(torch.ones(3, 2, dtype=torch.float64), torch.full((3, 1), float("inf")))
