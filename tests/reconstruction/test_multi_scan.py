"""Reconstruction from several scans of one beam (format version 2)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
import torch

from diffaccel.data import (
    MultiScanDataset,
    make_synthetic_quad_scan,
    sample_preset_beam,
)
from diffaccel.reconstruction import (
    ReconstructionConfig,
    evaluate,
    load,
    predict_dataset,
    predicted_dataset,
    reconstruct,
    training_selection,
)

BENT = [
    {"type": "Quadrupole", "name": "Q1", "length": 0.1, "k1": 0.0},
    {"type": "Drift", "name": "D1", "length": 0.5},
    {"type": "Dipole", "name": "B1", "length": 0.3, "angle": 0.3},
    {"type": "Drift", "name": "D2", "length": 0.5},
    {"type": "Screen", "name": "S2"},
]


@pytest.fixture(scope="module")
def two_scans() -> MultiScanDataset:
    """One beam seen straight ahead (24 x 24 px) and after a dipole (16 x 20 px)."""
    g = torch.Generator().manual_seed(3)
    beam = sample_preset_beam("gaussian", 4000, g)
    straight = make_synthetic_quad_scan(
        particles=beam,
        n_settings=5,
        k1_range=(-8.0, 8.0),
        screen_shape=(24, 24),
        pixel_size=(1e-3, 1e-3),
    )
    bent = make_synthetic_quad_scan(
        particles=beam,
        beamline_spec=BENT,
        n_settings=3,
        k1_range=(-5.0, 5.0),
        screen_shape=(16, 20),
        pixel_size=(1.5e-3, 1.5e-3),
    )
    return MultiScanDataset({"straight": straight, "bent": bent})


CONFIG = ReconstructionConfig(dims=6, n_particles=512, steps=6, snapshots=2)


@pytest.fixture(scope="module")
def result(two_scans):
    return reconstruct(
        two_scans, CONFIG, train_indices={"straight": [0, 2, 4], "bent": [0, 1, 2]}
    )


def test_every_scan_is_trained_and_recorded(result, two_scans) -> None:
    assert result.scan_names == ["straight", "bent"]
    assert result.info["scans"]["straight"]["train_indices"] == [0, 2, 4]
    assert result.info["scans"]["bent"]["train_settings"] == (
        two_scans["bent"].settings.tolist()
    )
    # the dipole's dispersion makes pz visible: the initial fit sees it
    assert result.info["initial_guess_cov"][5][5] > 0
    assert "pz" not in result.unconstrained_coordinates()


def test_predict_dataset_images_every_scan_on_its_grid(result, two_scans) -> None:
    pred = predict_dataset(result, two_scans, n_particles=1000)
    assert pred["straight"].shape == (5, 24, 24)
    assert pred["bent"].shape == (3, 16, 20)
    for images in pred.values():
        torch.testing.assert_close(
            images.sum((-2, -1)), torch.ones(images.shape[0]), rtol=0, atol=1e-5
        )


def test_evaluate_reports_per_scan_and_pooled_errors(result, two_scans) -> None:
    s = evaluate(result, two_scans, n_sample=10_000)
    assert s["scans"]["straight"]["held_out_indices"] == [1, 3]
    assert "images_held_out" not in s["scans"]["bent"]
    per = s["scans"]["straight"]["images_held_out"]["relative_l1"]
    # only the straight scan has held-out images, so the pooled value is its own
    assert s["metrics"]["images_held_out"]["relative_l1"] == pytest.approx(per)
    assert s["metrics"]["images_train"]["n_images"] == 6
    assert "corr_diff_z_pz" in s["metrics"]["ground_truth"]


def test_evaluate_with_the_callers_sample_is_the_same(result, two_scans) -> None:
    pred = predict_dataset(result, two_scans)
    drawn = evaluate(result, two_scans, predicted=pred, n_sample=5_000)
    given = evaluate(
        result,
        two_scans,
        predicted=pred,
        n_sample=5_000,
        sample=result.sample(5_000),
    )
    assert given["metrics"]["ground_truth"] == drawn["metrics"]["ground_truth"]
    other = evaluate(
        result,
        two_scans,
        predicted=pred,
        n_sample=5_000,
        sample=result.sample(5_000, seed=1),
    )  # the sample given is the one used
    assert other["metrics"]["ground_truth"] != drawn["metrics"]["ground_truth"]


def test_predicted_dataset_keeps_the_layout(result, two_scans) -> None:
    pred = predicted_dataset(two_scans, predict_dataset(result, two_scans))
    assert pred.names == two_scans.names
    assert pred["bent"].shape == (3, 1, 16, 20)
    assert torch.equal(pred["bent"].settings, two_scans["bent"].settings)
    assert pred.metadata["preprocessing"][-1]["step"] == "predicted"


def test_predicted_dataset_records_the_fraction_on_the_screen(
    result, two_scans
) -> None:
    pred, on_screen = predict_dataset(
        result, two_scans, n_particles=1000, return_on_screen=True
    )
    assert all(float(f.min()) > 0.9 for f in on_screen.values())
    same = predict_dataset(result, two_scans, n_particles=1000)  # images unchanged
    assert all(torch.equal(pred[n], same[n]) for n in two_scans.names)
    # as if the beam missed the bent scan's screen at its second setting
    low = dict(on_screen, bent=torch.tensor([0.97, 0.2, 0.96]))
    ds = predicted_dataset(two_scans, pred, source="run", on_screen=low)
    bent = ds["bent"].metadata["preprocessing"][-1]
    assert bent["fraction_on_screen"] == [0.97, 0.2, 0.96]
    (w,) = bent["warnings"]
    assert w.startswith("scan 'bent': only part of the predicted beam lands on the")
    assert "1 of 3 settings: setting 1 (Q1.k1 = 0) 20.0 %" in w
    straight = ds["straight"].metadata["preprocessing"][-1]
    assert straight["warnings"] == [] and len(straight["fraction_on_screen"]) == 5
    # the file's own step (version 2) holds the warnings of every scan
    assert ds.metadata["preprocessing"][-1] == {
        "step": "predicted",
        "reconstruction": "run",
        "warnings": [w],
    }
    # without the fractions the step is as before
    plain = predicted_dataset(two_scans, pred, source="run")
    assert plain.metadata["preprocessing"][-1] == {
        "step": "predicted",
        "reconstruction": "run",
    }


def test_save_load_keeps_every_forward_model(result, tmp_path: Path) -> None:
    result.save(tmp_path)
    back = load(tmp_path)
    assert back.scan_names == ["straight", "bent"]
    assert back.forwards["bent"].screen.shape == (16, 20)
    torch.testing.assert_close(back.sample(100), result.sample(100))


@pytest.mark.parametrize(
    ("selection", "message"),
    [
        ({"nope": [0]}, r"unknown scan\(s\) \['nope'\]"),
        ({"bent": [3]}, r"scan 'bent' must be distinct integers in \[0, 3\)"),
        ([0, 4], r"scan 'bent' must be distinct integers in \[0, 3\)"),
        ({"bent": []}, r"select no setting"),
    ],
    ids=["unknown_scan", "out_of_range", "list_out_of_range", "empty"],
)
def test_training_selection_errors_name_the_scan(two_scans, selection, message):
    with pytest.raises(ValueError, match=message):
        training_selection(two_scans, selection)


def test_the_prior_term_changes_the_awa6d_members(small_awa6d) -> None:
    """6D on the AWA layout (two directions unseen): the prior term
    (``unseen_weight``, 6D default 1e3) enters training; 0 trains without it."""
    assert CONFIG.unseen_weight == 1e3
    assert replace(CONFIG, dims=4, unseen_weight=None).unseen_weight == 0.0
    held = reconstruct(small_awa6d, CONFIG, uncertainty=False)
    free = reconstruct(
        small_awa6d, replace(CONFIG, unseen_weight=0.0), uncertainty=False
    )
    assert held.n_snapshots == free.n_snapshots == 1
    for a, b in zip(held.snapshots, free.snapshots, strict=True):
        assert not torch.equal(a["offset"], b["offset"])


def test_progress_counts_the_training_steps(small_awa6d) -> None:
    """The callback sees every training step counted against ``steps``: no
    stage after training."""
    seen: list[tuple[int, int]] = []
    reconstruct(
        small_awa6d,
        CONFIG,
        callback=lambda info: seen.append((info.step, info.total)),
        uncertainty=False,
        report_every=2,
    )
    assert {t for _, t in seen} == {6}
    steps = [s for s, _ in seen]
    assert steps == sorted(steps) and steps[-1] == 6


def test_a_quadrupole_scan_alone_holds_nothing(small_scan) -> None:
    """6D on a quad scan: z and pz are not seen at all (their prior widths set
    them), no direction is traded, so the prior term holds nothing: the same
    members as with ``unseen_weight=0``."""
    config = ReconstructionConfig(dims=6, n_particles=512, steps=4, snapshots=2)
    result = reconstruct(small_scan, config, uncertainty=False)
    plain = reconstruct(
        small_scan, replace(config, unseen_weight=0.0), uncertainty=False
    )
    for a, b in zip(result.snapshots, plain.snapshots, strict=True):
        assert all(torch.equal(a[k], b[k]) for k in a)
