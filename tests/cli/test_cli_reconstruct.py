from __future__ import annotations

import json
import os
import socket
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
from click.testing import CliRunner

import diffaccel.cli.reconstruct as cli_reconstruct
from diffaccel.cli import main
from diffaccel.data import (
    MultiScanDataset,
    make_synthetic_awa6d,
    make_synthetic_quad_scan,
    partial_folder,
    read_quad_scan,
    read_scans,
    sample_preset_beam,
    write_quad_scan,
    write_scans,
)
from diffaccel.reconstruction import LOW_ON_SCREEN_FRACTION, load

FAST = ["--particles", "512", "--steps", "6", "--snapshots", "2"]
# the same with the --epochs alias (kept from before the rename to --steps)
FAST_ALIAS = ["--particles", "512", "--epochs", "6", "--snapshots", "2"]


@pytest.fixture(scope="module")
def scan_file(tmp_path_factory) -> Path:
    ds = make_synthetic_quad_scan(
        "gaussian",
        n_particles=2000,
        n_settings=6,
        k1_range=(-8.0, 8.0),
        screen_shape=(24, 24),
        pixel_size=(1e-3, 1e-3),
        seed=2,
    )
    path = tmp_path_factory.mktemp("scan") / "scan.h5"
    write_quad_scan(ds, path)
    return path


@pytest.fixture(scope="module")
def result_dir(scan_file: Path, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("res") / "out"
    r = CliRunner().invoke(
        main,
        [
            "reconstruct",
            str(scan_file),
            "--out",
            str(out),
            "--train-indices=even",
            *FAST_ALIAS,
        ],
    )
    assert r.exit_code == 0, r.output
    return out


def test_reconstruct_writes_summary_ensemble_figures(result_dir: Path) -> None:
    s = json.loads((result_dir / "summary.json").read_text())
    assert s["train_indices"] == [0, 2, 4] and s["held_out_indices"] == [1, 3, 5]
    assert s["config"]["steps"] == 6  # given as --epochs 6 (alias)
    assert len(s["moments"]["rms"]["mean"]) == 6
    assert "relative_l1" in s["metrics"]["images_held_out"]
    assert "rms_x" in s["metrics"]["ground_truth"]
    for name in (
        "ensemble.pt",
        "particles.h5",
        "phase_space.png",
        "images.png",
        "training.png",
        "rms_evolution.png",
    ):
        assert (result_dir / name).exists(), name


def test_summary_std_is_calibrated_unless_no_uncertainty(
    scan_file: Path, result_dir: Path, tmp_path: Path
) -> None:
    on = json.loads((result_dir / "summary.json").read_text())
    assert on["uncertainty"]["method"].startswith("moment-space")
    assert on["moments"]["rms"]["std_posterior"] is not None
    assert "image_spread" in on["timings_s"]  # the figures drew the spread
    out = tmp_path / "out"
    args = ["reconstruct", str(scan_file), "--out", str(out), "--no-uncertainty"]
    r = CliRunner().invoke(main, [*args, "--train-indices=even", *FAST])
    assert r.exit_code == 0, r.output
    off = json.loads((out / "summary.json").read_text())
    assert off["uncertainty"] is None
    assert off["moments"]["rms"]["std_posterior"] is None
    assert off["moments"]["rms"]["std"] == off["moments"]["rms"]["std_ensemble"]
    assert "ensemble members only" in off["uncertainty_note"]
    assert "image_spread" not in off["timings_s"]


def test_refuses_non_empty_out(scan_file: Path, result_dir: Path) -> None:
    r = CliRunner().invoke(
        main, ["reconstruct", str(scan_file), "--out", str(result_dir)]
    )
    assert r.exit_code != 0 and "not empty" in r.output


def test_predict_on_another_dataset_and_settings(
    result_dir: Path, tmp_path: Path
) -> None:
    other = make_synthetic_quad_scan(
        "gaussian",
        n_particles=500,
        n_settings=3,
        k1_range=(-3.0, 3.0),
        screen_shape=(16, 20),
        pixel_size=(1.5e-3, 1.5e-3),
        seed=5,
    )
    write_quad_scan(other, tmp_path / "other.h5")
    out = tmp_path / "pred.npy"
    args = [
        "predict",
        str(result_dir),
        "--dataset",
        str(tmp_path / "other.h5"),
        "--out",
        str(out),
        "--particles",
        "1000",
    ]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output
    img = np.load(out)
    assert img.shape == (3, 16, 20)
    assert np.allclose(img.sum((-2, -1)), 1.0, atol=1e-5)
    r = CliRunner().invoke(main, args)
    assert r.exit_code != 0 and "exists" in r.output
    out2 = tmp_path / "p2.npy"
    r = CliRunner().invoke(
        main,
        [
            "predict",
            str(result_dir),
            "--settings",
            "-1.5,2.5",
            "--out",
            str(out2),
            "--particles",
            "1000",
        ],
    )
    assert r.exit_code == 0, r.output
    assert np.load(out2).shape == (2, 24, 24)
    # the per-pixel spread, on the unit-sum scale of the images
    std = tmp_path / "std.npy"
    r = CliRunner().invoke(
        main, [*args[:-2], "--particles", "1000", "--force", "--std-out", str(std)]
    )
    assert r.exit_code == 0, r.output
    spread = np.load(std)
    assert spread.shape == (3, 16, 20) and spread.dtype == np.float32
    assert spread.min() >= 0 and 0 < spread.max() < np.load(out).max()
    r = CliRunner().invoke(
        main, [*args, "--force", "--std-out", str(tmp_path / "s.txt")]
    )
    assert r.exit_code != 0 and "--std-out" in r.output


def _snapshots(out: Path) -> list[dict]:
    return torch.load(out / "ensemble.pt", weights_only=True)["snapshots"]


def test_resume_completes_an_interrupted_run(
    scan_file: Path, tmp_path: Path, monkeypatch
) -> None:
    """Ctrl-C at step 3 (after the checkpoint of the first snapshot), resume, and
    get the uninterrupted run's ensemble bit for bit."""
    args = ["reconstruct", str(scan_file), *FAST, "--no-figures"]
    ref = tmp_path / "ref"
    assert CliRunner().invoke(main, [*args, "--out", str(ref)]).exit_code == 0
    out = tmp_path / "out"
    real = cli_reconstruct.reconstruct

    def interrupted(*a, callback=None, **kw):
        def stop(info):
            callback(info)
            if info.step >= 3:  # the first report: the snapshot at step 3
                raise KeyboardInterrupt  # as Ctrl-C

        return real(*a, callback=stop, **kw)

    monkeypatch.setattr(cli_reconstruct, "reconstruct", interrupted)
    r = CliRunner().invoke(main, [*args, "--out", str(out)])
    assert r.exit_code == 1 and "Aborted" in r.output
    assert "--resume continues it" in r.output
    assert not out.exists()  # nothing half-written where results belong
    assert (partial_folder(out) / "checkpoint.pt").is_file()
    monkeypatch.setattr(cli_reconstruct, "reconstruct", real)
    r = CliRunner().invoke(main, [*args, "--out", str(out), "--resume"])
    assert r.exit_code == 0, r.output
    assert not partial_folder(out).exists()
    got, want = _snapshots(out), _snapshots(ref)
    assert len(got) == len(want) == 2
    for a, b in zip(got, want, strict=True):
        for k in a:
            assert torch.equal(a[k], b[k]), k


def _interrupt_after_first_checkpoint(monkeypatch) -> Callable[[], None]:
    """Make ``reconstruct`` stop as Ctrl-C after the first snapshot's
    checkpoint; returns the function that puts the real one back."""
    real = cli_reconstruct.reconstruct

    def interrupted(*a, callback=None, **kw):
        def stop(info):
            callback(info)
            if info.step >= 3:  # after the checkpoint of the first snapshot
                raise KeyboardInterrupt

        return real(*a, callback=stop, **kw)

    monkeypatch.setattr(cli_reconstruct, "reconstruct", interrupted)
    return lambda: monkeypatch.setattr(cli_reconstruct, "reconstruct", real)


def test_resume_takes_the_runs_train_indices(
    scan_file: Path, tmp_path: Path, monkeypatch
) -> None:
    out = tmp_path / "out"
    args = ["reconstruct", str(scan_file), *FAST, "--no-figures", "--out", str(out)]
    restore = _interrupt_after_first_checkpoint(monkeypatch)
    r = CliRunner().invoke(main, [*args, "--train-indices", "even"])
    assert r.exit_code == 1 and "--resume continues it" in r.output
    stored = json.loads((partial_folder(out) / "selection.json").read_text())
    assert stored == {"train_indices": {"scan": [0, 2, 4]}}
    restore()
    # another selection given is refused, naming both
    r = CliRunner().invoke(main, [*args, "--resume", "--train-indices", "odd"])
    assert r.exit_code == 1
    assert "trained on other settings" in r.output
    assert "[1, 3, 5]" in r.output and "[0, 2, 4]" in r.output, r.output
    assert (partial_folder(out) / "checkpoint.pt").is_file()  # still resumable
    # none given: the run's own (its data match the checkpoint's fingerprint)
    r = CliRunner().invoke(main, [*args, "--resume"])
    assert r.exit_code == 0, r.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["train_indices"] == [0, 2, 4]  # one scan: a list


def test_resume_of_a_run_without_stored_train_indices_names_them(
    scan_file: Path, tmp_path: Path, monkeypatch
) -> None:
    """A run interrupted before selection.json existed (removed here) resumes
    with the --train-indices given, and says so when they differ."""
    out = tmp_path / "out"
    args = ["reconstruct", str(scan_file), *FAST, "--no-figures", "--out", str(out)]
    restore = _interrupt_after_first_checkpoint(monkeypatch)
    r = CliRunner().invoke(main, [*args, "--train-indices", "even"])
    assert r.exit_code == 1 and "--resume continues it" in r.output
    (partial_folder(out) / "selection.json").unlink()
    restore()
    r = CliRunner().invoke(main, [*args, "--resume"])
    assert r.exit_code == 1 and "other training data" in r.output
    assert "give the same again with --resume" in r.output, r.output
    r = CliRunner().invoke(main, [*args, "--resume", "--train-indices", "even"])
    assert r.exit_code == 0, r.output


def test_interrupt_before_the_first_checkpoint_says_so(
    scan_file: Path, tmp_path: Path, monkeypatch
) -> None:
    out = tmp_path / "out"
    real = cli_reconstruct.reconstruct

    def interrupted(*a, callback=None, **kw):
        def stop(info):
            raise KeyboardInterrupt  # Ctrl-C at the first report

        return real(*a, callback=stop, **kw)

    monkeypatch.setattr(cli_reconstruct, "reconstruct", interrupted)
    args = ["reconstruct", str(scan_file), "--out", str(out), "--no-figures"]
    r = CliRunner().invoke(main, [*args, "--steps", "400", "--snapshots", "2"])
    assert r.exit_code == 1 and "Aborted" in r.output
    assert "before the first checkpoint (written every 100 steps)" in r.output
    assert "--resume continues it" not in r.output
    assert not out.exists() and not partial_folder(out).exists()


def _resume_on_other_images(scan_file: Path, out: Path, tmp_path: Path):
    """``reconstruct --resume`` into ``out`` with a copy of the scan whose
    images are flipped (same shapes, other training data)."""
    other = tmp_path / "other.h5"
    ds = read_quad_scan(scan_file)
    write_quad_scan(ds.with_step({"step": "test"}, images=ds.images.flip(-1)), other)
    return CliRunner().invoke(
        main,
        ["reconstruct", str(other), "--out", str(out), "--no-figures", "--resume"],
    )


def test_resume_refuses_other_options_and_other_data(
    scan_file: Path, tmp_path: Path
) -> None:
    out = tmp_path / "out"
    args = ["reconstruct", str(scan_file), "--out", str(out), "--no-figures"]
    assert CliRunner().invoke(main, [*args, *FAST]).exit_code == 0
    r = CliRunner().invoke(
        main, [*args, "--resume", "--steps", "20", "--particles", "512"]
    )
    assert r.exit_code == 1
    assert "--steps 20 (checkpoint: 6)" in r.output, r.output
    assert "--particles" not in r.output.split("options:")[1].split(".")[0]
    # other data: same shapes, other images
    r = _resume_on_other_images(scan_file, out, tmp_path)
    assert r.exit_code == 1 and "other training data" in r.output, r.output
    assert (out / "summary.json").is_file()
    # nothing to resume
    r = CliRunner().invoke(main, [*args[:3], str(tmp_path / "new"), "--resume"])
    assert r.exit_code == 1 and "no checkpoint.pt" in r.output


def test_resume_of_a_finished_result_checks_options_against_its_checkpoint(
    scan_file: Path, tmp_path: Path
) -> None:
    out = tmp_path / "out"
    args = ["reconstruct", str(scan_file), "--out", str(out), "--no-figures"]
    assert CliRunner().invoke(main, [*args, *FAST]).exit_code == 0
    # 8 steps are a multiple of the checkpoint's 2 snapshots (not of the default)
    r = CliRunner().invoke(main, [*args, "--resume", "--steps", "8"])
    assert r.exit_code == 1 and "--steps 8 (checkpoint: 6)" in r.output, r.output
    # other data: refused, and no copy of the result is left as a "checkpoint"
    r = _resume_on_other_images(scan_file, out, tmp_path)
    assert r.exit_code == 1 and "other training data" in r.output, r.output
    assert "--resume continues it" not in r.output
    assert not partial_folder(out).exists()


# plot_corner is drawn by the forked child (cli.background), the image grid by
# the command's own process: a failure in either fails the command
@pytest.mark.parametrize("figure", ["plot_corner", "plot_image_comparison"])
def test_late_failure_with_force_keeps_the_old_result(
    scan_file: Path, tmp_path: Path, monkeypatch, figure: str
) -> None:
    out = tmp_path / "out"
    args = ["reconstruct", str(scan_file), "--out", str(out), *FAST]
    assert CliRunner().invoke(main, args).exit_code == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    def broken(*a, **kw):
        raise RuntimeError("figure failed")

    monkeypatch.setattr(cli_reconstruct, figure, broken)
    r = CliRunner().invoke(main, [*args, "--seed", "1", "--force"])
    assert r.exit_code != 0
    assert "figure failed" in r.output
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_force_no_figures_drops_the_old_figures(
    scan_file: Path, tmp_path: Path
) -> None:
    out = tmp_path / "out"
    args = ["reconstruct", str(scan_file), "--out", str(out), *FAST]
    assert CliRunner().invoke(main, args).exit_code == 0
    assert (out / "images.png").exists()
    r = CliRunner().invoke(main, [*args, "--force", "--no-figures"])
    assert r.exit_code == 0, r.output
    assert not list(out.glob("*.png"))


def test_force_keeps_files_the_user_added(scan_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    args = ["reconstruct", str(scan_file), "--out", str(out), *FAST, "--no-figures"]
    assert CliRunner().invoke(main, args).exit_code == 0
    (out / "notes.txt").write_text("mine")
    (out / "mysub").mkdir()
    r = CliRunner().invoke(main, [*args, "--force"])
    assert r.exit_code == 1 and "did not write (mysub, notes.txt)" in r.output
    assert (out / "notes.txt").read_text() == "mine" and (out / "mysub").is_dir()


def test_a_fresh_run_keeps_an_interrupted_runs_checkpoint(
    scan_file: Path, tmp_path: Path, monkeypatch
) -> None:
    out = tmp_path / "out"
    args = ["reconstruct", str(scan_file), *FAST, "--no-figures", "--out", str(out)]
    restore = _interrupt_after_first_checkpoint(monkeypatch)
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 1 and "--resume continues it" in r.output
    restore()
    checkpoint = (partial_folder(out) / "checkpoint.pt").read_bytes()
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 1
    assert "pass --resume to continue it or --force to discard it" in r.output
    assert (partial_folder(out) / "checkpoint.pt").read_bytes() == checkpoint
    assert not out.exists()
    r = CliRunner().invoke(main, [*args, "--force"])  # discards it
    assert r.exit_code == 0, r.output
    assert not partial_folder(out).exists()


def test_resume_without_a_checkpoint_names_force_for_the_staging_folder(
    scan_file: Path, tmp_path: Path
) -> None:
    """A run killed before its first checkpoint leaves only selection.json."""
    out = tmp_path / "out"
    partial_folder(out).mkdir()
    (partial_folder(out) / "selection.json").write_text("{}")
    args = ["reconstruct", str(scan_file), *FAST, "--no-figures", "--out", str(out)]
    r = CliRunner().invoke(main, [*args, "--resume"])
    assert r.exit_code == 1 and "run with --force instead of --resume" in r.output
    r = CliRunner().invoke(main, [*args, "--force"])
    assert r.exit_code == 0, r.output


def test_a_second_run_into_a_busy_folder_is_refused(
    scan_file: Path, tmp_path: Path
) -> None:
    out = tmp_path / "out"
    lock = tmp_path / ".out.lock"  # as a running process (this one) holds it
    lock.write_text(json.dumps({"pid": os.getpid(), "host": socket.gethostname()}))
    # the running one's checkpoint: not this refused run's to offer for --resume
    (tmp_path / ".out.partial").mkdir()
    (tmp_path / ".out.partial" / "checkpoint.pt").write_bytes(b"of the other run")
    r = CliRunner().invoke(
        main, ["reconstruct", str(scan_file), "--out", str(out), *FAST]
    )
    assert r.exit_code == 1 and "being written by another run" in r.output
    assert "--resume continues it" not in r.output
    assert not out.exists() and lock.exists()


def _corrupt(path: Path, tmp: Path, how: str) -> Path:
    bad = tmp / f"{how}.h5"
    bad.write_bytes(path.read_bytes())
    with h5py.File(bad, "r+") as f:
        if how == "nan":
            img = f["images"][...]
            img[0, 0, 3, 3] = np.nan
            f["images"][...] = img
        elif how == "zero":
            img = f["images"][...]
            img[1] = 0.0
            f["images"][...] = img
        elif how == "unknown-element":
            f["settings"].attrs["names"] = json.dumps(["QX.k1"])
        elif how == "mismatch":
            del f["settings"]
            f["settings"] = np.zeros((2, 1))
            f["settings"].attrs["names"] = json.dumps(["Q1.k1"])
            f["settings"].attrs["units"] = json.dumps(["1/m^2"])
    return bad


@pytest.mark.parametrize(
    "how", ["nan", "zero", "unknown-element", "mismatch", "garbage"]
)
def test_bad_input_gives_a_clear_error(
    scan_file: Path, tmp_path: Path, how: str
) -> None:
    if how == "garbage":
        bad = tmp_path / "garbage.h5"
        bad.write_bytes(b"this is not hdf5")
    else:
        bad = _corrupt(scan_file, tmp_path, how)
    r = CliRunner().invoke(
        main, ["reconstruct", str(bad), "--out", str(tmp_path / "o"), *FAST]
    )
    assert r.exit_code != 0
    assert "Error" in r.output and "Traceback" not in r.output
    assert not isinstance(r.exception, (IndexError, KeyError, TypeError))


# ------------------------------------------------------------------ several scans
@pytest.fixture(scope="module")
def two_scan_file(tmp_path_factory) -> Path:
    """Format version 2: one beam, a straight scan and one after a dipole."""
    beam = sample_preset_beam("gaussian", 2000, torch.Generator().manual_seed(4))
    straight = make_synthetic_quad_scan(
        particles=beam, n_settings=4, k1_range=(-8.0, 8.0), screen_shape=(24, 24)
    )
    bent_line = [
        {"type": "Quadrupole", "name": "Q1", "length": 0.1, "k1": 0.0},
        {"type": "Drift", "name": "D1", "length": 0.5},
        {"type": "Dipole", "name": "B1", "length": 0.3, "angle": 0.3},
        {"type": "Drift", "name": "D2", "length": 0.5},
        {"type": "Screen", "name": "S2"},
    ]
    bent = make_synthetic_quad_scan(
        particles=beam,
        beamline_spec=bent_line,
        n_settings=3,
        k1_range=(-5.0, 5.0),
        screen_shape=(16, 20),
        pixel_size=(1.5e-3, 1.5e-3),
    )
    path = tmp_path_factory.mktemp("v2") / "two.h5"
    write_scans(MultiScanDataset({"straight": straight, "bent": bent}), path)
    return path


def test_reconstruct_and_predict_version_2(two_scan_file: Path, tmp_path) -> None:
    out = tmp_path / "out"
    r = CliRunner().invoke(
        main,
        [
            "reconstruct",
            str(two_scan_file),
            "--out",
            str(out),
            "--dims",
            "6",
            "--train-indices",
            "straight:0,2;bent:all",
            *FAST,
        ],
    )
    assert r.exit_code == 0, r.output
    s = json.loads((out / "summary.json").read_text())
    assert s["scans"]["straight"]["held_out_indices"] == [1, 3]
    assert s["scans"]["bent"]["held_out_indices"] == []
    assert (out / "images_straight.png").exists() and (out / "images_bent.png").exists()
    pred = tmp_path / "pred.h5"
    args = ["predict", str(out), "--dataset", str(two_scan_file), "--out", str(pred)]
    r = CliRunner().invoke(main, [*args, "--particles", "1000"])
    assert r.exit_code == 0, r.output
    got, want = read_scans(pred), read_scans(two_scan_file)
    assert got.format_version == 2 and got.names == want.names
    for name, scan in want:
        assert got[name].shape == (scan.n_settings, 1, *scan.screen_shape)
        assert torch.equal(got[name].settings, scan.settings)
        torch.testing.assert_close(
            got[name].images.sum((-2, -1)),
            torch.ones(scan.n_settings, 1),
            rtol=0,
            atol=1e-5,
        )
    # several scans do not fit one .npy array: a clear error, and no folder
    # of the --out path made before it
    npy = tmp_path / "new" / "sub" / "p.npy"
    r = CliRunner().invoke(main, [*args[:-1], str(npy)])
    assert r.exit_code == 1 and "holds 2 scans" in r.output
    assert not (tmp_path / "new").exists()
    # nor one .npy spread, refused before the predictions are written
    r = CliRunner().invoke(main, [*args, "--force", "--std-out", str(npy)])
    assert r.exit_code == 1 and "2 scans; write them to an .npz" in r.output
    assert not (tmp_path / "new").exists()
    # nothing is written into the result folder (its --force would refuse it)
    r = CliRunner().invoke(main, [*args[:-1], str(out / "pred.h5")])
    assert r.exit_code == 1 and "inside the result folder" in r.output
    assert not (out / "pred.h5").exists()
    # the spread of every scan: one array per scan name
    std = tmp_path / "std.npz"
    r = CliRunner().invoke(
        main, [*args, "--particles", "1000", "--force", "--std-out", str(std)]
    )
    assert r.exit_code == 0, r.output
    with np.load(std) as spread:
        assert sorted(spread.files) == sorted(want.names)
        for name, scan in want:
            assert spread[name].shape == (scan.n_settings, *scan.screen_shape)


def _predict_ok(result_dir: Path, dataset: Path, out: Path):
    """``diffaccel predict RESULT --dataset DATASET --out OUT``, exit code 0."""
    r = CliRunner().invoke(
        main, ["predict", str(result_dir), "--dataset", str(dataset), "--out", str(out)]
    )
    assert r.exit_code == 0, r.output
    return r


def test_predict_h5_of_a_version_1_file_is_version_1(
    result_dir: Path, scan_file: Path, tmp_path: Path
) -> None:
    pred = tmp_path / "pred.h5"
    _predict_ok(result_dir, scan_file, pred)
    with h5py.File(pred, "r") as h5:
        assert int(h5.attrs["format_version"]) == 1
    assert read_quad_scan(pred).shape == (6, 1, 24, 24)


def test_predict_of_settings_on_the_screen_warns_of_nothing(
    result_dir: Path, scan_file: Path, tmp_path: Path
) -> None:
    pred = tmp_path / "pred.h5"
    r = _predict_ok(result_dir, scan_file, pred)
    assert "warning" not in r.output
    step = read_quad_scan(pred).metadata["preprocessing"][-1]
    assert step["step"] == "predicted" and step["warnings"] == []
    assert len(step["fraction_on_screen"]) == 6
    assert min(step["fraction_on_screen"]) > 0.9


def test_predict_warns_when_a_setting_throws_the_beam_off_the_screen(
    result_dir: Path, scan_file: Path, tmp_path: Path
) -> None:
    # at k1 = 200 about a tenth of the beam reaches the
    # screen, yet its sum-normalised image looks like a beam
    other = tmp_path / "k1_200.h5"
    other.write_bytes(scan_file.read_bytes())
    with h5py.File(other, "r+") as h5:
        h5["settings"][5] = 200.0
    pred = tmp_path / "pred.h5"
    args = ["predict", str(result_dir), "--dataset", str(other)]
    r = CliRunner().invoke(main, [*args, "--out", str(pred)])
    assert r.exit_code == 0, r.output
    step = read_quad_scan(pred).metadata["preprocessing"][-1]
    fraction = step["fraction_on_screen"]
    assert fraction[5] < LOW_ON_SCREEN_FRACTION and min(fraction[:5]) > 0.9
    (w,) = step["warnings"]
    assert w.startswith(
        "scan 'scan': only part of the predicted beam lands on the screen at 1 of "
        f"6 settings: setting 5 (Q1.k1 = 200) {100 * fraction[5]:.1f} %"
    )
    assert f"warning: {w}" in r.output
    # the .npy output has no metadata: the warning is printed all the same
    r = CliRunner().invoke(main, [*args, "--out", str(tmp_path / "pred.npy")])
    assert r.exit_code == 0, r.output
    assert f"warning: {w}" in r.output
    r = CliRunner().invoke(
        main,
        [
            "predict",
            str(result_dir),
            "--settings",
            "0,200",
            "--out",
            str(tmp_path / "k1.npy"),
        ],
    )
    assert r.exit_code == 0, r.output
    assert "warning: scan 'scan': only part of the predicted beam" in r.output
    assert "at 1 of 2 settings: setting 1 (Q1.k1 = 200)" in r.output


@pytest.mark.parametrize(
    ("rule", "message"),
    [("straight:9", "indices must be distinct and in [0, 4)"), ("x:1", "SCAN:RULE")],
    ids=["out_of_range", "unknown_scan"],
)
def test_bad_train_indices_name_the_scan(
    two_scan_file: Path, tmp_path: Path, rule: str, message: str
) -> None:
    r = CliRunner().invoke(
        main,
        [
            "reconstruct",
            str(two_scan_file),
            "--out",
            str(tmp_path / "o"),
            f"--train-indices={rule}",
            *FAST,
        ],
    )
    assert r.exit_code == 2 and message in r.output


def _distributed_cli_worker(rank: int, port: int, args: list[str], log: str) -> None:
    # what torchrun sets for each process
    os.environ.update(
        RANK=str(rank),
        LOCAL_RANK=str(rank),
        WORLD_SIZE="2",
        MASTER_ADDR="127.0.0.1",
        MASTER_PORT=str(port),
    )
    torch.set_num_threads(1)
    r = CliRunner().invoke(main, args)
    Path(f"{log}{rank}").write_text(f"{r.exit_code}\n{r.output}")


@pytest.mark.parametrize("rank", [0, 1])
def test_distributed_refusal_is_shared_with_every_process(
    scan_file: Path, tmp_path: Path, monkeypatch, rank: int
) -> None:
    # in-process: process 0 broadcasts its refusal of --out, process 1 raises it
    tdist = cli_reconstruct.tdist
    sent: list = []

    def broadcast(objects: list, src: int) -> None:
        assert src == 0
        if rank == 0:
            sent.append(objects[0])
        else:
            objects[0] = "--out holds files that are not a diffaccel result"

    monkeypatch.setattr(cli_reconstruct, "_init_distributed", lambda device: "cpu")
    monkeypatch.setattr(tdist, "get_rank", lambda: rank)
    monkeypatch.setattr(tdist, "broadcast_object_list", broadcast)
    monkeypatch.setattr(tdist, "destroy_process_group", lambda: None)
    out = tmp_path / "out"
    out.mkdir()
    (out / "mine.txt").write_text("a user's file")
    r = CliRunner().invoke(
        main,
        ["reconstruct", str(scan_file), "--out", str(out), *FAST, "--distributed"],
    )
    assert r.exit_code == 1, r.output
    if rank == 0:
        assert len(sent) == 1 and "mine.txt" in sent[0]
    else:
        assert "process 0 stopped: --out holds files" in r.output
    assert (out / "mine.txt").read_text() == "a user's file"


@pytest.mark.slow  # two spawned interpreters (~15 s under load)
def test_distributed_run_stops_every_process_when_out_is_refused(
    scan_file: Path, tmp_path: Path
) -> None:
    import torch.multiprocessing as mp

    out = tmp_path / "out"
    out.mkdir()
    (out / "mine.txt").write_text("a user's file")  # not a result: refused
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    args = ["reconstruct", str(scan_file), "--out", str(out), *FAST, "--distributed"]
    log = str(tmp_path / "rank")
    ctx = mp.spawn(
        _distributed_cli_worker, args=(port, args, log), nprocs=2, join=False
    )
    # before the fix rank 1 waited for rank 0 in a barrier forever
    finished = False
    for _ in range(120):
        if ctx.join(timeout=1):
            finished = True
            break
    if not finished:
        for p in ctx.processes:
            p.kill()
    assert finished, "a process hung after process 0 refused --out"
    codes = [Path(f"{log}{r}").read_text().split("\n", 1) for r in (0, 1)]
    assert codes[0][0] == "1" and "mine.txt" in codes[0][1], codes[0]
    assert codes[1][0] == "1" and "process 0 stopped" in codes[1][1], codes[1]
    assert "mine.txt" in codes[1][1]  # the same reason, on one line
    assert (out / "mine.txt").read_text() == "a user's file"


def test_split_members_needs_distributed(scan_file: Path, tmp_path: Path) -> None:
    r = CliRunner().invoke(
        main,
        [
            *("reconstruct", str(scan_file), "--out", str(tmp_path / "o"), *FAST),
            *("--split", "members"),
        ],
    )
    assert r.exit_code == 2 and "--split members needs --distributed" in r.output
    assert not (tmp_path / "o").exists()


@pytest.mark.slow  # two spawned interpreters
def test_distributed_members_write_one_ensemble_of_both_processes(
    scan_file: Path, tmp_path: Path
) -> None:
    import torch.multiprocessing as mp

    out = tmp_path / "out"
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    args = ["reconstruct", str(scan_file), "--out", str(out), *FAST]
    args += ["--distributed", "--split", "members", "--no-figures"]
    log = str(tmp_path / "rank")
    mp.spawn(_distributed_cli_worker, args=(port, args, log), nprocs=2, join=True)
    codes = [Path(f"{log}{r}").read_text().split("\n", 1) for r in (0, 1)]
    assert codes[0][0] == "0" and codes[1][0] == "0", codes
    assert "wrote" in codes[0][1] and "wrote" not in codes[1][1]
    result = load(out)
    assert len(result.snapshots) == 2 * 2  # --snapshots 2 on each process
    assert result.info["member_processes"] == 2
    summary = json.loads((out / "summary.json").read_text())
    assert summary["member_processes"] == 2 and summary["snapshots"] == 4
    assert {"checkpoint.pt", "checkpoint.rank1.pt"} <= {p.name for p in out.iterdir()}
    assert summary["metrics"]["images_train"]["relative_l1"] < 0.5


def test_6d_run_states_what_the_prior_sets(tmp_path: Path) -> None:
    """The AWA 6D layout's unseen correlations (px-pz, py-z): their values and
    what the same images would fit elsewhere, in the summary and printed."""
    data = make_synthetic_awa6d(
        "correlated",
        n_particles=3000,
        k1_values=[-12.0, 0.0, 12.0],
        screen_shape=(24, 24),
        seed=2,
    )
    path = tmp_path / "awa6d.h5"
    write_scans(data, path)
    out = tmp_path / "o"
    args = ["reconstruct", str(path), "--out", str(out), "--dims", "6"]
    r = CliRunner().invoke(main, [*args, *FAST, "--no-figures", "--no-uncertainty"])
    assert r.exit_code == 0, r.output
    s = json.loads((out / "summary.json").read_text())
    dep = {e["pair"]: e for e in s["prior_dependence"]}
    assert set(dep) == {"px-pz", "py-z"}
    assert "unseen_weight" in s["prior_dependence_note"]
    assert dep["px-pz"]["moves"] == "rms_pz" and dep["py-z"]["moves"] == "rms_z"
    for e in dep.values():
        # held near the prior point by the prior term: zero partial
        # correlation (a short run)
        assert abs(e["partial_correlation"]) < 0.2, e["partial_correlation"]
        at = e["if_partial_correlation"]
        assert [a["partial_correlation"] for a in at] == [
            -0.6,
            -0.3,
            -0.1,
            0.1,
            0.3,
            0.6,
        ]
        # elsewhere along the line the same images fit another z emittance
        # (the line may pass the smallest one near the prior point, so one
        # side can barely change: this short run's -9 % / +0.1 % at -0.1 / +0.1)
        changes = [a["relative_change"]["emit_z"] for a in at if a["relative_change"]]
        assert max(abs(c) for c in changes) > 0.02
    assert r.output.count("set by the prior, not the images:") == 2


def test_reconstruct_warns_when_the_fit_misses_its_training_images(
    scan_file: Path, tmp_path: Path
) -> None:
    # settings 200x too large (units mistaken): training
    # cannot reproduce the images, and the run must say so, not just end
    bad = tmp_path / "k1_big.h5"
    bad.write_bytes(scan_file.read_bytes())
    with h5py.File(bad, "r+") as f:
        f["settings"][...] = f["settings"][...] * 200.0
    out = tmp_path / "out"
    r = CliRunner().invoke(
        main,
        ["reconstruct", str(bad), "--out", str(out), "--no-figures", *FAST],
    )
    assert r.exit_code == 0, r.output
    s = json.loads((out / "summary.json").read_text())
    assert s["metrics"]["images_train"]["relative_l1"] > 0.5
    # (the fit-quality alarms add their own warnings: moments missed...)
    (fit,) = [w for w in s["warnings"] if "does not reproduce" in w]
    (screen,) = [w for w in s["warnings"] if "only part of the predicted" in w]
    assert "does not reproduce its training images" in fit
    # settings 200x too strong also throw the reconstructed beam off the screen
    assert "only part of the predicted beam lands on the screen at 6 of 6" in screen
    assert max(s["scans"]["scan"]["fraction_on_screen"]) < 0.5
    assert "warning: the reconstruction does not reproduce" in r.output
    assert "settings in the wrong units" in r.output


@pytest.mark.parametrize(
    ("attr", "value", "message"),
    [
        ("p0c", 63e6, "p0c = 6.3e+07 eV; the reconstruction was made at p0c"),
        ("species", "positron", "species 'positron'; the reconstruction is of"),
    ],
    ids=["p0c", "species"],
)
def test_predict_refuses_a_dataset_of_another_beam(
    result_dir: Path, scan_file: Path, tmp_path: Path, attr: str, value, message
) -> None:
    other = tmp_path / "other.h5"
    other.write_bytes(scan_file.read_bytes())
    with h5py.File(other, "r+") as h5:
        h5.attrs[attr] = value
    pred = tmp_path / "pred.h5"
    r = CliRunner().invoke(
        main,
        ["predict", str(result_dir), "--dataset", str(other), "--out", str(pred)],
    )
    assert r.exit_code != 0
    assert message in r.output and "this is a bug" not in r.output
    assert not pred.exists()
