"""Acceptance runs on the reference data in ``data/``, against the README claims.

The GPSR 4D case (one default reconstruction, ~4 s on two cores) runs in
``make test``; the measured AWA scan is marked slow. The benchmark's limits: rms
sizes within 3 % of the truth (measured within 0.7 %), x and y emittances within
5 % (measured -4.9 / -0.3 % at seed 0, x -4.0 / -3.3 % at seeds 1 / 2), held-out
relative L1 below gpsr's 0.117 (measured 0.062-0.071 over seeds 0-2). The
bounds below add the sampling error of the 100 000-particle sample the errors
are measured on (rms: sqrt(1/2N) = 0.2 %; emittance ~0.4 %) to looser figures
(rms within 1.8 %, L1 below 0.087) or to the limit (emittances).
"""

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

DATA = Path(__file__).resolve().parents[2] / "data" / "phase_space"
GPSR = DATA / "gpsr_4d_synthetic.h5"
AWA = DATA / "awa_quad_scan_train.h5"


@pytest.fixture(scope="module")
def gpsr_errors() -> dict[str, float]:
    ds = read_quad_scan(GPSR)
    r = reconstruct(ds, ReconstructionConfig(), train_indices=range(0, 20, 2))
    errors = moment_errors(r.sample(100_000), ds.ground_truth)
    pred = r.predict_images(ds.settings[1::2])
    errors["held_out_l1"] = image_errors(pred, ds.mean_images()[1::2])["relative_l1"]
    return errors


@pytest.mark.parametrize("key", ["rms_x", "rms_px", "rms_y", "rms_py"])
def test_gpsr_4d_rms_sizes_as_claimed(gpsr_errors, key: str) -> None:
    assert abs(gpsr_errors[key]) < 0.018 + 0.002, gpsr_errors[key]


@pytest.mark.parametrize("key", ["emit_x", "emit_y"])
def test_gpsr_4d_emittances_as_claimed(gpsr_errors, key: str) -> None:
    assert abs(gpsr_errors[key]) < 0.05 + 0.004, gpsr_errors[key]


def test_gpsr_4d_held_out_images_as_claimed(gpsr_errors) -> None:
    # 0.062-0.071 at seeds 0-2; gpsr 0.2.0 gets 0.117
    assert gpsr_errors["held_out_l1"] < 0.087, gpsr_errors["held_out_l1"]


@pytest.mark.slow
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
