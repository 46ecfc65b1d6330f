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


@pytest.mark.skipif(not GPSR.exists(), reason="shared reference data not present")
def test_gpsr_4d_benchmark_accuracy() -> None:
    ds = read_quad_scan(GPSR)
    r = reconstruct(ds, ReconstructionConfig(), train_indices=range(0, 20, 2))
    e = moment_errors(r.sample(100_000), ds.ground_truth)
    # acceptance: rms sizes within 3 %, emittances within 5 % of the truth
    for k in ("rms_x", "rms_px", "rms_y", "rms_py"):
        assert abs(e[k]) < 0.03, (k, e[k])
    for k in ("emit_x", "emit_y"):
        assert abs(e[k]) < 0.05, (k, e[k])


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
