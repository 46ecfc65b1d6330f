"""Reconstruction from several scans of one beam (format version 2)."""

from __future__ import annotations

import math
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
from diffaccel.reconstruction.unseen import (
    PLACEMENT_PARTICLES,
    coupling_directions,
    member_moments,
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


def test_refit_of_placed_members_changes_them(small_awa6d) -> None:
    """``refit_steps`` (6D default 60): every placed member is trained again;
    0 leaves the placed members as they are."""
    assert CONFIG.refit_steps == 60
    assert replace(CONFIG, dims=4, refit_steps=None).refit_steps == 0
    config = replace(CONFIG, refit_steps=4)
    refit = reconstruct(small_awa6d, config, uncertainty=False)
    placed_only = reconstruct(
        small_awa6d, replace(config, refit_steps=0), uncertainty=False
    )
    assert refit.n_snapshots == placed_only.n_snapshots == 1
    for a, b in zip(refit.snapshots, placed_only.snapshots, strict=True):
        assert not torch.equal(a["offset"], b["offset"])


def test_uncoupled_members_end_at_the_largest_determinant(small_awa6d) -> None:
    """``place_coupling``: after training, placement and refit every member sits
    where its determinant along the barely seen x-y coupling direction is
    largest; training alone (no moment polish, which moves it toward what the
    image moments say) leaves it wherever it settled."""
    config = replace(CONFIG, refit_steps=4)

    def slopes(result) -> list[float]:
        maps = [
            result.forwards[name].transfer_maps(scan.settings)
            for name, scan in small_awa6d
        ]
        out = []
        for state in result.snapshots:
            _, cov = member_moments(
                state, 6, config.width, config.depth, PLACEMENT_PARTICLES, config.seed
            )
            v = coupling_directions(maps, cov)
            assert v.shape[0] == 1
            # d log det / dt along the unit direction: 0 at the largest
            out.append(abs(float(torch.einsum("ij,ji->", torch.linalg.inv(cov), v[0]))))
        return out

    placed = reconstruct(
        small_awa6d, replace(config, place_coupling=True), uncertainty=False
    )
    plain = reconstruct(
        small_awa6d, replace(config, polish_moments=False), uncertainty=False
    )
    assert max(slopes(placed)) < 1e-3
    assert max(slopes(plain)) > 1e-2
    # also after the probe along px-pz (both sides probed; whether this small
    # run's gain takes it off the prior point depends on the last bits of the
    # arithmetic, so either end is accepted): the coupling is placed last
    probed = reconstruct(
        small_awa6d,
        replace(config, place_coupling=True, probe_unseen=0.05, probe_away=False),
        uncertainty=False,
    )
    assert len(probed.info["unseen_probe"]["steps"]) >= 3  # the point and both sides
    assert max(slopes(probed)) < 1e-3


def test_progress_counts_training_and_refit(small_awa6d) -> None:
    """The callback's steps run on through the refit of the placed members
    (the plain refit; with the probe, test_probe_refits_every_member_...)."""
    seen: list[tuple[int, int]] = []
    config = replace(CONFIG, refit_steps=4, report_every=2, probe_unseen=0.0)
    reconstruct(
        small_awa6d,
        config,
        callback=lambda info: seen.append((info.step, info.total)),
        uncertainty=False,
    )
    # 6 training steps, then 4 refit steps of the one member (burn_in 1 of 2)
    assert config.total_steps == 6 + 4
    assert {t for _, t in seen} == {10}
    steps = [s for s, _ in seen]
    assert steps == sorted(steps)
    assert steps[-1] == 10
    assert any(s > 6 for s in steps)


def test_a_quadrupole_scan_alone_is_not_refitted(small_scan) -> None:
    """6D on a quad scan: z and pz are not seen at all, nothing is placed, so
    nothing is refitted (the same members as with ``refit_steps=0``; likewise
    ``two_scans``, which has a dipole but no cavity: z unseen)."""
    seen: list[tuple[int, int]] = []
    config = ReconstructionConfig(dims=6, n_particles=512, steps=4, snapshots=2)
    result = reconstruct(
        small_scan,
        config,
        callback=lambda info: seen.append((info.step, info.total)),
        uncertainty=False,
    )
    plain = reconstruct(small_scan, replace(config, refit_steps=0), uncertainty=False)
    assert {t for _, t in seen} == {4}
    for a, b in zip(result.snapshots, plain.snapshots, strict=True):
        assert all(torch.equal(a[k], b[k]) for k in a)


def test_probe_refits_every_member_at_three_points_and_records_them(
    small_awa6d,
) -> None:
    """``probe_unseen`` without ``probe_away``: each member refitted at -step,
    0, +step along px-pz (more steps only where the KL gain passes
    ``probe_gain``); the record in ``info["unseen_probe"]``, the progress
    counting every refit."""
    seen: list[tuple[int, int]] = []
    config = replace(
        CONFIG, refit_steps=4, report_every=2, probe_unseen=0.05, probe_away=False
    )
    result = reconstruct(
        small_awa6d,
        config,
        callback=lambda info: seen.append((info.step, info.total)),
        uncertainty=False,
    )
    record = result.info["unseen_probe"]
    points = [s["t"] for s in record["steps"]]
    assert points[:3] == [0.0, -0.05, 0.05]
    assert record["t"] in points
    assert all(len(s["kl"]) == result.n_snapshots for s in record["steps"])
    assert all(s["kl"][0] > 0 for s in record["steps"])
    # 6 training steps, then 4 steps per refit, one member
    assert config.total_steps == 6 + 3 * 4
    steps = [s for s, _ in seen]
    assert steps == sorted(steps)
    assert steps[-1] == 6 + 4 * len(points)
    assert (
        "unseen_probe"
        not in reconstruct(
            small_awa6d, replace(config, probe_unseen=0.0), uncertainty=False
        ).info
    )


def test_probe_away_probes_the_side_away_from_the_trained_members(
    small_awa6d,
) -> None:
    """``probe_away`` (the default): the members' trained ``t`` recorded, the
    probe's first two points the prior point and the step away from their
    mean, the progress counting the refits so."""
    config = replace(CONFIG, refit_steps=4, report_every=2, probe_unseen=0.05)
    assert config.probe_away and config.total_steps == 6 + 2 * 4
    result = reconstruct(small_awa6d, config, uncertainty=False)
    record = result.info["unseen_probe"]
    assert len(record["trained_t"]) == result.n_snapshots
    mean = sum(record["trained_t"]) / len(record["trained_t"])
    assert mean != 0
    points = [s["t"] for s in record["steps"]]
    assert points[:2] == [0.0, -math.copysign(0.05, mean)]
    assert all(t * mean <= 0 for t in points)
