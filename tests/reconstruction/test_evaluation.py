from __future__ import annotations

import dataclasses

import pytest
import torch

from diffaccel.data import make_synthetic_awa6d
from diffaccel.reconstruction import (
    LOW_ON_SCREEN_FRACTION,
    POOR_FIT_RELATIVE_L1,
    ReconstructionConfig,
    evaluate,
    evaluation,
    off_screen_warnings,
    predict_dataset,
    reconstruct,
)

FAST = {"n_particles": 512, "steps": 4, "snapshots": 1}


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
    assert min(s["scans"]["scan"]["fraction_on_screen"]) > 0.95
    # its waist (0.55 pixels rms) is below the 1-pixel point spread: a note,
    # not a warning about the fit
    [note] = s["point_spread"]
    assert "scan 'scan'" in note and "point spread's shape" in note


def test_a_fit_that_misses_its_training_images_is_warned(
    small_scan, small_result
) -> None:
    pred = predict_dataset(small_result, small_scan)
    # the beam's image moved by a third of the screen: nothing overlaps
    wrong = {n: torch.roll(p, shifts=(11, 11), dims=(-2, -1)) for n, p in pred.items()}
    s = evaluate(small_result, small_scan, predicted=wrong, n_sample=2000)
    assert s["metrics"]["images_train"]["relative_l1"] > POOR_FIT_RELATIVE_L1
    # the moved images also miss the moments (a fit-quality alarm of its own)
    (w,) = [w for w in s["warnings"] if "does not reproduce" in w]
    assert "does not reproduce its training images" in w
    for cause in ("units", "beamline", "screen calibration", "p0c"):
        assert cause in w
    assert {a["kind"] for a in s["fit_alarms"]} <= {
        "moment_miss",
        "outlier_setting",
        "screen_edge",
    }


def test_settings_that_throw_the_beam_off_the_screen_are_warned(
    small_scan, small_result
) -> None:
    # the last setting 20x too strong (k1 = 200): most of the beam misses the
    # 32 mm screen, and its unit-sum image alone would not show it
    settings = small_scan.settings.clone()
    settings[-1] = 200.0
    other = dataclasses.replace(small_scan, settings=settings)
    s = evaluate(small_result, other, n_sample=2000)
    fraction = s["scans"]["scan"]["fraction_on_screen"]
    assert fraction[-1] < LOW_ON_SCREEN_FRACTION and min(fraction[:-1]) > 0.95
    (w,) = s["warnings"]
    assert w.startswith(
        "scan 'scan': only part of the predicted beam lands on the screen at 1 of "
        f"6 settings: setting 5 (Q1.k1 = 200) {100 * fraction[-1]:.1f} %"
    )
    # predicted images given without their fractions: nothing to check
    pred = predict_dataset(small_result, other, n_particles=500)
    assert (
        evaluate(small_result, other, predicted=pred, n_sample=2000)["warnings"] == []
    )


def test_off_screen_warnings_name_the_scan_settings_and_fractions() -> None:
    names = ["Q1.k1", "Q2.k1"]
    settings = torch.arange(24.0).reshape(12, 2)
    fine = torch.tensor([1.0, 0.97, LOW_ON_SCREEN_FRACTION])  # at the threshold: no
    assert off_screen_warnings(fine, settings[:3], names, scan="a") == []
    (w,) = off_screen_warnings(
        torch.tensor([0.99, 0.098, 0.0]), settings[:3], names, scan="a"
    )
    assert w.startswith(
        "scan 'a': only part of the predicted beam lands on the screen at 2 of 3 "
        "settings: setting 1 (Q1.k1 = 2, Q2.k1 = 3) 9.8 %, setting 2 (Q1.k1 = 4, "
        "Q2.k1 = 5) 0.0 % (warned below 50 %)"
    )
    (w,) = off_screen_warnings(torch.zeros(12), settings, names, scan="a")
    assert "at 12 of 12 settings" in w and "setting 7 (" in w
    assert "setting 8 (" not in w and "and 4 more" in w


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
    config = ReconstructionConfig(dims=6, **FAST)
    result = reconstruct(data, config, uncertainty=False)

    def degenerate(maps, cov):
        raise ValueError("cov is not positive definite: no beam has it.")

    # a covariance no beam has: the summary is still written, with a warning
    monkeypatch.setattr(evaluation, "prior_dependence", degenerate)
    s = evaluate(result, data, n_sample=4000)
    assert s["prior_dependence"] == []
    assert any("prior_dependence not computed" in w for w in s["warnings"])


def test_every_image_error_carries_the_predictions_own_noise(
    small_scan, small_result
) -> None:
    s = evaluate(small_result, small_scan, n_sample=2000)
    scan = s["scans"]["scan"]
    for key in ("images_train", "images_held_out"):
        errors = scan[key]
        assert errors["prediction_particles"] >= 50_000
        assert 0 < errors["prediction_noise_l1"] < errors["relative_l1"]
        assert errors["data_noise_l1"] is None  # single shots
        pooled = s["metrics"][key]
        assert pooled["prediction_noise_l1"] == pytest.approx(
            errors["prediction_noise_l1"]
        )
        assert "data_noise_l1" in pooled
    # images given without their particle count: their own noise is unknown
    pred = predict_dataset(small_result, small_scan)
    given = evaluate(small_result, small_scan, predicted=pred, n_sample=2000)
    assert given["scans"]["scan"]["images_train"]["prediction_noise_l1"] is None
    assert given["metrics"]["images_train"]["prediction_noise_l1"] is None
