"""Magnet-history CSV reader and atomic CSV writer."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from diffaccel.data import FormatError, read_magnet_csv, write_csv_atomic
from diffaccel.data.magnet_stream import (
    check_finite,
    check_input_range,
    check_magnitude,
    check_time_column,
)

SLAC = (
    Path(__file__).resolve().parents[2]
    / "data"
    / "hysteresis"
    / "slac_lcls2_quad_4194"
    / "measurements.csv"
)


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "m.csv"
    p.write_text(text)
    return p


def test_reads_default_and_named_columns(tmp_path: Path) -> None:
    p = _write(tmp_path, "run,current_A,field_Tm,amps\na,0,0.03,1\nb,10.5,0.35,2\n")
    h = read_magnet_csv(p)
    assert h.input.dtype == torch.float64
    assert h.input.tolist() == [0.0, 10.5] and h.output.tolist() == [0.03, 0.35]
    assert h.header == ["run", "current_A", "field_Tm", "amps"]
    assert h.rows[1] == ["b", "10.5", "0.35", "2"]
    h2 = read_magnet_csv(p, input_column="amps", require_output=False)
    assert h2.input.tolist() == [1.0, 2.0]


def test_missing_output_allowed_when_not_required(tmp_path: Path) -> None:
    p = _write(tmp_path, "current_A\n1\n2\n")
    assert read_magnet_csv(p, require_output=False).output is None
    with pytest.raises(FormatError, match="no output column 'field_Tm'"):
        read_magnet_csv(p)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("", "empty file"),
        ("current_A,field_Tm\n", "header only"),
        ("current_A,field_Tm\n1,2\n3\n", "row 2 has 1 cells"),
        ("I,field_Tm\n1,2\n", "no input column 'current_A'"),
        ("current_A,field_Tm\n1,2\nx,3\n", "row 2: expected a number; found 'x'"),
        ("current_A,field_Tm\n1,nan\n", "expected a finite number"),
        ("current_A,field_Tm\n1,inf\n", "expected a finite number"),
    ],
    ids=["empty", "header-only", "ragged", "no-input", "text", "nan", "inf"],
)
def test_bad_files_raise(tmp_path: Path, text: str, match: str) -> None:
    with pytest.raises(FormatError, match=match):
        read_magnet_csv(_write(tmp_path, text))


def test_write_is_atomic_and_refuses_overwrite(tmp_path: Path) -> None:
    p = tmp_path / "out.csv"
    write_csv_atomic(p, ["a", "b"], [[1.5, "x"], [0.1, "y"]])
    assert p.read_text() == "a,b\n1.5,x\n0.1,y\n"
    with pytest.raises(FileExistsError, match="overwrite"):
        write_csv_atomic(p, ["a"], [[1]])
    write_csv_atomic(p, ["a"], [[1]], overwrite=True)
    assert p.read_text() == "a\n1\n"
    assert sorted(x.name for x in tmp_path.iterdir()) == ["out.csv"]
    with pytest.raises(ValueError, match="row 0 has 2 cells"):
        write_csv_atomic(tmp_path / "bad.csv", ["a"], [[1, 2]])


def test_float_round_trip(tmp_path: Path) -> None:
    x = [0.1 + 1e-17, 1 / 3, 165.0386175]
    p = write_csv_atomic(tmp_path / "x.csv", ["current_A"], [[v] for v in x])
    assert read_magnet_csv(p, require_output=False).input.tolist() == x


def test_reads_slac_measurements() -> None:
    h = read_magnet_csv(SLAC)
    assert len(h) == 187
    assert h.header[:3] == ["run", "time_s", "current_A"]
    assert 164 < float(h.input.max()) < 166


def test_utf8_bom_is_accepted(tmp_path: Path) -> None:
    p = tmp_path / "bom.csv"
    p.write_bytes("current_A,field_Tm\n1,2\n".encode("utf-8-sig"))
    h = read_magnet_csv(p)
    assert h.header == ["current_A", "field_Tm"] and h.input.tolist() == [1.0]


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("current_A,field_Tm,current_A\n1,2,3\n", "appears more than once"),
        (
            "current_A,field_Tm\n1," + "9" * 5000 + "\n",
            "a cell longer than 1000 characters",
        ),
    ],
    ids=["duplicate-column", "long-cell"],
)
def test_bad_headers_and_cells(tmp_path: Path, text: str, match: str) -> None:
    with pytest.raises(FormatError, match=match):
        read_magnet_csv(_write(tmp_path, text))


def test_stream_reader_chunks_and_checks(tmp_path: Path) -> None:
    from diffaccel.data import iter_magnet_csv

    p = _write(tmp_path, "current_A\n" + "".join(f"{i}\n" for i in range(10)))
    header, chunks = iter_magnet_csv(p, "current_A", chunk_rows=4)
    got = [(len(rows), x) for rows, x in chunks]
    assert header == ["current_A"]
    assert all(1 <= n <= 4 for n, _ in got) and len(got) == 3
    assert np.concatenate([x for _, x in got]).tolist() == [float(i) for i in range(10)]
    bad = _write(tmp_path, "current_A\n1\n2\nx\n")
    with pytest.raises(FormatError, match="row 3: expected a number"):
        list(iter_magnet_csv(bad, "current_A", chunk_rows=2)[1])
    only = _write(tmp_path, "current_A\n")
    with pytest.raises(FormatError, match="header only"):
        list(iter_magnet_csv(only, "current_A")[1])


@pytest.mark.parametrize(
    "body",
    [
        "".join(f"{i},{0.5 * i},r{i}\n" for i in range(9)),
        "0,1,a\n\n1,2,b\n 2 , 3 ,c\n3,4,d",  # blank line, spaces, no final newline
        "0,1,a\r\n1,2,b\r\n2,3,c\r\n",  # CRLF
        '0,1,a\n1,2,b\n2,3,"c, quoted"\n3,4,"multi\nline"\n4,5,e\n',
    ],
    ids=["plain", "blank-spaces", "crlf", "quoted-late"],
)
@pytest.mark.parametrize("chunk", [1, 2, 100])
def test_stream_reader_rows_equal_the_csv_module(
    tmp_path: Path, body: str, chunk: int
) -> None:
    import csv

    from diffaccel.data import iter_magnet_csv

    p = tmp_path / "m.csv"
    p.write_bytes(("t,current_A,label\n" + body).encode())
    whole = read_magnet_csv(p, "current_A", require_output=False)
    header, chunks = iter_magnet_csv(p, "current_A", chunk_rows=chunk)
    parts = list(chunks)
    texts = [t for rows, _ in parts for t in rows]
    assert header == whole.header
    assert np.concatenate([x for _, x in parts]).tolist() == whole.input.tolist()
    # the row texts are CSV records holding the original cells
    assert list(csv.reader(texts)) == whole.rows
    # dropped columns leave the texts, not the header
    header, chunks = iter_magnet_csv(p, "current_A", chunk_rows=chunk, drop=["t"])
    kept = [t for rows, _ in chunks for t in rows]
    assert list(csv.reader(kept)) == [r[1:] for r in whole.rows]


@pytest.mark.parametrize(
    ("body", "match"),
    [
        ("1\n2\n3,4\n", "data row 3 has 2 cells"),
        ("1\n2\nnan\n", "data row 3: expected a finite number"),
        ("1\n\n2\nx\n", "data row 3: expected a number; found 'x'"),
        ("1\n" + "9" * 2000 + "\n", "a cell longer than 1000 characters"),
    ],
    ids=["ragged", "nan", "text-after-blank", "long-cell"],
)
def test_stream_reader_errors_in_plain_chunks(
    tmp_path: Path, body: str, match: str
) -> None:
    from diffaccel.data import iter_magnet_csv

    p = _write(tmp_path, "current_A\n" + body)
    with pytest.raises(FormatError, match=match):
        list(iter_magnet_csv(p, "current_A", chunk_rows=2)[1])


def test_append_columns_formats_in_bulk_like_format() -> None:
    from diffaccel.data import append_columns

    gen = torch.Generator().manual_seed(0)
    x = torch.randn(2000, generator=gen, dtype=torch.float64)
    x = x * torch.exp(10.0 * torch.randn(2000, generator=gen, dtype=torch.float64))
    x[:4] = torch.tensor([0.0, -0.0, 9.99999999999999999e2, -1e-99])
    s = torch.rand(2000, generator=gen, dtype=torch.float64)
    rows = [f'r{i},"q, {i}"' for i in range(2000)]
    text = append_columns(rows, [x, s], [15, 7])
    lines = text.split("\n")
    assert lines[-1] == "" and len(lines) == 2001
    cells = [line.rsplit(",", 2) for line in lines[:-1]]
    assert [c[0] for c in cells] == rows
    got_x = torch.tensor([float(c[1]) for c in cells], dtype=torch.float64)
    got_s = torch.tensor([float(c[2]) for c in cells], dtype=torch.float64)
    # 15 significant digits: within one unit of the last one (1e-14 relative)
    assert ((got_x - x).abs() <= 1e-14 * x.abs()).all()
    assert ((got_s - s).abs() <= 1e-6 * s).all()  # 7 digits
    # the same text as Python's format where that rounds the same way
    same = [c[1] == f"{v:.14e}" for c, v in zip(cells, x.tolist(), strict=True)]
    assert sum(same) > 0.9 * len(same)
    assert cells[0][1] == "0.00000000000000e+00" and cells[2][1].startswith("1.0")
    assert [c[2] for c in cells[:3]] == [f"{v:.6e}" for v in s[:3].tolist()]


def test_append_columns_falls_back_for_nonfinite_and_huge() -> None:
    from diffaccel.data import append_columns

    x = torch.tensor([1.0, float("nan"), -float("inf"), 1e200], dtype=torch.float64)
    text = append_columns(["a", "b", "c", "d"], [x], [3])
    assert text == "a,1.00e+00\nb,nan\nc,-inf\nd,1.00e+200\n"
    assert append_columns([], [x[:0]], [3]) == ""
    # blocks all negative, all positive, mixed
    neg, pos, mix = (torch.tensor(v) for v in ([-1.5, -2.0], [3.0, 4.0], [5.0, -6.0]))
    text = append_columns(["a", "b"], [neg, pos, mix], [2, 2, 2])
    assert text == "a,-1.5e+00,3.0e+00,5.0e+00\nb,-2.0e+00,4.0e+00,-6.0e+00\n"


# ------------------------------------------------------ measurement order

_TIMED = "run,time_s,current_A,field_Tm\n"


@pytest.mark.parametrize(
    ("body", "match"),
    [
        (
            "a,0,1,2\na,1,5,3\na,0.5,2,4\n",
            r"m\.csv: column 'time_s', data row 3: '0\.5' is not after '1' of data "
            r"row 2 \(run 'a'\); rows must be in measurement order",
        ),
        (
            "a,0,1,2\na,1,5,3\na,1,2,4\n",
            r"column 'time_s', data row 3: '1' is not after '1' of data row 2",
        ),
        (
            "a,0,1,2\na,1,5,3\na,1,5,3\na,2,1,2\n",
            r"m\.csv: data row 3 repeats data row 2 in every cell \(column 'time_s' "
            r"= '1'\): a row exported twice\?",
        ),
    ],
    ids=["decreasing", "equal-time", "repeated-row"],
)
def test_time_must_increase_within_a_run(tmp_path: Path, body: str, match: str) -> None:
    from diffaccel.data import iter_magnet_csv

    p = _write(tmp_path, _TIMED + body)
    with pytest.raises(FormatError, match=match):
        read_magnet_csv(p)
    for chunk in (1, 2, 100):  # within a chunk and across chunks
        with pytest.raises(FormatError, match=match):
            list(iter_magnet_csv(p, "current_A", chunk_rows=chunk)[1])
    # the csv module's path (a quoted cell) says the same
    quoted = _write(tmp_path, _TIMED + '"a",' + body[2:])
    with pytest.raises(FormatError, match=match):
        list(iter_magnet_csv(quoted, "current_A", chunk_rows=2)[1])


def test_time_may_restart_where_the_run_changes(tmp_path: Path) -> None:
    from diffaccel.data import iter_magnet_csv

    # the SLAC files restart time_s at 0 in each run
    body = "a,0,1,2\na,1,5,3\nb,0,5,3\nb,2.5,1,2\nc,0,1,2\n"
    p = _write(tmp_path, _TIMED + body)
    assert read_magnet_csv(p).input.tolist() == [1.0, 5.0, 5.0, 1.0, 1.0]
    for chunk in (1, 2, 100):
        chunks = iter_magnet_csv(p, "current_A", chunk_rows=chunk)[1]
        assert sum(len(rows) for rows, _ in chunks) == 5
    # without a run column a restart is a time going back: refused, with a hint
    p = _write(tmp_path, "time_s,current_A,field_Tm\n0,1,2\n1,5,3\n0,5,3\n")
    with pytest.raises(FormatError, match=r"data row 3: '0' is not after '1'.*'run'"):
        read_magnet_csv(p)


def test_time_column_cells_must_be_numbers(tmp_path: Path) -> None:
    from diffaccel.data import iter_magnet_csv

    p = _write(tmp_path, _TIMED + "a,0,1,2\na,later,5,3\n")
    match = r"column 'time_s', data row 2: expected a number; found 'later'"
    with pytest.raises(FormatError, match=match):
        read_magnet_csv(p)
    with pytest.raises(FormatError, match=match):
        list(iter_magnet_csv(p, "current_A", chunk_rows=1)[1])


def test_order_is_not_checked_without_a_time_column(tmp_path: Path) -> None:
    from diffaccel.data import iter_magnet_csv

    # repeated currents (a current held) are valid hysteresis data, and
    # without a time column order cannot be told from the rows themselves
    body = "r1,5,3\nr1,5,3\nr2,0,1\n"
    p = _write(tmp_path, "run,current_A,field_Tm\n" + body)
    assert read_magnet_csv(p).input.tolist() == [5.0, 5.0, 0.0]
    assert len(list(iter_magnet_csv(p, "current_A")[1])) == 1
    # another time column by name; or none
    p = _write(tmp_path, "t,current_A,field_Tm\n1,5,3\n0,5,3\n")
    with pytest.raises(FormatError, match="column 't', data row 2"):
        read_magnet_csv(p, time_column="t")
    with pytest.raises(FormatError, match="column 't', data row 2"):
        list(iter_magnet_csv(p, "current_A", time_column="t")[1])
    p = _write(tmp_path, _TIMED + "a,1,5,3\na,0,5,3\n")
    assert len(read_magnet_csv(p, time_column=None)) == 2
    assert len(list(iter_magnet_csv(p, "current_A", time_column=None)[1])) == 1


def test_append_columns_writes_boolean_flags_as_0_and_1() -> None:
    from diffaccel.data import append_columns

    x = np.array([1.5, -2.0, 3.0])
    flag = np.array([False, True, False])
    text = append_columns(["a", "b", "c"], [x, flag, -x], [2, 1, 2])
    assert text == "a,1.5e+00,0,-1.5e+00\nb,-2.0e+00,1,2.0e+00\nc,3.0e+00,0,-3.0e+00\n"
    # the fallback of a non-finite chunk writes the same flags
    x[1] = np.nan
    text = append_columns(["a", "b", "c"], [x, flag], [2, 1])
    assert text == "a,1.5e+00,0\nb,nan,1\nc,3.0e+00,0\n"


@pytest.mark.parametrize(
    ("cell", "hint"),
    [
        ("1_000", "digit separators"),
        ("0x10", "hexadecimal"),
        ("1,5", "decimal comma"),
    ],
)
def test_numbers_are_read_strictly(tmp_path, cell, hint):
    """Python's float() reads '1_000' as 1000; a magnet file must not."""
    from diffaccel.data import iter_magnet_csv

    path = tmp_path / "m.csv"
    quoted = f'"{cell}"' if "," in cell else cell
    path.write_text(f"current_A,field_Tm\n1.0,0.1\n{quoted},0.2\n")
    with pytest.raises(FormatError, match=f"data row 2.*{hint}"):
        read_magnet_csv(path)
    _, chunks = iter_magnet_csv(path, "current_A")
    with pytest.raises(FormatError, match=f"data row 2.*{hint}"):
        list(chunks)


def test_a_semicolon_file_is_named_as_such(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text("current_A;field_Tm\n1,0;0,1\n2,0;0,2\n")
    with pytest.raises(FormatError, match="';' or tabs"):
        read_magnet_csv(path)


def test_plain_decimals_and_exponents_still_read(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text("current_A,field_Tm\n-1.5e2,0.1\n+.5,2E-3\n 7 ,1.\n")
    h = read_magnet_csv(path)
    assert h.input.tolist() == [-150.0, 0.5, 7.0]


def test_magnitude_and_time_column_checks_name_file_column_and_row() -> None:
    check_magnitude("m.csv", "current_A", np.array([1.0, -1e100]))
    with pytest.raises(FormatError, match=r"m.csv: column 'x', data row 12: -2e\+100"):
        check_magnitude("m.csv", "x", np.array([0.0, -2e100]), first_row=11)
    check_time_column("m.csv", ["a", "t"], None)
    check_time_column("m.csv", ["a", "t"], "t")
    with pytest.raises(ValueError, match=r"m.csv has no column 's'; columns are") as e:
        check_time_column("m.csv", ["a", "t"], "s")
    assert e.value.option == "--time-column"


def test_finite_numbers_and_input_ranges_are_checked() -> None:
    assert check_finite(None) is None and check_finite(-2.5) == -2.5
    with pytest.raises(ValueError, match="expected a finite number; got nan"):
        check_finite(float("nan"))
    assert check_input_range(None) is None
    assert check_input_range((-1.0, 2.0)) == (-1.0, 2.0)
    for bad, msg in (
        ((0.0, float("inf")), "expected finite numbers"),
        ((2.0, 2.0), "expected LO < HI; got 2.0 2.0"),
        ((-1e308, 1e308), "HI - LO overflows"),
    ):
        with pytest.raises(ValueError, match=msg):
            check_input_range(bad)
