"""Writing results safely: replace only what diffaccel wrote, resume cleanly,
OS conditions named, the headline numbers and report of a reconstruction."""

from __future__ import annotations

import errno
import json
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
from click.testing import CliRunner

import diffaccel.cli.reconstruct as cli_reconstruct
import diffaccel.data.atomic as atomic
from diffaccel.cli import main
from diffaccel.data import (
    make_synthetic_quad_scan,
    partial_folder,
    read_openpmd_particles,
    write_quad_scan,
)
from diffaccel.hysteresis import LaplaceBand, PreisachMesh, PreisachModel, save_fit

FAST = ["--particles", "512", "--steps", "6", "--snapshots", "2"]


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
def result_dir(scan_file: Path, tmp_path_factory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("res") / "out"
    args = ["reconstruct", str(scan_file), "--out", str(out), "--charge", "250"]
    r = CliRunner().invoke(main, [*args, "--train-indices=even", *FAST])
    assert r.exit_code == 0, r.output
    return out, r.output


def _files(folder: Path) -> dict[str, tuple[bytes, int]]:
    return {
        p.name: (p.read_bytes(), p.stat().st_mtime_ns)
        for p in folder.iterdir()
        if p.is_file()
    }


def test_reconstruct_prints_the_headline_numbers_and_writes_a_report(
    result_dir: tuple[Path, str],
) -> None:
    out, output = result_dir
    s = json.loads((out / "summary.json").read_text())
    emit = s["moments"]["norm_emit_x"]
    line = next(x for x in output.splitlines() if x.startswith("emittance"))
    assert f"x {1e6 * emit['mean']:.4g} +- {1e6 * emit['std']:.2g} mm mrad" in line
    assert "twiss: beta_x" in output and "alpha_y" in output
    assert "rms: x " in output and " mm" in output
    assert f"report: {out / 'report.md'}" in output
    report = (out / "report.md").read_text()
    assert "| emittance (normalised) x [mm mrad] |" in report
    assert "| rms x [mm] |" in report and "![images.png](images.png)" in report
    rms_x = s["metrics"]["ground_truth"]["rms_x"]
    assert f"| {100 * rms_x:+.1f} % |" in report
    assert "report.md" in json.loads((out / ".diffaccel-result").read_text())["files"]


def test_charge_sets_the_particle_files_bunch_charge(
    result_dir: tuple[Path, str],
) -> None:
    out, _ = result_dir
    s = json.loads((out / "summary.json").read_text())
    assert s["particles_charge_C"] == pytest.approx(250e-12, rel=1e-12)
    assert s["particles_charge_source"] == "given"
    with h5py.File(out / "particles.h5") as h5:
        g = h5["data/0/particles"]
        assert float(g.attrs["totalCharge"]) == pytest.approx(250e-12, rel=1e-12)
        assert float(g["weight"][...].sum()) == pytest.approx(250e-12, rel=1e-9)
    read_openpmd_particles(out / "particles.h5")  # still our reader's file


def test_charge_from_the_datasets_metadata_and_a_bad_one(
    scan_file: Path, tmp_path: Path
) -> None:
    marked = tmp_path / "charged.h5"
    marked.write_bytes(scan_file.read_bytes())
    with h5py.File(marked, "r+") as h5:
        meta = json.loads(h5.attrs["metadata"])
        h5.attrs["metadata"] = json.dumps({**meta, "charge_C": -1.0})
    out = tmp_path / "o"
    args = ["reconstruct", str(marked), "--out", str(out), "--no-figures", *FAST]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 1 and "metadata charge_C" in r.output
    assert "positive" in r.output and not out.exists()
    with h5py.File(marked, "r+") as h5:
        h5.attrs["metadata"] = json.dumps({**meta, "charge_C": 2e-10})
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output
    s = json.loads((out / "summary.json").read_text())
    assert s["particles_charge_C"] == 2e-10
    assert s["particles_charge_source"] == "dataset"


def test_resume_of_a_finished_result_does_nothing_and_says_so(
    scan_file: Path, tmp_path: Path
) -> None:
    out = tmp_path / "out"
    args = ["reconstruct", str(scan_file), "--out", str(out), *FAST]
    assert CliRunner().invoke(main, args).exit_code == 0
    before = _files(out)
    # --no-uncertainty would drop the std, --no-figures the figures: neither runs
    r = CliRunner().invoke(
        main, [*args, "--resume", "--no-uncertainty", "--no-figures"]
    )
    assert r.exit_code == 0, r.output
    assert "nothing to resume" in r.output and "unchanged" in r.output
    assert _files(out) == before  # bytes and modification times
    assert not partial_folder(out).exists()


def test_a_resumed_run_keeps_no_file_of_the_failed_attempt(
    scan_file: Path, tmp_path: Path, monkeypatch
) -> None:
    """Training ends, the write fails after some figures (as a full disk would):
    ``--resume --no-figures`` finishes without the failed attempt's figures."""
    out = tmp_path / "out"
    args = ["reconstruct", str(scan_file), "--out", str(out), *FAST]

    def disk_full(*a, **kw):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(cli_reconstruct, "plot_image_comparison", disk_full)
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 1, r.output
    assert "no space left on the device (disk full)" in r.output
    assert "bug" not in r.output
    kept = {p.name for p in partial_folder(out).iterdir()}
    assert "checkpoint.pt" in kept and "phase_space.png" in kept  # the old attempt
    monkeypatch.undo()
    r = CliRunner().invoke(main, [*args, "--resume", "--no-figures"])
    assert r.exit_code == 0, r.output
    names = {p.name for p in out.iterdir()}
    assert not [n for n in names if n.endswith(".png")], names
    summary = json.loads((out / "summary.json").read_text())
    assert "figures" not in summary


def _foreign_npy(path: Path) -> bytes:
    with path.open("wb") as f:
        np.save(f, np.ones((2, 3), dtype=np.float32))  # a user's array
    return path.read_bytes()


def test_predict_force_replaces_only_files_diffaccel_wrote(
    result_dir: tuple[Path, str], scan_file: Path, tmp_path: Path
) -> None:
    out_dir, _ = result_dir
    base = ["predict", str(out_dir), "--dataset", str(scan_file), "--force"]
    base += ["--particles", "500"]
    for name in ("measured.npy", "measured.h5"):
        target = tmp_path / name
        if name.endswith(".npy"):
            mine = _foreign_npy(target)
        else:
            write_quad_scan(
                make_synthetic_quad_scan("gaussian", n_particles=200, n_settings=2),
                target,
            )
            with h5py.File(target, "r+") as h5:
                del h5.attrs["written_by"]  # as a file another program wrote
            mine = target.read_bytes()
        r = CliRunner().invoke(main, [*base, "--out", str(target)])
        assert r.exit_code == 1, r.output
        assert "was not written by diffaccel" in r.output
        assert len(r.output.strip().splitlines()) == 1
        assert target.read_bytes() == mine
    # a file diffaccel wrote is replaced, and a --std-out .npz too
    ours = tmp_path / "pred.npy"
    std = tmp_path / "std.npz"
    args = [*base, "--out", str(ours), "--std-out", str(std)]
    assert CliRunner().invoke(main, args).exit_code == 0
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output
    assert np.load(ours).shape == (6, 24, 24)
    with np.load(std) as spread:
        assert spread.files == ["scan"]


def _read_only(monkeypatch) -> None:
    """Every atomic write fails as on a read-only file system."""

    def refuse(*a, dir=None, **kw):
        raise OSError(errno.EROFS, "Read-only file system", str(dir))

    monkeypatch.setattr(atomic.tempfile, "mkstemp", refuse)


@pytest.mark.parametrize("command", ["synthetic", "predict"])
def test_a_read_only_folder_is_named_in_one_line(
    command: str,
    result_dir: tuple[Path, str],
    scan_file: Path,
    tmp_path: Path,
    monkeypatch,
) -> None:
    out = tmp_path / "ro" / "pred.h5"
    if command == "synthetic":
        args = ["synthetic", str(out), "--settings", "3", "--particles", "500"]
        args += ["--shape", "16", "16"]
    else:
        args = ["predict", str(result_dir[0]), "--dataset", str(scan_file)]
        args += ["--out", str(out), "--particles", "500"]
    _read_only(monkeypatch)
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 1, r.output
    (line,) = r.output.strip().splitlines()
    assert f"cannot write {out}: read-only file system" in line, line
    assert "bug" not in line and not out.exists()


def test_a_locked_hdf5_file_is_named_as_locked(
    scan_file: Path, tmp_path: Path, monkeypatch
) -> None:
    def locked(*a, **kw):
        raise OSError(
            errno.EAGAIN,
            "Unable to synchronously open file (unable to lock file, errno = 11, "
            "error message = 'Resource temporarily unavailable')",
        )

    monkeypatch.setattr(h5py, "File", locked)
    r = CliRunner().invoke(
        main, ["reconstruct", str(scan_file), "--out", str(tmp_path / "o"), *FAST]
    )
    assert r.exit_code == 1
    assert "cannot open it: locked by another program" in r.output
    assert "not a readable HDF5 file" not in r.output


def test_a_refused_default_selection_does_not_blame_train_indices(
    tmp_path: Path,
) -> None:
    one_k1 = make_synthetic_quad_scan(
        "gaussian", n_particles=500, n_settings=1, screen_shape=(16, 16)
    )
    path = tmp_path / "one.h5"
    write_quad_scan(one_k1, path)
    r = CliRunner().invoke(
        main, ["reconstruct", str(path), "--out", str(tmp_path / "o"), *FAST]
    )
    assert r.exit_code == 1
    assert "--train-indices" not in r.output
    assert "its settings hold a single value" in r.output


def _saved_fit(fit_dir: Path) -> None:
    """A small saved Preisach fit (4-level mesh, input 0..25 A)."""
    model = PreisachModel(PreisachMesh.triangular(4), input_range=(0.0, 25.0))
    m = model.alpha.numel()
    band = LaplaceBand(torch.eye(2, m + 3, dtype=torch.float64), 0.01, 1.2)
    save_fit(fit_dir, model, band, extra={"input_column": "current_A"})


def test_hysteresis_predict_force_replaces_only_its_own_csv(
    tmp_path: Path, monkeypatch
) -> None:
    fit = tmp_path / "fit"
    _saved_fit(fit)
    data = tmp_path / "mine.csv"
    data.write_text("run,current_A\n" + "".join(f"r{i},{2.0 * i}\n" for i in range(10)))
    out = tmp_path / "measured.csv"
    out.write_text("run,current_A,field_Tm\nr0,1,0.03\n")  # a measurement
    mine = out.read_bytes()
    args = ["hysteresis", "predict", str(fit), "--input", str(data)]
    r = CliRunner().invoke(main, [*args, "--out", str(out), "--force"])
    assert r.exit_code == 1 and "was not written by diffaccel" in r.output
    assert out.read_bytes() == mine
    ours = tmp_path / "pred.csv"
    assert CliRunner().invoke(main, [*args, "--out", str(ours)]).exit_code == 0
    r = CliRunner().invoke(main, [*args, "--out", str(ours), "--force"])
    assert r.exit_code == 0, r.output
    # a read-only folder: named, in one line
    _read_only(monkeypatch)
    r = CliRunner().invoke(main, [*args, "--out", str(ours), "--force"])
    assert r.exit_code == 1
    (line,) = r.output.strip().splitlines()
    assert "read-only file system" in line and "bug" not in line
