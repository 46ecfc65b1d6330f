"""Predicted screen images for new settings, with their warnings."""

from __future__ import annotations

import pytest
import torch

from diffaccel.reconstruction import (
    ReconstructionConfig,
    as_scans,
    predict_dataset,
    reconstruct,
)
from diffaccel.reconstruction.prediction import predict_scans, predict_settings


@pytest.fixture(scope="module")
def result(small_scan):
    config = ReconstructionConfig(n_particles=256, steps=4, snapshots=2)
    return reconstruct(small_scan, config, uncertainty=False)


def test_predict_scans_equals_predict_dataset(result, small_scan) -> None:
    scans = as_scans(small_scan)
    pred = predict_scans(result, scans, n_particles=300, seed=3)
    images, on_screen = predict_dataset(
        result, scans, n_particles=300, seed=3, return_on_screen=True
    )
    assert list(pred.images) == list(images) == scans.names
    for name in scans.names:
        torch.testing.assert_close(pred.images[name], images[name])
        torch.testing.assert_close(pred.on_screen[name], on_screen[name])
        assert pred.images[name].sum(dim=(-2, -1)) == pytest.approx(1.0, rel=1e-5)
    assert pred.spread is None and pred.warnings == []
    spread = predict_scans(result, scans, n_particles=300, return_std=True).spread
    assert spread is not None
    assert spread[scans.names[0]].shape == pred.images[scans.names[0]].shape


def test_predict_settings_images_the_first_training_beamline(result) -> None:
    settings = torch.tensor([[-5.0], [0.0], [5.0]], dtype=torch.float64)
    pred = predict_settings(result, settings, n_particles=300, return_std=True)
    (name,) = pred.images
    assert name == result.scan_names[0]
    assert pred.images[name].shape == (3, 32, 32)
    assert pred.spread is not None and pred.spread[name].shape == (3, 32, 32)
    assert pred.on_screen[name].shape == (3,)
    assert bool((pred.on_screen[name] > 0.5).all()) and pred.warnings == []


def test_predict_settings_warns_where_the_beam_leaves_the_screen(result) -> None:
    # a strong quadrupole spreads the beam far beyond the 32 mm screen
    settings = torch.tensor([[0.0], [300.0]], dtype=torch.float64)
    pred = predict_settings(result, settings, n_particles=300)
    name = result.scan_names[0]
    assert float(pred.on_screen[name][1]) < 0.5
    assert len(pred.warnings) == 1 and "screen" in pred.warnings[0]
