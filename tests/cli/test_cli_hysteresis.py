"""``diffaccel hysteresis fit`` and ``predict`` through click's CliRunner."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from diffaccel.cli.main import main
from diffaccel.data import write_csv_atomic
from diffaccel.data.result_folder import MARKER
from diffaccel.hysteresis import load_fit, save_fit
from diffaccel.hysteresis.synthetic import bh_loop_case, synthetic_measurement

FAST = ["--mesh-size", "12", "--steps", "30"]


@pytest.fixture
def magnet_csv(tmp_path: Path) -> Path:
    current, field, _ = synthetic_measurement(noise=1e-4, seed=3)
    rows = [
        [f"r{i}", i * 3.0, float(c), float(f)]
        for i, (c, f) in enumerate(zip(current.tolist(), field.tolist(), strict=True))
    ]
    path = tmp_path / "magnet.csv"
    write_csv_atomic(path, ["run", "time_s", "I", "B"], rows)
    return path


def _fit(magnet_csv: Path, out: Path, *extra: str):
    args = ["hysteresis", "fit", str(magnet_csv), "--train-rows", "21"]
    args += ["--input", "I", "--output", "B", "--out", str(out), *FAST, *extra]
    return CliRunner().invoke(main, args)


def test_fit_writes_summary_model_and_figures(magnet_csv: Path, tmp_path: Path) -> None:
    out = tmp_path / "fit"
    result = _fit(magnet_csv, out)
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["train_rows"] == 21 and summary["test_rows"] == 106 - 21
    for key in ("train_rmse", "test_rmse", "fit_seconds", "test_mean_std"):
        assert summary[key] >= 0
    # % of the training output range, consistent with the absolute rmse
    pct = 100 * summary["test_rmse"] / summary["output_range"]
    assert summary["test_rmse_percent"] == pytest.approx(pct)
    # a unipolar range: no symmetry by default
    assert summary["symmetric"] is False
    # held-out rows only: less than half the straight line's error there
    assert summary["test_rmse"] < 0.5 * summary["straight_line_test_rmse"]
    for name in ("model.pt", "model.json", "fit.png", "density.png"):
        assert (out / name).stat().st_size > 0
    tensors = torch.load(out / "model.pt", weights_only=True)
    assert isinstance(tensors, dict) and "raw_density" in tensors
    assert "band.directions" in tensors
    assert not list(out.glob(".*tmp"))  # no temporary files left behind


def test_fit_refuses_to_overwrite_without_force(
    magnet_csv: Path, tmp_path: Path
) -> None:
    out = tmp_path / "fit"
    assert _fit(magnet_csv, out, "--no-figures").exit_code == 0
    again = _fit(magnet_csv, out, "--no-figures")
    assert again.exit_code != 0 and "--force" in again.output
    assert _fit(magnet_csv, out, "--force", "--no-figures").exit_code == 0


def test_fit_force_keeps_files_the_user_added(magnet_csv: Path, tmp_path: Path) -> None:
    out = tmp_path / "fit"
    assert _fit(magnet_csv, out, "--no-figures").exit_code == 0
    (out / "extra.txt").write_text("mine")
    again = _fit(magnet_csv, out, "--force", "--no-figures")
    assert again.exit_code == 1 and "did not write (extra.txt)" in again.output
    assert (out / "extra.txt").read_text() == "mine"


def test_fit_force_refuses_a_result_of_another_command(
    magnet_csv: Path, tmp_path: Path
) -> None:
    # the marker reconstruct writes (tests/data/test_result_folder.py writes one)
    out = tmp_path / "recon"
    out.mkdir()
    (out / "ensemble.pt").write_bytes(b"a reconstruction")
    marker = {"command": "reconstruct", "written": 0.0, "files": ["ensemble.pt"]}
    (out / MARKER).write_text(json.dumps(marker))
    again = _fit(magnet_csv, out, "--force", "--no-figures")
    assert again.exit_code == 1
    assert "a result of 'reconstruct', not of 'hysteresis fit'" in again.output
    assert (out / "ensemble.pt").read_bytes() == b"a reconstruction"


def test_gp_fit_force_refuses_a_fit(magnet_csv: Path, tmp_path: Path) -> None:
    out = tmp_path / "fit"
    assert _fit(magnet_csv, out, "--no-figures").exit_code == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    args = ["hysteresis", "gp-fit", str(magnet_csv), "--x", "I", "--y", "B"]
    args += ["--out", str(out), "--mesh-size", "8", "--restarts", "1", "--force"]
    again = CliRunner().invoke(main, args)
    assert again.exit_code == 1
    assert "a result of 'hysteresis fit', not of 'hysteresis gp-fit'" in again.output
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_predict_reproduces_fit_and_keeps_columns(
    magnet_csv: Path, tmp_path: Path
) -> None:
    out = tmp_path / "fit"
    assert _fit(magnet_csv, out, "--no-figures").exit_code == 0
    pred_csv = tmp_path / "pred.csv"
    args = ["hysteresis", "predict", str(out), "--input", str(magnet_csv)]
    result = CliRunner().invoke(main, [*args, "--out", str(pred_csv)])
    assert result.exit_code == 0, result.output
    with pred_csv.open() as f:
        rows = list(csv.reader(f))
    with magnet_csv.open() as f:
        original = list(csv.reader(f))
    added = ["prediction", "prediction_std", "outside_input_range"]
    assert rows[0] == [*original[0], *added]
    assert [r[:-3] for r in rows[1:]] == original[1:]
    model, band, _ = load_fit(out)
    current = torch.tensor([float(r[2]) for r in original[1:]], dtype=torch.float64)
    with torch.no_grad():
        expect = model(current)
        expect_std = band.std(model, current)
    got = torch.tensor([float(r[-3]) for r in rows[1:]], dtype=torch.float64)
    got_std = torch.tensor([float(r[-2]) for r in rows[1:]], dtype=torch.float64)
    lo, hi = model.input_range
    assert [r[-1] for r in rows[1:]] == [
        "1" if not lo <= c <= hi else "0" for c in current.tolist()
    ]
    # streamed in chunks vs one pass: float64 round-off of the state sums
    torch.testing.assert_close(got, expect, rtol=0, atol=1e-12)
    torch.testing.assert_close(got_std, expect_std, rtol=1e-5, atol=0)  # float32 sums
    assert (got_std > 0).all()
    # and predicted rmse on the held-out rows equals the summary's
    summary = json.loads((out / "summary.json").read_text())
    measured = torch.tensor([float(r[3]) for r in original[1:]], dtype=torch.float64)
    rmse = float((got[21:] - measured[21:]).pow(2).mean().sqrt())
    assert rmse == pytest.approx(summary["test_rmse"], rel=1e-9)
    refused = CliRunner().invoke(main, [*args, "--out", str(pred_csv)])
    assert refused.exit_code != 0 and "--force" in refused.output


def test_predict_refuses_input_with_prediction_column(
    magnet_csv: Path, tmp_path: Path
) -> None:
    out = tmp_path / "fit"
    assert _fit(magnet_csv, out, "--no-figures").exit_code == 0
    inputs = tmp_path / "inputs.csv"
    write_csv_atomic(inputs, ["I", "prediction"], [[0.0, 1.0], [5.0, 2.0]])
    args = ["hysteresis", "predict", str(out), "--input", str(inputs)]
    dest = tmp_path / "p.csv"
    refused = CliRunner().invoke(main, [*args, "--out", str(dest)])
    assert refused.exit_code != 0 and "already has column" in refused.output
    assert not dest.exists()
    forced = CliRunner().invoke(main, [*args, "--out", str(dest), "--force"])
    assert forced.exit_code == 0, forced.output
    header = dest.read_text().splitlines()[0]
    assert header == "I,prediction,prediction_std,outside_input_range"
    assert inputs.read_text().splitlines()[1] == "0.0,1.0"  # input untouched


def test_predict_beyond_range_is_flagged_widened_and_warned(
    magnet_csv: Path, tmp_path: Path
) -> None:
    # rows beyond the fitted range used to get only a note, and a std frozen
    # at the range's edge while the prediction moved on with the linear term
    out = tmp_path / "fit"
    assert _fit(magnet_csv, out, "--no-figures").exit_code == 0
    model, band, _ = load_fit(out)
    lo, hi = model.input_range
    inputs = tmp_path / "inputs.csv"
    write_csv_atomic(inputs, ["I"], [[0.0], [5.0], [hi], [12.0], [14.0]])
    pred_csv = tmp_path / "pred.csv"
    args = ["hysteresis", "predict", str(out), "--input", str(inputs)]
    result = CliRunner().invoke(main, [*args, "--out", str(pred_csv)])
    assert result.exit_code == 0, result.output
    warning = next(
        line for line in result.output.splitlines() if line.startswith("warning:")
    )
    assert "2 of 5 rows (the first: data row 4) have I outside" in warning
    assert f"input range [{lo:.6g}, {hi:.6g}] I, by up to {14.0 - hi:.4g} I" in warning
    assert "outside_input_range = 1 there" in warning
    rows = list(csv.reader(pred_csv.open()))[1:]
    y = [float(r[1]) for r in rows]
    std = [float(r[2]) for r in rows]
    assert [r[3] for r in rows] == ["0", "0", "0", "1", "1"]
    # saturated: beyond the range only the linear term changes the output
    slope = float((model.output_scale * model.slope).detach()) / (hi - lo)
    assert y[4] - y[3] == pytest.approx(2.0 * slope, rel=1e-9)
    # and the std widens there with the linear term's uncertainty
    assert std[2] < std[3] < std[4]
    # inside the range: the band of the history as it was
    u = torch.tensor([0.0, 5.0, hi], dtype=torch.float64)
    with torch.no_grad():
        inside = band.std(model, u)
    got_inside = torch.tensor(std[:3], dtype=torch.float64)
    torch.testing.assert_close(got_inside, inside, rtol=1e-5, atol=0)  # float32


def test_fit_bh_loop_beyond_training_range(tmp_path: Path) -> None:
    current, field, n_train, _ = bh_loop_case(seed=0)
    path = tmp_path / "bh.csv"
    write_csv_atomic(
        path,
        ["H", "B"],
        [[c, f] for c, f in zip(current.tolist(), field.tolist(), strict=True)],
    )
    out = tmp_path / "fit"
    args = ["hysteresis", "fit", str(path), "--train-rows", str(n_train)]
    args += ["--input", "H", "--output", "B", "--out", str(out), "--no-figures"]
    args += ["--initial-state", "demagnetized", "--mesh-size", "16", "--steps", "60"]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["symmetric"] is True
    assert summary["test_rmse"] < 0.5 * summary["straight_line_test_rmse"]


@pytest.mark.parametrize(
    ("extra", "match"),
    [
        (["--train-rows", "1000"], "exceeds"),
        (["--input", "nope"], "no input column"),
        (["--input-range", "0", "5"], "input_range"),
    ],
    ids=["too-many-rows", "missing-column", "range-misses-training-rows"],
)
def test_fit_bad_arguments(magnet_csv: Path, tmp_path: Path, extra, match) -> None:
    args = ["hysteresis", "fit", str(magnet_csv), "--train-rows", "21"]
    args += ["--input", "I", "--output", "B", "--out", str(tmp_path / "f"), *FAST]
    result = CliRunner().invoke(main, [*args, *extra])
    assert result.exit_code != 0
    assert match in result.output
    assert "Traceback" not in result.output


def test_predict_rejects_mismatched_model_files(
    magnet_csv: Path, tmp_path: Path
) -> None:
    out = tmp_path / "fit"
    assert _fit(magnet_csv, out, "--no-figures").exit_code == 0
    config = json.loads((out / "model.json").read_text())
    config["n_hysterons"] = 3
    (out / "model.json").write_text(json.dumps(config))
    args = ["hysteresis", "predict", str(out), "--input", str(magnet_csv)]
    result = CliRunner().invoke(main, [*args, "--out", str(tmp_path / "p.csv")])
    assert result.exit_code != 0 and "hysterons" in result.output
    assert len(result.output.strip().splitlines()) == 1


def test_read_ahead_keeps_order_and_raises_in_the_caller() -> None:
    from diffaccel.cli.hysteresis_predict import read_ahead

    assert list(read_ahead(iter(range(50)), depth=3)) == list(range(50))

    def broken():
        yield 1
        raise ValueError("bad row 2")

    got = []
    with pytest.raises(ValueError, match="bad row 2"):
        for item in read_ahead(broken()):
            got.append(item)
    assert got == [1]


def test_predict_runs_without_torch_and_reads_older_fit_folders(
    magnet_csv: Path, tmp_path: Path
) -> None:
    out = tmp_path / "fit"
    assert _fit(magnet_csv, out, "--no-figures").exit_code == 0
    new_csv, old_csv = tmp_path / "new.csv", tmp_path / "old.csv"
    code = (
        "import sys\n"
        "from diffaccel.cli.main import main\n"
        "try:\n"
        "    main(sys.argv[1:])\n"
        "except SystemExit as e:\n"
        "    assert not e.code, e.code\n"
        "print('RESULT', 'torch' in sys.modules, 'h5py' in sys.modules)\n"
    )
    args = ["hysteresis", "predict", str(out), "--input", str(magnet_csv)]
    run = subprocess.run(
        [sys.executable, "-c", code, *args, "--out", str(new_csv)],
        capture_output=True,
        text=True,
        check=True,
    )
    assert "RESULT False False" in run.stdout, run.stdout + run.stderr
    # a folder saved before stream.npz: the model is read with torch
    old = tmp_path / "old_fit"
    old.mkdir()
    for name in ("model.pt", "model.json"):
        (old / name).write_bytes((out / name).read_bytes())
    args = ["hysteresis", "predict", str(old), "--input", str(magnet_csv)]
    result = CliRunner().invoke(main, [*args, "--out", str(old_csv)])
    assert result.exit_code == 0, result.output
    assert old_csv.read_text() == new_csv.read_text()


@pytest.mark.parametrize(
    ("damage", "match"),
    [
        ("pt", "not the file"),
        ("npz", "cannot read arrays"),
        ("range", "input_range"),
    ],
)
def test_predict_refuses_a_stream_file_of_another_fit(
    magnet_csv: Path, tmp_path: Path, damage: str, match: str
) -> None:
    out = tmp_path / "fit"
    assert _fit(magnet_csv, out, "--no-figures").exit_code == 0
    if damage == "pt":  # model.pt of another fit, stream.npz of this one
        model, band, _ = load_fit(out)
        with torch.no_grad():
            model.slope.add_(1.0)
        keep = (out / "stream.npz").read_bytes()
        save_fit(out, model, band, overwrite=True)
        (out / "stream.npz").write_bytes(keep)
    elif damage == "npz":
        (out / "stream.npz").write_bytes(b"PK\x03\x04 not a zip")
    else:
        config = json.loads((out / "model.json").read_text())
        config["input_range"] = [0.0, 1.0]
        (out / "model.json").write_text(json.dumps(config))
    args = ["hysteresis", "predict", str(out), "--input", str(magnet_csv)]
    result = CliRunner().invoke(main, [*args, "--out", str(tmp_path / "p.csv")])
    assert result.exit_code != 0 and match in result.output, result.output
    assert len(result.output.strip().splitlines()) == 1
