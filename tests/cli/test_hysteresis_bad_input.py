"""Bad input to ``diffaccel hysteresis fit``, ``gp-fit`` and ``predict``: one true line.

Every case is refused before any fit runs, so these tests are fast.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from diffaccel.cli.main import main
from diffaccel.data.result_folder import MARKER
from diffaccel.hysteresis import LaplaceBand, PreisachMesh, PreisachModel, save_fit
from diffaccel.hysteresis.predictive import min_training_rows
from diffaccel.hysteresis.stream import StreamSpec


def _csv(path: Path, n: int = 30, big_row: int | None = None) -> Path:
    """A magnet CSV of ``n`` rows (current up and down); ``big_row``: 1e300 there."""
    lines = ["run,current_A,field_Tm"]
    for i in range(n):
        current = 10.0 * math.sin(0.3 * i) + 10.0
        if big_row is not None and i + 1 == big_row:
            current = 1e300
        lines.append(f"r{i},{current},{0.03 * current + 0.001 * i}")
    path.write_text("\n".join(lines) + "\n")
    return path


def _invoke(*args: str):
    return CliRunner().invoke(main, ["hysteresis", *args])


def _one_line_error(result, *needles: str) -> str:
    assert result.exit_code != 0, result.output
    assert "Traceback" not in result.output
    last = result.output.strip().splitlines()[-1]
    assert last.startswith("Error:"), result.output
    for needle in needles:
        assert needle in last, result.output
    return last


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "1e200", "-1"])
def test_fit_refuses_a_smoothness_that_is_not_a_finite_weight(
    tmp_path: Path, value: str
) -> None:
    data = _csv(tmp_path / "m.csv")
    out = tmp_path / "fit"
    result = _invoke(
        "fit", str(data), "--train-rows", "20", "--out", str(out), "--smoothness", value
    )
    _one_line_error(result, "--smoothness")
    assert not out.exists()


@pytest.mark.parametrize("command", ["fit", "gp-fit"])
@pytest.mark.parametrize(
    ("lo", "hi", "match"),
    [
        ("nan", "30", "finite"),
        ("0", "inf", "finite"),
        ("30", "0", "LO < HI"),
        ("5", "5", "LO < HI"),
        ("-1e308", "1e308", "overflows"),
    ],
)
def test_input_range_must_be_finite_and_increasing(
    tmp_path: Path, command: str, lo: str, hi: str, match: str
) -> None:
    data = _csv(tmp_path / "m.csv")
    if command == "fit":
        args = ["fit", str(data), "--train-rows", "20"]
    else:
        args = ["gp-fit", str(data), "--x", "current_A", "--y", "field_Tm"]
    result = _invoke(*args, "--out", str(tmp_path / "o"), "--input-range", lo, hi)
    _one_line_error(result, "--input-range", match)


@pytest.mark.parametrize(
    ("command", "args"),
    [
        ("fit", ["--train-rows", "20"]),
        ("gp-fit", ["--x", "current_A", "--y", "field_Tm"]),
    ],
)
def test_earlier_result_refusal_names_only_options_the_command_has(
    tmp_path: Path, command: str, args: list[str]
) -> None:
    data = _csv(tmp_path / "m.csv")
    out = tmp_path / "earlier"
    out.mkdir()
    (out / MARKER).write_text("{}\n")  # an earlier result folder
    result = _invoke(command, str(data), *args, "--out", str(out))
    _one_line_error(result, "--force")
    assert "--resume" not in result.output


def test_fit_names_train_rows_when_too_few(tmp_path: Path) -> None:
    data = _csv(tmp_path / "m.csv")
    result = _invoke(
        "fit", str(data), "--train-rows", "2", "--out", str(tmp_path / "o")
    )
    last = _one_line_error(result, "--train-rows", str(min_training_rows()))
    assert "fit_preisach" not in last


@pytest.mark.parametrize(("row", "train_rows"), [(6, "20"), (25, "20")])
def test_fit_huge_value_names_file_column_and_data_row(
    tmp_path: Path, row: int, train_rows: str
) -> None:
    data = _csv(tmp_path / "m.csv", big_row=row)
    out = tmp_path / "o"
    result = _invoke("fit", str(data), "--train-rows", train_rows, "--out", str(out))
    _one_line_error(result, str(data), "'current_A'", f"data row {row}:", "1e+300")
    assert not out.exists()


def test_min_training_rows_leaves_enough_rows_to_fit() -> None:
    assert min_training_rows() == 7
    assert min_training_rows(0.5) == 9
    with pytest.raises(ValueError, match="validation_fraction"):
        min_training_rows(1.0)


@pytest.mark.parametrize(("column", "option"), [("current_A", "--x"), ("y", "--y")])
def test_gp_fit_refuses_plain_column_that_is_x_or_y(
    tmp_path: Path, column: str, option: str
) -> None:
    data = tmp_path / "beam.csv"
    data.write_text(
        "current_A,energy,y\n" + "".join(f"{i % 7},{i},{i % 3}\n" for i in range(20))
    )
    out = tmp_path / "o"
    result = _invoke(
        "gp-fit", str(data), "--x", "current_A", "--y", "y", "--plain", column,
        "--out", str(out),
    )  # fmt: skip
    _one_line_error(result, "--plain", repr(column), option)
    assert not out.exists()


def test_gp_fit_refuses_a_seed_torch_cannot_take(tmp_path: Path) -> None:
    data = _csv(tmp_path / "m.csv")
    result = _invoke(
        "gp-fit", str(data), "--x", "current_A", "--y", "field_Tm",
        "--out", str(tmp_path / "o"), "--seed", str(10**30),
    )  # fmt: skip
    _one_line_error(result, "--seed")


def test_predict_onto_its_input_says_so_first(tmp_path: Path) -> None:
    data = _csv(tmp_path / "mine.csv")
    before = data.read_text()
    fit_dir = tmp_path / "fit"
    fit_dir.mkdir()
    for force in ([], ["--force"]):
        result = _invoke(
            "predict", str(fit_dir), "--input", str(data), "--out", str(data), *force
        )
        _one_line_error(result, "is the --input file")
        assert "pass --force" not in result.output
    assert data.read_text() == before


@pytest.mark.parametrize("name", ["o.npy", "o.h5", "o.csv.gz", "o"])
def test_predict_refuses_an_out_suffix_it_does_not_write(
    tmp_path: Path, name: str
) -> None:
    data = _csv(tmp_path / "mine.csv")
    fit_dir = tmp_path / "fit"
    fit_dir.mkdir()
    out = tmp_path / name
    result = _invoke("predict", str(fit_dir), "--input", str(data), "--out", str(out))
    _one_line_error(result, "--out", ".csv")
    assert not out.exists()


def test_predict_refuses_chunk_rows_beyond_its_limit(tmp_path: Path) -> None:
    data = _csv(tmp_path / "mine.csv")
    fit_dir = tmp_path / "fit"
    fit_dir.mkdir()
    result = _invoke(
        "predict", str(fit_dir), "--input", str(data), "--out",
        str(tmp_path / "p.csv"), "--chunk-rows", str(10**30),
    )  # fmt: skip
    _one_line_error(result, "--chunk-rows")


def _saved_fit(fit_dir: Path) -> None:
    model = PreisachModel(PreisachMesh.triangular(4), input_range=(0.0, 25.0))
    m = model.alpha.numel()
    band = LaplaceBand(torch.eye(2, m + 3, dtype=torch.float64), 0.01, 1.2)
    save_fit(fit_dir, model, band, extra={"input_column": "current_A"})


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("noise_std", -0.1, "noise_std must be >= 0"),
        ("noise_std", math.nan, "non-finite noise_std"),
        ("calibration", 0.5, "calibration must be >= 1"),
        ("output_scale", math.inf, "non-finite output_scale"),
    ],
)
def test_predict_checks_the_numbers_of_stream_npz(
    tmp_path: Path, field: str, value: float, match: str
) -> None:
    fit_dir = tmp_path / "fit"
    _saved_fit(fit_dir)
    data = _csv(tmp_path / "mine.csv")
    args = ["predict", str(fit_dir), "--input", str(data)]
    good = _invoke(*args, "--out", str(tmp_path / "good.csv"))
    assert good.exit_code == 0, good.output
    npz = fit_dir / "stream.npz"
    with np.load(npz) as f:
        arrays = dict(f)
    arrays[field] = np.array(value)
    with open(npz, "wb") as f:
        np.savez(f, **arrays)
    out = tmp_path / "p.csv"
    result = _invoke(*args, "--out", str(out))
    _one_line_error(result, str(npz), match)
    assert not out.exists()


def test_predict_checks_the_band_of_an_older_fit_folder(tmp_path: Path) -> None:
    fit_dir = tmp_path / "fit"
    _saved_fit(fit_dir)
    (fit_dir / "stream.npz").unlink()  # saved before stream.npz existed
    tensors = torch.load(fit_dir / "model.pt", weights_only=True)
    tensors["band.noise_std"] = torch.tensor(-0.1, dtype=torch.float64)
    torch.save(tensors, fit_dir / "model.pt")
    data = _csv(tmp_path / "mine.csv")
    result = _invoke(
        "predict", str(fit_dir), "--input", str(data), "--out", str(tmp_path / "p.csv")
    )
    _one_line_error(result, str(fit_dir / "model.pt"), "noise_std")


def test_stream_spec_names_the_bad_number() -> None:
    one = np.array([0.5])
    base = dict(
        input_range=(0.0, 1.0), alpha=one, beta=one / 2, weights=np.array([1.0]),
        initial=np.array([-1.0]), offset=0.0, slope=0.0, scale=1.0,
        output_loc=0.0, output_scale=1.0,
    )  # fmt: skip
    StreamSpec(**base)
    with pytest.raises(ValueError, match="non-finite slope"):
        StreamSpec(**{**base, "slope": math.nan})
    with pytest.raises(ValueError, match="weights must be >= 0"):
        StreamSpec(**{**base, "weights": np.array([-1.0])})
    with pytest.raises(ValueError, match="noise_std must be >= 0"):
        StreamSpec(**{**base, "noise_std": -1.0})


@pytest.mark.parametrize(
    ("column", "args"),
    [
        ("current_A", ["--x", "current_A", "--y", "y"]),
        ("y", ["--x", "current_A", "--y", "y"]),
        ("energy", ["--x", "current_A", "--y", "y", "--plain", "energy"]),
    ],
    ids=["x", "y", "plain"],
)
def test_gp_fit_huge_value_names_file_column_and_data_row(
    tmp_path: Path, column: str, args: list[str]
) -> None:
    # a field in T m times 1e160 used to fit to "noise sigma inf" and exit 0
    header = ["current_A", "energy", "y"]
    rows = [[float(i % 7), float(i), 0.1 * (i % 3)] for i in range(20)]
    rows[11][header.index(column)] = 1e160
    data = tmp_path / "beam.csv"
    data.write_text(
        ",".join(header) + "\n" + "".join(",".join(map(str, r)) + "\n" for r in rows)
    )
    out = tmp_path / "o"
    result = _invoke("gp-fit", str(data), *args, "--out", str(out))
    _one_line_error(result, str(data), repr(column), "data row 12:", "1e+160")
    assert not out.exists()


@pytest.mark.parametrize("row", [3, 25], ids=["first-chunk", "later-chunk"])
def test_predict_huge_input_names_file_column_and_data_row(
    tmp_path: Path, row: int
) -> None:
    # used to overflow in numpy (a RuntimeWarning) and then report NaN or
    # infinite inputs with no file or row
    fit_dir = tmp_path / "fit"
    _saved_fit(fit_dir)
    data = _csv(tmp_path / "mine.csv", big_row=row)
    out = tmp_path / "p.csv"
    result = _invoke(
        "predict", str(fit_dir), "--input", str(data), "--out", str(out),
        "--chunk-rows", "7",
    )  # fmt: skip
    last = _one_line_error(
        result, str(data), "'current_A'", f"data row {row}:", "1e+300"
    )
    assert "RuntimeWarning" not in result.output, last
    assert not out.exists()


def test_predict_creates_a_missing_out_folder(tmp_path: Path) -> None:
    # as fit and gp-fit do; it used to end in "unexpected FileNotFoundError"
    fit_dir = tmp_path / "fit"
    _saved_fit(fit_dir)
    data = _csv(tmp_path / "mine.csv")
    out = tmp_path / "new" / "deeper" / "p.csv"
    result = _invoke("predict", str(fit_dir), "--input", str(data), "--out", str(out))
    assert result.exit_code == 0, result.output
    lines = out.read_text().splitlines()
    assert lines[0] == (
        "run,current_A,field_Tm,prediction,prediction_std,outside_input_range"
    )
    assert len(lines) == 31


def test_predict_out_folder_that_is_a_file_is_one_line(tmp_path: Path) -> None:
    fit_dir = tmp_path / "fit"
    _saved_fit(fit_dir)
    data = _csv(tmp_path / "mine.csv")
    blocker = tmp_path / "blocker"
    blocker.write_text("not a folder\n")
    result = _invoke(
        "predict", str(fit_dir), "--input", str(data),
        "--out", str(blocker / "p.csv"),
    )  # fmt: skip
    _one_line_error(result, "--out", "cannot create its folder")


@pytest.mark.parametrize(("size", "memory"), [("101", "1.49 GB"), ("500", "879 GB")])
def test_fit_refuses_a_mesh_its_band_cannot_hold_up_front(
    tmp_path: Path, size: str, memory: str
) -> None:
    # 500 used to fit and then fail allocating 125 GB for the band, reported
    # as an "unexpected RuntimeError ... bug in diffaccel"
    data = _csv(tmp_path / "m.csv")
    out = tmp_path / "o"
    result = _invoke(
        "fit", str(data), "--train-rows", "20", "--out", str(out),
        "--mesh-size", size, "--steps", "1", "--no-figures",
    )  # fmt: skip
    _one_line_error(result, "--mesh-size", memory, "at most 100")
    assert not out.exists()


def test_cli_magnitude_limit_is_the_librarys() -> None:
    # kept as a copy so that 'hysteresis predict' streams without torch
    from diffaccel.cli.hysteresis import MAX_MAGNITUDE as cli_limit
    from diffaccel.hysteresis.fit import MAX_MAGNITUDE

    assert cli_limit == MAX_MAGNITUDE


def _timed_csv(
    path: Path,
    n: int = 30,
    swap: int | None = None,
    repeat: int | None = None,
    time: str = "time_s",
) -> Path:
    """:func:`_csv` with a time column that restarts with the second of two runs.

    ``swap``: data rows ``swap`` and ``swap + 1`` exchanged; ``repeat``: data
    row ``repeat`` written twice.
    """
    rows = []
    for i in range(n):
        current = 10.0 * math.sin(0.3 * i) + 10.0
        run, t = ("a", 2.5 * i) if i < n // 2 else ("b", 2.5 * (i - n // 2))
        rows.append(f"{run},{t},{current},{0.03 * current + 0.001 * i}")
    if swap is not None:
        rows[swap - 1], rows[swap] = rows[swap], rows[swap - 1]
    if repeat is not None:
        rows.insert(repeat, rows[repeat - 1])
    path.write_text(f"run,{time},current_A,field_Tm\n" + "\n".join(rows) + "\n")
    return path


def _order_args(command: str, data: Path, tmp_path: Path) -> tuple[list[str], Path]:
    """Arguments of ``command`` on ``data``, and what it writes."""
    out = tmp_path / "o"
    if command == "fit":
        return ["fit", str(data), "--train-rows", "20", "--out", str(out)], out
    if command == "gp-fit":
        return ["gp-fit", str(data), "--x", "current_A", "--y", "field_Tm",
                "--out", str(out)], out  # fmt: skip
    fit_dir = tmp_path / "fit"
    _saved_fit(fit_dir)
    out = tmp_path / "p.csv"
    return ["predict", str(fit_dir), "--input", str(data), "--out", str(out),
            "--chunk-rows", "7"], out  # fmt: skip


@pytest.mark.parametrize("command", ["fit", "gp-fit", "predict"])
@pytest.mark.parametrize(
    ("swap", "repeat", "needles"),
    [
        (20, None, ["'time_s', data row 21:", "'10.0' is not after '12.5' of data "
                    "row 20 (run 'b')", "measurement order"]),
        (None, 20, ["data row 21 repeats data row 20 in every cell", "'time_s'"]),
    ],
    ids=["shuffled", "repeated"],
)  # fmt: skip
def test_rows_out_of_measurement_order_are_refused(
    tmp_path: Path, command: str, swap: int | None, repeat: int | None, needles
) -> None:
    # hysteresis depends on the order of the inputs: shuffled or repeated rows
    # used to be fitted (and predicted) as if they were a history
    data = _timed_csv(tmp_path / "m.csv", swap=swap, repeat=repeat)
    args, out = _order_args(command, data, tmp_path)
    _one_line_error(_invoke(*args), str(data), *needles)
    assert not out.exists()


def test_predict_accepts_a_time_that_restarts_with_each_run(tmp_path: Path) -> None:
    data = _timed_csv(tmp_path / "m.csv")
    args, out = _order_args("predict", data, tmp_path)
    result = _invoke(*args)
    assert result.exit_code == 0, result.output
    assert len(out.read_text().splitlines()) == 31


@pytest.mark.parametrize("command", ["fit", "gp-fit", "predict"])
def test_time_column_option_names_the_column_to_check(
    tmp_path: Path, command: str
) -> None:
    data = _timed_csv(tmp_path / "m.csv", swap=5, time="step")
    args, out = _order_args(command, data, tmp_path)
    _one_line_error(
        _invoke(*args, "--time-column", "step"), str(data), "'step', data row 6:"
    )
    _one_line_error(
        _invoke(*args, "--time-column", "t_s"),
        "--time-column",
        f"{data} has no column 't_s'",
    )
    assert not out.exists()
