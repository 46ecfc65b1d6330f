"""Fixtures for ``tests/data``: small hand-made quad-scan datasets."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from diffaccel.data import QuadScanDataset

REFERENCE = Path(__file__).resolve().parents[2] / "data" / "phase_space"

SPEC = [
    {"type": "Quadrupole", "name": "Q1", "length": 0.1, "k1": 0.0},
    {"type": "Drift", "name": "D1", "length": 1.0},
    {"type": "Screen", "name": "SCREEN"},
]


def gaussian_images(k: int, s: int, h: int, w: int, seed: int = 0) -> torch.Tensor:
    """Positive blobs of random position/width on a (K, S, H, W) grid."""
    g = torch.Generator().manual_seed(seed)
    i = torch.arange(h, dtype=torch.float64)[:, None]
    j = torch.arange(w, dtype=torch.float64)[None, :]
    out = torch.empty(k, s, h, w, dtype=torch.float64)
    for a in range(k):
        for b in range(s):
            ci, cj = (torch.rand(2, generator=g, dtype=torch.float64) - 0.5) * 4
            si, sj = 1.5 + torch.rand(2, generator=g, dtype=torch.float64) * 2
            out[a, b] = torch.exp(
                -0.5 * ((i - (h - 1) / 2 - ci) / si) ** 2
                - 0.5 * ((j - (w - 1) / 2 - cj) / sj) ** 2
            )
    return (out / out.sum(dim=(-2, -1), keepdim=True)).float()


def make_dataset(
    k: int = 5, s: int = 2, h: int = 16, w: int = 20, ground_truth: bool = True
) -> QuadScanDataset:
    g = torch.Generator().manual_seed(1)
    gt = (
        torch.randn(200, 6, generator=g, dtype=torch.float64) * 1e-3
        if ground_truth
        else None
    )
    return QuadScanDataset(
        images=gaussian_images(k, s, h, w),
        settings=torch.linspace(-10.0, 10.0, k, dtype=torch.float64)[:, None],
        setting_names=["Q1.k1"],
        setting_units=["1/m^2"],
        p0c=43.36e6,
        species="electron",
        beamline_spec=SPEC,
        pixel_size=(1e-3, 2e-3),
        center=(1e-4, -2e-4),
        ground_truth=gt,
        metadata={"source": "test", "preprocessing": []},
    )


@pytest.fixture
def dataset() -> QuadScanDataset:
    """5 settings x 2 shots of 16 x 20 pixels, with a Bmad ground truth."""
    return make_dataset()


@pytest.fixture
def dataset_factory():
    """``make_dataset`` for tests that need other sizes."""
    return make_dataset


@pytest.fixture
def reference_file():
    """Path to a quad-scan file of the reference data in ``data/phase_space``."""

    def get(name: str) -> Path:
        path = REFERENCE / name
        assert path.exists(), f"reference data missing from the repository: {path}"
        return path

    return get
