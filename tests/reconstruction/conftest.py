"""Small synthetic quad scans shared by the reconstruction tests."""

from __future__ import annotations

import pytest
import torch

from diffaccel.data import (
    MultiScanDataset,
    QuadScanDataset,
    make_synthetic_awa6d,
    make_synthetic_quad_scan,
)
from diffaccel.reconstruction import ScreenForwardModel


@pytest.fixture(scope="session")
def small_scan() -> QuadScanDataset:
    """6 settings of a correlated 6D beam on a 32 x 32 screen (1 mm pixels)."""
    return make_synthetic_quad_scan(
        "correlated",
        n_particles=4000,
        n_settings=6,
        k1_range=(-10.0, 10.0),
        screen_shape=(32, 32),
        pixel_size=(1e-3, 1e-3),
        seed=1,
    )


@pytest.fixture(scope="session")
def small_awa6d() -> MultiScanDataset:
    """The AWA 6D layout (5 quadrupole settings x TDC off/on, dipole off/on)
    of a correlated beam on 32 x 32 pixel screens."""
    return make_synthetic_awa6d(
        "correlated",
        n_particles=4000,
        k1_values=torch.linspace(-12.0, 12.0, 5),
        screen_shape=(32, 32),
        seed=2,
    )


@pytest.fixture()
def gaussian_beam() -> torch.Tensor:
    """4000 particles of an uncorrelated 4D Gaussian beam (z = pz = 0) [Bmad]."""
    g = torch.Generator().manual_seed(3)
    sig = torch.tensor([1.5e-3, 0.6e-3, 1.2e-3, 0.5e-3, 0.0, 0.0], dtype=torch.float64)
    return torch.randn(4000, 6, generator=g, dtype=torch.float64) * sig


@pytest.fixture(scope="session")
def awa6d_two_settings() -> tuple[list, list, list]:
    """``(forwards, images, settings)`` of the AWA 6D layout at two quadrupole
    settings (k1 = -6, 6): a rank-deficient Gaussian fit."""
    ms = make_synthetic_awa6d(
        n_particles=2000, k1_values=[-6.0, 6.0], screen_shape=(32, 32), seed=1
    )
    forwards = [ScreenForwardModel.from_dataset(s) for _, s in ms]
    images = [s.mean_images() for _, s in ms]
    settings = [s.settings for _, s in ms]
    return forwards, images, settings
