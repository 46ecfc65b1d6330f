"""Shared fixtures for the dynamics tests."""

from __future__ import annotations

from collections.abc import Callable

import pytest
import torch

SIZES = (1e-3, 1e-4, 1e-3, 1e-4, 1e-3, 1e-3)


def _gaussian_beam(
    n: int,
    sizes: tuple[float, ...] = SIZES,
    seed: int = 0,
    dtype: torch.dtype = torch.float64,
) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randn(n, 6, generator=g, dtype=dtype) * torch.tensor(
        sizes, dtype=dtype
    )


@pytest.fixture
def make_beam() -> Callable[..., torch.Tensor]:
    """Factory: uncorrelated Gaussian beam ``(n, 6)`` with rms ``sizes``."""
    return _gaussian_beam
