"""Acceptance runs on the shared reference data (slow: deselected by default)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from diffaccel.data import read_quad_scan
from diffaccel.reconstruction import (
    ReconstructionConfig,
    image_errors,
    moment_errors,
    reconstruct,
)

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "phase_space"
GPSR = DATA / "gpsr_4d_synthetic.h5"
AWA = DATA / "awa_quad_scan_train.h5"

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def gpsr_errors() -> dict[str, float]:
    if not GPSR.exists():
        pytest.skip("shared reference data not present")
    ds = read_quad_scan(GPSR)
    r = reconstruct(ds, ReconstructionConfig(), train_indices=range(0, 20, 2))
    return moment_errors(r.sample(100_000), ds.ground_truth)


@pytest.mark.parametrize("key", ["rms_x", "rms_px", "rms_y", "rms_py"])
def test_gpsr_4d_rms_sizes_within_3_percent(gpsr_errors, key: str) -> None:
    assert abs(gpsr_errors[key]) < 0.03, gpsr_errors[key]


@pytest.mark.parametrize("key", ["emit_x", "emit_y"])
def test_gpsr_4d_emittances_within_5_percent(gpsr_errors, key: str) -> None:
    assert abs(gpsr_errors[key]) < 0.05, gpsr_errors[key]


@pytest.mark.skipif(not AWA.exists(), reason="shared reference data not present")
def test_awa_measured_scan_predicts_its_images() -> None:
    ds = read_quad_scan(AWA)
    r = reconstruct(ds, ReconstructionConfig(), train_indices=range(0, 11, 2))
    pred = r.predict_images(ds.settings)
    err = image_errors(pred, ds.mean_images())
    # held-out (odd) settings predicted about as well as the training ones
    held = [err["relative_l1_per_setting"][i] for i in range(1, 11, 2)]
    train = [err["relative_l1_per_setting"][i] for i in range(0, 11, 2)]
    assert sum(held) / len(held) < 1.5 * sum(train) / len(train) + 0.05
    # settings not in the file (between and beyond the measured ones)
    k = ds.settings[:, 0]
    new = torch.cat([(k[:-1] + k[1:]) / 2, k[-1:] + (k[-1] - k[-2])])[:, None]
    imgs = r.predict_images(new.double())
    assert torch.isfinite(imgs).all()
    assert imgs.sum((-2, -1)).sub(1).abs().max() < 1e-4
