from __future__ import annotations

import dataclasses

import pytest
import torch

from diffaccel.data import make_synthetic_awa6d
from diffaccel.reconstruction import (
    POOR_FIT_RELATIVE_L1,
    ReconstructionConfig,
    evaluate,
    evaluation,
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


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"p0c": 63e6}, r"p0c = 6\.3e\+07 eV; the reconstruction was made at p0c"),
        ({"p0c": 1e3}, r"p0c = 1000 eV; the reconstruction was made at p0c"),
        ({"species": "positron"}, r"species 'positron'; the reconstruction is of"),
    ],
    ids=["p0c_63MeV", "p0c_keV", "positron"],
)
def test_predicting_another_beams_dataset_is_refused(
    small_scan, small_result, changes: dict, message: str
) -> None:
    other = dataclasses.replace(small_scan, **changes)
    with pytest.raises(ValueError, match=message):
        predict_dataset(small_result, other)
    with pytest.raises(ValueError, match=message):
        evaluate(small_result, other, n_sample=2000)


def test_a_p0c_rounded_when_recorded_is_accepted(small_scan, small_result) -> None:
    # within P0C_RELATIVE_TOLERANCE (1e-3): the same beam, its energy rounded
    other = dataclasses.replace(small_scan, p0c=small_scan.p0c * (1 + 5e-4))
    pred = predict_dataset(small_result, other, n_particles=500)
    assert pred["scan"].shape[0] == small_scan.n_settings


def test_6d_summary_without_a_prior_dependence_warns(monkeypatch) -> None:
    data = make_synthetic_awa6d(
        "correlated",
        n_particles=2000,
        k1_values=[-12.0, 0.0, 12.0],
        screen_shape=(24, 24),
        seed=3,
    )
    config = ReconstructionConfig(dims=6, **FAST, place_unseen=False)
    result = reconstruct(data, config, uncertainty=False)

    def degenerate(maps, cov):
        raise ValueError("cov is not positive definite: no beam has it.")

    # a covariance no beam has: the summary is still written, with a warning
    monkeypatch.setattr(evaluation, "prior_dependence", degenerate)
    s = evaluate(result, data, n_sample=4000)
    assert s["prior_dependence"] == []
    assert any("prior_dependence not computed" in w for w in s["warnings"])
