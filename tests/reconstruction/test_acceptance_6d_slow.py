"""Acceptance of the 6D reconstruction on the shared 6D benchmark (slow).

Train on ``sixd_synthetic_train.h5`` with the default 6D
settings, compare ``sample(200_000)`` with the stored ground truth, predict the
held-out ``sixd_synthetic_test.h5``. ``benchmarks/reconstruction_6d.py`` runs the
same through the CLI, times it and runs gpsr on the same data.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from diffaccel.data import read_scans
from diffaccel.reconstruction import (
    ReconstructionConfig,
    image_errors,
    moment_errors,
    predict_dataset,
    reconstruct,
)

DATA = Path(__file__).resolve().parents[2] / "data" / "phase_space"
TRAIN = DATA / "sixd_synthetic_train.h5"
TEST = DATA / "sixd_synthetic_test.h5"

pytestmark = [pytest.mark.slow]


@pytest.fixture(scope="module")
def run():
    train = read_scans(TRAIN)
    result = reconstruct(train, ReconstructionConfig(dims=6))
    errors = moment_errors(result.sample(200_000), train.ground_truth)
    test = read_scans(TEST)
    pred = predict_dataset(result, test)
    held = {
        name: image_errors(pred[name], scan.mean_images())["relative_l1"]
        for name, scan in test
    }
    return errors, held


# acceptance: rms sizes and x, y emittances within 5 %, z emittance within 10 %,
# 6D emittance within 15 % (relative to the truth)
LIMITS = {
    **{f"rms_{c}": 0.05 for c in ("x", "px", "y", "py", "z", "pz")},
    "emit_x": 0.05,
    "emit_y": 0.05,
    "emit_z": 0.10,
    "emit_6d": 0.15,
}


@pytest.mark.parametrize("key", list(LIMITS))
def test_moments_match_the_truth(run, key: str) -> None:
    errors, _ = run
    assert abs(errors[key]) <= LIMITS[key], errors[key]


@pytest.mark.parametrize("pair", ["x_z", "y_py", "z_pz"])
def test_correlations_within_0_05(run, pair: str) -> None:
    errors, _ = run
    assert abs(errors[f"corr_diff_{pair}"]) <= 0.05, errors[f"corr_diff_{pair}"]


@pytest.mark.parametrize("scan", ["dipole_off", "dipole_on"])
def test_held_out_images_relative_l1_at_most_0_15(run, scan: str) -> None:
    _, held = run
    assert held[scan] <= 0.15, held[scan]
