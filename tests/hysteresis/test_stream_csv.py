"""Streaming prediction of a magnet CSV, chunk by chunk."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest

from diffaccel.data import OptionError, iter_magnet_csv
from diffaccel.data.owned_files import OutputFileError
from diffaccel.hysteresis import (
    InputRangeWarning,
    StreamPredictor,
    StreamSpec,
    save_fit,
)
from diffaccel.hysteresis.stream_csv import (
    COLUMNS,
    OUTSIDE,
    StreamStats,
    check_csv_output,
    outside_warning,
    predict_csv,
    read_ahead,
    stream_fit,
    write_predictions,
)
from diffaccel.hysteresis.synthetic import synthetic_magnet

#: one hysteron switching at 0.5 up and 0.25 down, in the range [0, 1]
SPEC = StreamSpec(
    (0.0, 1.0),
    np.array([0.5]),
    np.array([0.25]),
    np.array([1.0]),
    np.array([-1.0]),
    0.0,
    0.0,
    1.0,
    0.0,
    1.0,
)


def _csv(path: Path, inputs: list[float], extra: str = "") -> Path:
    head = "current_A,note" + extra
    rows = [f"{x},r{i}" + ("," if extra else "") for i, x in enumerate(inputs)]
    path.write_text("\n".join([head, *rows]) + "\n")
    return path


def test_write_predictions_equals_one_pass_over_the_history(tmp_path: Path) -> None:
    inputs = [0.1, 0.6, 0.4, 0.2, 0.7, 1.5, 0.3]
    src = _csv(tmp_path / "in.csv", inputs, extra=",prediction")
    header, chunks = iter_magnet_csv(src, "current_A", chunk_rows=2, drop=COLUMNS)
    seen = []
    stats = write_predictions(
        tmp_path / "out.csv",
        SPEC,
        header,
        chunks,
        check=lambda x, first: seen.append((len(x), first)),
    )
    assert seen == [(2, 1), (2, 3), (2, 5), (1, 7)]  # data rows of each chunk
    with (tmp_path / "out.csv").open() as f:
        rows = list(csv.reader(f))
    assert rows[0] == ["current_A", "note", *COLUMNS]  # the old column replaced
    with pytest.warns(InputRangeWarning):  # the row beyond the range
        expect, _ = StreamPredictor(SPEC)(np.array(inputs))
    got = np.array([float(r[2]) for r in rows[1:]])
    np.testing.assert_allclose(got, expect, rtol=1e-14)
    assert [r[1] for r in rows[1:]] == [f"r{i}" for i in range(len(inputs))]
    assert [r[4] for r in rows[1:]] == ["0"] * 5 + ["1", "0"]
    assert (stats.rows, stats.outside_rows, stats.outside_first) == (7, 1, 6)
    assert (stats.min, stats.max, stats.finite) == (0.1, 1.5, True)


def test_check_refuses_a_chunk_before_it_is_written(tmp_path: Path) -> None:
    src = _csv(tmp_path / "in.csv", [0.1, 0.2, 0.3])
    header, chunks = iter_magnet_csv(src, "current_A", chunk_rows=1, drop=COLUMNS)

    def check(x: np.ndarray, first_row: int) -> None:
        if first_row == 3:
            raise ValueError("row 3 is bad")

    with pytest.raises(ValueError, match="row 3 is bad"):
        write_predictions(tmp_path / "o.csv", SPEC, header, chunks, check=check)


def test_outside_warning_names_count_first_row_and_distance() -> None:
    assert outside_warning(StreamStats(rows=5), (0.0, 1.0), "I") is None
    stats = StreamStats(rows=7, min=-0.5, max=1.2, outside_rows=2, outside_first=3)
    text = outside_warning(stats, (0.0, 1.0), "I")
    assert text is not None
    assert text.startswith("2 of 7 rows (the first: data row 3) have I outside")
    assert "by up to 0.5 I (50 % of the range)" in text and f"{OUTSIDE} = 1" in text


def test_read_ahead_keeps_order_and_raises_in_the_caller() -> None:
    assert list(read_ahead(iter(range(30)), depth=2)) == list(range(30))

    def broken():
        yield 1
        raise RuntimeError("third")

    it = read_ahead(broken())
    assert next(it) == 1
    with pytest.raises(RuntimeError, match="third"):
        next(it)


def test_stream_fit_reads_a_saved_fit_with_and_without_its_stream_file(
    tmp_path: Path,
) -> None:
    model = synthetic_magnet()
    save_fit(tmp_path, model, extra={"input_column": "I"})
    spec, config = stream_fit(tmp_path)
    assert config["input_column"] == "I"
    (tmp_path / "stream.npz").unlink()  # an older folder: read with torch
    old, _ = stream_fit(tmp_path)
    x = np.linspace(*model.input_range, 9)
    a, _ = StreamPredictor(spec)(x)
    b, _ = StreamPredictor(old)(x)
    np.testing.assert_allclose(a, b, rtol=1e-12)
    assert math.isfinite(float(a.sum()))


def test_check_csv_output_refuses_the_input_other_names_and_existing_files(
    tmp_path: Path,
) -> None:
    src = _csv(tmp_path / "in.csv", [0.1])
    check_csv_output(tmp_path / "new" / "out.csv", src, force=False)
    with pytest.raises(OutputFileError, match="is the --input file"):
        check_csv_output(src, src, force=True)
    with pytest.raises(OutputFileError, match=r"expected a \.csv file name"):
        check_csv_output(tmp_path / "out.txt", src, force=False)
    other = _csv(tmp_path / "other.csv", [0.2])
    for force in (False, True):  # not diffaccel's: refused, --force or not
        with pytest.raises(OutputFileError, match="not written by diffaccel"):
            check_csv_output(other, src, force=force)


def test_predict_csv_writes_every_row_and_refuses_its_own_columns(
    tmp_path: Path,
) -> None:
    config = {"input_column": "current_A"}
    src = _csv(tmp_path / "in.csv", [0.1, 0.6, 0.4])
    out = tmp_path / "made" / "out.csv"
    stats = predict_csv(SPEC, config, src, out, chunk_rows=2)
    assert stats.rows == 3 and stats.finite
    with out.open() as f:
        rows = list(csv.reader(f))
    assert rows[0] == ["current_A", "note", *COLUMNS] and len(rows) == 4
    check_csv_output(out, src, force=True)  # its own output: --force replaces it
    with pytest.raises(OutputFileError, match="pass --force"):
        check_csv_output(out, src, force=False)
    clash = _csv(tmp_path / "clash.csv", [0.1], extra=",prediction")
    with pytest.raises(ValueError, match=r"already has column\(s\) \['prediction'\]"):
        predict_csv(SPEC, config, clash, tmp_path / "o.csv")
    assert predict_csv(SPEC, config, clash, tmp_path / "o.csv", force=True).rows == 1
    with pytest.raises(OptionError, match="no column 't'"):
        predict_csv(SPEC, config, src, tmp_path / "p.csv", time_column="t")
    big = _csv(tmp_path / "big.csv", [0.1, 1e101])
    with pytest.raises(ValueError, match="data row 2: 1e\\+101 is beyond"):
        predict_csv(SPEC, config, big, tmp_path / "q.csv")
    assert not (tmp_path / "q.csv").exists()
