from __future__ import annotations

import pytest
import torch

from diffaccel.reconstruction import (
    POOR_FIT_RELATIVE_L1,
    ReconstructionConfig,
    evaluate,
    predict_dataset,
    reconstruct,
)

FAST = {"n_particles": 512, "steps": 4, "snapshots": 1, "checkpoint_every": 5}


@pytest.fixture(scope="module")
def small_result(small_scan):
    return reconstruct(
        small_scan, ReconstructionConfig(**FAST), train_indices=[0, 2, 4]
    )


def test_a_fit_that_reproduces_its_images_has_no_warning(
    small_scan, small_result
) -> None:
    s = evaluate(small_result, small_scan, n_sample=2000)
    assert s["metrics"]["images_train"]["relative_l1"] < POOR_FIT_RELATIVE_L1
    assert s["warnings"] == []


def test_a_fit_that_misses_its_training_images_is_warned(
    small_scan, small_result
) -> None:
    pred = predict_dataset(small_result, small_scan)
    # the beam's image moved by a third of the screen: nothing overlaps
    wrong = {n: torch.roll(p, shifts=(11, 11), dims=(-2, -1)) for n, p in pred.items()}
    s = evaluate(small_result, small_scan, predicted=wrong, n_sample=2000)
    assert s["metrics"]["images_train"]["relative_l1"] > POOR_FIT_RELATIVE_L1
    (w,) = s["warnings"]
    assert "does not reproduce its training images" in w
    for cause in ("units", "beamline", "screen calibration", "p0c"):
        assert cause in w
