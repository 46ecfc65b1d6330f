"""Long magnet CSV files in chunks of rows: read, and written back with columns.

:func:`iter_magnet_csv` reads a time-ordered magnet CSV (see
:mod:`~diffaccel.data.magnet_csv`) a chunk of rows at a time, keeping each row's
text; :func:`append_columns` writes rows back with float columns appended,
formatted in bulk. numpy only (no torch), so that a command streaming a long
file (``diffaccel hysteresis predict``) starts fast.

Measurement order: hysteresis depends on the order of the inputs, so rows must
be in the order they were measured. Where a file has a time column
(``time_s`` by default, any increasing unit), its values must increase from
row to row within a run (consecutive rows with the same ``run`` label, or the
whole file without a ``run`` column); the time may restart where the label
changes, as it does in the SLAC files. A non-increasing time is refused,
naming the file, the column and the first offending data row, and a row equal
to the one before it in every cell is named as a row exported twice. Without a
time column nothing is checked: shuffled rows cannot be told from valid ones
(repeated currents, even identical rows, occur in valid histories; applying the
same input again switches no hysteron), and the order of runs is not checked.
"""

from __future__ import annotations

import csv
import io
import itertools
import math
import operator
import os
import re
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np

from diffaccel.data.errors import FormatError, OptionError

__all__ = [
    "DEFAULT_INPUT_COLUMN",
    "DEFAULT_OUTPUT_COLUMN",
    "DEFAULT_RUN_COLUMN",
    "DEFAULT_TIME_COLUMN",
    "MAX_CELL_CHARS",
    "MAX_MAGNITUDE",
    "append_columns",
    "check_finite",
    "check_input_range",
    "check_magnitude",
    "check_time_column",
    "iter_magnet_csv",
]

DEFAULT_INPUT_COLUMN = "current_A"
DEFAULT_OUTPUT_COLUMN = "field_Tm"
#: Time of each measurement [s, or any unit that increases], checked when present
DEFAULT_TIME_COLUMN = "time_s"
#: Label of the run (one measurement sequence) of each row; time restarts per run
DEFAULT_RUN_COLUMN = "run"
# longest accepted cell (a number, a label); longer ones are not magnet data
MAX_CELL_CHARS = 1000
#: Largest |value| of a measured series (fit, H-GP and the CLI readers): larger
#: magnitudes overflow squares and ranges in float64; no measurement has them.
MAX_MAGNITUDE = 1e100


def check_magnitude(
    data: str | os.PathLike, column: str, values: np.ndarray, first_row: int = 1
) -> None:
    """Refuse a value beyond :data:`MAX_MAGNITUDE`, naming the file, column and row.

    Args:
        data: The CSV file the values come from.
        column: Their column name.
        values: The column's values (a numpy array or a CPU tensor), shape ``(T,)``.
        first_row: Data row (1 = the first row below the header) of ``values[0]``.

    Raises:
        FormatError: at the first value beyond :data:`MAX_MAGNITUDE`.
    """
    v = np.asarray(values, dtype=np.float64)
    big = np.flatnonzero(np.abs(v) > MAX_MAGNITUDE)
    if big.size:
        i = int(big[0])
        raise FormatError(
            f"{data}: column {column!r}, data row {first_row + i}: "
            f"{float(v[i]):.6g} is beyond {MAX_MAGNITUDE:.0e} in magnitude, "
            "not a measurement (a unit or parsing error?)."
        )


def check_finite(value: float | None) -> float | None:
    """``value`` unless it is NaN or infinite (None passes).

    Raises:
        ValueError: ``expected a finite number; got VALUE.``
    """
    if value is not None and not math.isfinite(value):
        raise ValueError(f"expected a finite number; got {value}.")
    return value


def check_input_range(
    value: tuple[float, float] | None,
) -> tuple[float, float] | None:
    """An input range ``(LO, HI)`` of finite numbers with ``LO < HI`` (None passes).

    Raises:
        ValueError: naming the numbers: not finite, not increasing, or a width
            that overflows.
    """
    if value is None:
        return None
    lo, hi = value
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError(f"expected finite numbers; got {lo} {hi}.")
    if not lo < hi:
        raise ValueError(f"expected LO < HI; got {lo} {hi}.")
    if not math.isfinite(hi - lo):
        raise ValueError(
            f"HI - LO overflows (got {lo} {hi}); expected a range of finite width."
        )
    return value


def check_time_column(
    data: str | os.PathLike, header: Sequence[str], name: str | None
) -> None:
    """Refuse a time column ``name`` that the header of ``data`` lacks.

    None (the default column, which may be absent) passes.

    Raises:
        OptionError: for ``--time-column``, naming the file and its columns.
    """
    if name is not None and name not in header:
        raise OptionError(
            f"{data} has no column {name!r}; columns are {list(header)}.",
            "--time-column",
        )


def _parse_column(
    rows: list[list[str]], col: int, name: str, path: str, first: int = 0
) -> np.ndarray:
    """Column ``col`` of ``rows`` as finite float64 numbers, or a clear error."""
    cells = [row[col] if col < len(row) else "<missing>" for row in rows]
    return _parse_cells(cells, name, path, first)


_DECIMAL_COMMA = re.compile(r"\s*[+-]?\d+,\d+\s*")


def separator_hint(header: Sequence[str]) -> str:
    """A hint for a header read as one column that holds ``;`` or tabs."""
    if len(header) == 1 and (";" in header[0] or "\t" in header[0]):
        return (
            " (the header is one column: the file seems to separate cells with "
            "';' or tabs; diffaccel reads ',' with a decimal point)"
        )
    return ""


def _number_hint(cell: str) -> str:
    """Why ``cell`` is not a plain decimal number, for the error message."""
    if "_" in cell:
        return " (digit separators such as '_' are not read; write 1000, not 1_000)"
    if cell.strip().lower().startswith(("0x", "-0x", "+0x")):
        return " (hexadecimal is not read; write the decimal value)"
    if _DECIMAL_COMMA.fullmatch(cell) or ";" in cell:
        return (
            " (this looks like a decimal comma or a ';'-separated file: write "
            "numbers with a decimal point, cells separated by ',')"
        )
    return ""


def _parse_cells(cells: list[str], name: str, path: str, first: int = 0) -> np.ndarray:
    """Cells of column ``name`` (data rows ``first + 1 ...``) as finite float64.

    Only plain decimal numbers are read (Python's ``float`` would also take
    ``1_000`` and ``infinity``): a cell that is not one is named with its row.
    """
    try:
        values = np.array(list(map(float, cells)), dtype=np.float64)
    except ValueError:
        values = None
    if values is not None:
        bad = ~np.isfinite(values)
        if not bad.any():
            strange = [i for i, c in enumerate(cells) if "_" in c]
            if not strange:
                return values
            i = strange[0]
            raise FormatError(
                f"{path}: column {name!r}, data row {first + i + 1}: expected a "
                f"number; found {cells[i]!r}{_number_hint(cells[i])}."
            )
        i = int(np.flatnonzero(bad)[0])
        raise FormatError(
            f"{path}: column {name!r}, data row {first + i + 1}: expected a finite "
            f"number; found {cells[i]!r}."
        )
    for i, cell in enumerate(cells):  # find the first bad cell for the message
        try:
            float(cell)
        except ValueError:
            raise FormatError(
                f"{path}: column {name!r}, data row {first + i + 1}: expected a "
                f"number; found {cell!r}{_number_hint(cell)}."
            ) from None
    raise AssertionError("unreachable")  # pragma: no cover


class _OrderCheck:
    """Measurement order of a magnet CSV, chunk by chunk (see the module notes).

    Run labels are looked at only where the time does not increase (a run
    boundary or an error), so that a long file costs one parsed column.

    Args:
        path_s: The file, for messages.
        header: Its column names.
        time_column: Time column, checked if the file has it; ``None``: none.
        run_column: Run labels, used if the file has it; ``None``: none.
    """

    def __init__(
        self,
        path_s: str,
        header: list[str],
        time_column: str | None,
        run_column: str | None,
    ) -> None:
        self._path = path_s
        self._header = header
        #: Index of the time column, or ``None`` (nothing to check)
        self.time = header.index(time_column) if time_column in header else None
        self._run = header.index(run_column) if run_column in header else None
        # (time, its cell, all cells) of the last row checked
        self._last: tuple[float, str, list[str]] | None = None

    def __call__(
        self, t_cells: list[str], row: Callable[[int], list[str]], first: int
    ) -> None:
        """Check one chunk, continuing from the last row of the previous one.

        Args:
            t_cells: The chunk's cells of column :attr:`time`.
            row: All cells of the chunk's row ``i``.
            first: Data rows before the chunk.

        Raises:
            FormatError: at the first row whose time does not increase within
                its run.
        """
        if self.time is None or not t_cells:
            return
        name = self._header[self.time]
        t = _parse_cells(t_cells, name, self._path, first)
        last = self._last
        n0 = 0 if last is None else 1  # rows before the chunk's first in t_all
        t_all = t if last is None else np.concatenate([[last[0]], t])

        def cells(j: int) -> list[str]:  # all cells of row j of t_all
            return last[2] if j < n0 else row(j - n0)

        for d in np.flatnonzero(np.diff(t_all) <= 0).tolist():
            before, here = cells(d), cells(d + 1)
            run = None
            if self._run is not None:
                if before[self._run] != here[self._run]:
                    continue  # a new run: its time may restart
                run = here[self._run]
            k = first + d + 1 - n0 + 1  # data row of the offending row
            cell, prev = t_cells[d + 1 - n0], before[self.time]
            if here == before:
                raise FormatError(
                    f"{self._path}: data row {k} repeats data row {k - 1} in every "
                    f"cell (column {name!r} = {cell!r}): a row exported twice? "
                    "Each measurement must appear once, in measurement order."
                )
            where = "" if run is None else f" (run {run!r})"
            hint = (
                f"; a file of several runs whose time restarts needs a "
                f"{DEFAULT_RUN_COLUMN!r} column naming each row's run"
                if self._run is None and t_all[d + 1] < t_all[d]
                else ""
            )
            raise FormatError(
                f"{self._path}: column {name!r}, data row {k}: {cell!r} is not "
                f"after {prev!r} of data row {k - 1}{where}; rows must be in "
                "measurement order, each measurement once (hysteresis depends on "
                f"the order of the inputs){hint}."
            )
        self._last = (float(t[-1]), t_cells[-1], row(len(t_cells) - 1))


def _header(path_s: str, row: list[str]) -> list[str]:
    header = [c.strip() for c in row]
    seen: set[str] = set()
    for name in header:
        if name in seen:
            raise FormatError(
                f"{path_s}: column name {name!r} appears more than once in the "
                "header; names must be unique."
            )
        seen.add(name)
    return header


def iter_magnet_csv(
    path: str | os.PathLike,
    input_column: str,
    chunk_rows: int = 50_000,
    drop: Sequence[str] = (),
    time_column: str | None = DEFAULT_TIME_COLUMN,
    run_column: str | None = DEFAULT_RUN_COLUMN,
) -> tuple[list[str], Iterator[tuple[list[str], np.ndarray]]]:
    """Stream a long magnet CSV: its header and chunks of rows with their inputs.

    Checks as :func:`read_magnet_csv` (header and input column up front, each
    chunk's rows as they arrive), holding one chunk in memory. Rows come back
    as CSV text, one string per row without the line end, ready to be written
    back with more cells appended. Plain files (no quotes, no carriage
    returns) are split with ``str`` methods and parsed with ``float`` in bulk;
    a chunk they do not fit (blank lines, bad cells) and everything after a
    quote or a carriage return go through the ``csv`` module, with the same
    checks and errors, and the measurement order (see the module notes)
    checked across chunks.

    Args:
        path: CSV file with a header row (UTF-8, with or without a BOM).
        input_column: Name of the input column.
        chunk_rows: Rows per chunk (>= 1).
        drop: Columns left out of the returned row texts (not of ``header``).
        time_column: Time column whose values must increase within each run,
            checked if the file has it; ``None``: no order check.
        run_column: Column of run labels (the time may restart where it
            changes), used if the file has it; ``None``: one run.

    Returns:
        ``(header, chunks)``; ``chunks`` yields ``(rows, inputs)``: the rows as
        CSV text and the inputs as float64, shape ``(len(rows),)``.

    Raises:
        FileNotFoundError: if ``path`` does not exist.
        FormatError: as :func:`read_magnet_csv` (raised while iterating for
            problems in data rows, a time that does not increase included).

    Example:
        >>> import tempfile, pathlib
        >>> p = pathlib.Path(tempfile.mkdtemp()) / "m.csv"
        >>> _ = p.write_text("t,current_A\\n0,1.5\\n1,2\\n2,3\\n")
        >>> header, chunks = iter_magnet_csv(p, "current_A", chunk_rows=2)
        >>> [(rows, x.tolist()) for rows, x in chunks]
        [(['0,1.5', '1,2'], [1.5, 2.0]), (['2,3'], [3.0])]
    """
    path_s = str(path)
    if not Path(path).is_file():
        raise FileNotFoundError(f"{path_s}: no such file.")
    if chunk_rows < 1:
        raise ValueError(f"chunk_rows must be >= 1; got {chunk_rows}.")
    stream = _stream_chunks(
        path, input_column, chunk_rows, tuple(drop), time_column, run_column
    )
    header = next(stream)
    return header, stream


def _stream_chunks(
    path: str | os.PathLike,
    input_column: str,
    size: int,
    drop: tuple[str, ...],
    time_column: str | None,
    run_column: str | None,
) -> Iterator:
    """Generator behind :func:`iter_magnet_csv`: the header, then the chunks."""
    path_s = str(path)
    try:
        with open(path, encoding="utf-8-sig", newline="") as f:
            header: list[str] = []
            for line in f:
                rows = _csv_rows([line], path_s)  # [] for a blank row
                if rows:
                    header = _header(path_s, rows[0])
                    break
            if not header:
                raise FormatError(
                    f"{path_s}: empty file; expected a header row and data."
                )
            if input_column not in header:
                raise FormatError(
                    f"{path_s}: no input column {input_column!r}; columns are "
                    f"{header}{separator_hint(header)}."
                )
            col = header.index(input_column)
            keep = [i for i, c in enumerate(header) if c not in drop]
            order = _OrderCheck(path_s, header, time_column, run_column)
            yield header
            done = 0
            while True:
                lines = list(itertools.islice(f, size))
                if not lines:
                    break
                block = "".join(lines)
                if '"' in block or "\r" in block:
                    # quoted cells may span lines: the csv module from here on
                    reader = csv.reader(itertools.chain(lines, f))
                    for rows in _reader_batches(reader, size, path_s):
                        texts, x = _parse_rows(
                            rows, header, col, keep, path_s, done, order
                        )
                        if texts:
                            yield texts, x
                            done += len(texts)
                    break
                got = _fast_chunk(block, len(header), col, keep, order.time)
                if got is not None:
                    texts, x, t_cells, raw = got
                    order(t_cells, lambda i, raw=raw: raw[i].split(","), done)
                    got = texts, x
                else:  # something to skip or report: the careful way
                    rows = _csv_rows(lines, path_s)
                    got = _parse_rows(rows, header, col, keep, path_s, done, order)
                if got[0]:
                    yield got
                    done += len(got[0])
            if done == 0:
                raise FormatError(
                    f"{path_s}: header only; expected at least one data row."
                )
    except UnicodeDecodeError as err:
        raise FormatError(f"{path_s}: not UTF-8 text ({err.reason}).") from None


def _fast_chunk(
    block: str, n_cols: int, col: int, keep: list[int], time: int | None
) -> tuple[list[str], np.ndarray, list[str], list[str]] | None:
    """Rows and inputs of a plain chunk (no quotes), or ``None`` if it is not clean.

    Clean: no blank lines, ``n_cols`` cells per row, no cell (line) longer
    than ``MAX_CELL_CHARS``, finite numbers in the input column.

    Returns:
        The rows' texts (columns ``keep``), their inputs, their cells of column
        ``time`` (``[]`` for ``None``) and their whole texts.
    """
    texts = block.split("\n")
    if texts[-1] == "":
        texts.pop()
    if max(map(len, texts)) > MAX_CELL_CHARS:
        return None
    if n_cols == 1:
        if "," in block:
            return None
        picked = [texts, texts]
    else:
        if block.count(",") != len(texts) * (n_cols - 1) or any(
            t.count(",") != n_cols - 1 for t in texts
        ):
            return None
        # one comprehension per column: keeping each row's split list alive
        # for both would wake the garbage collector (~3x slower)
        wanted = (col,) if time is None else (col, time)
        picked = [[t.split(",", c + 1)[c] for t in texts] for c in wanted]
    if any("_" in c for c in picked[0]):  # not a plain decimal: the careful way
        return None
    try:
        x = np.array(list(map(float, picked[0])), dtype=np.float64)
    except ValueError:  # a blank line or a cell that is not a number
        return None
    if not np.isfinite(x).all():
        return None
    t_cells = picked[1] if time is not None else []
    raw = texts
    if len(keep) < n_cols:
        texts = [",".join(t.split(",")[i] for i in keep) for t in texts]
    return texts, x, t_cells, raw


def _csv_rows(lines: Iterable[str], path_s: str) -> list[list[str]]:
    """Rows of ``lines`` by the ``csv`` module (cells up to ``MAX_CELL_CHARS``)."""
    return next(_reader_batches(csv.reader(lines), None, path_s), [])


def _reader_batches(reader, size: int | None, path_s: str) -> Iterator[list[list[str]]]:
    """Non-blank rows of a ``csv.reader`` in batches (one batch for ``None``)."""
    while True:
        limit = csv.field_size_limit(MAX_CELL_CHARS)
        try:
            batch = list(itertools.islice(reader, size))
        except csv.Error as err:
            if "field larger than field limit" in str(err):
                raise FormatError(
                    f"{path_s}: line {reader.line_num}: a cell longer than "
                    f"{MAX_CELL_CHARS} characters; not magnet data."
                ) from None
            raise FormatError(
                f"{path_s}: line {reader.line_num}: not valid CSV ({err})."
            ) from None
        finally:
            csv.field_size_limit(limit)
        if not batch:
            return
        yield [r for r in batch if "".join(r).strip()]
        if size is None:
            return


def _parse_rows(
    rows: list[list[str]],
    header: list[str],
    col: int,
    keep: list[int],
    path_s: str,
    done: int,
    order: _OrderCheck,
) -> tuple[list[str], np.ndarray]:
    """Checked rows of a chunk as CSV text, and their inputs."""
    for i, row in enumerate(rows):
        if len(row) != len(header):
            raise FormatError(
                f"{path_s}: data row {done + i + 1} has {len(row)} cells; "
                f"the header has {len(header)}."
            )
    x = _parse_column(rows, col, header[col], path_s, done)
    if order.time is not None:
        order([row[order.time] for row in rows], rows.__getitem__, done)
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    texts = []
    for row in rows:
        writer.writerow([row[i] for i in keep])
        texts.append(buf.getvalue()[:-1])
        buf.seek(0)
        buf.truncate()
    return texts, x


def append_columns(
    rows: Sequence[str], columns: Sequence[np.ndarray], digits: Sequence[int]
) -> str:
    """CSV text of ``rows`` with float (or flag) columns appended, formatted in bulk.

    Row ``i`` becomes ``f"{rows[i]},{c1[i]},{c2[i]}...\\n"``, each number in
    scientific notation with ``digits`` significant digits (at most 15, the
    decimal digits a float64 keeps: ``-1.23456789012345e-03``; the last digit
    within one unit of correct rounding, relative error <= 1e-14 at 15). The
    digits come from integer arithmetic on whole columns (numpy), not one
    ``format`` call per number; a chunk holding non-finite values or exponents
    beyond +-99 is formatted by Python's ``format`` instead (``nan``, ``inf``).
    A boolean column is written as ``0`` and ``1`` (its ``digits`` unused).

    Args:
        rows: CSV text of each row, without the line end.
        columns: Values to append, each shape ``(len(rows),)`` (numpy arrays,
            or anything ``numpy.asarray`` takes, e.g. CPU tensors); boolean
            ones are flags.
        digits: Significant digits per column, ``1 <= d <= 15``.

    Returns:
        The text, one line per row, each ending in ``"\\n"``.

    Example:
        >>> append_columns(["a", "b"], [np.array([1.5, -0.00025])], [3])
        'a,1.50e+00\\nb,-2.50e-04\\n'
        >>> append_columns(["a", "b"], [np.array([2.0, 3.0]), [False, True]], [2, 1])
        'a,2.0e+00,0\\nb,3.0e+00,1\\n'
    """
    if not rows:
        return ""
    columns = [np.asarray(c).reshape(-1) for c in columns]
    columns = [c if c.dtype == np.bool_ else c.astype(np.float64) for c in columns]
    parts = [
        _flags(c) if c.dtype == np.bool_ else _scientific(c, d)
        for c, d in zip(columns, digits, strict=True)
    ]
    if any(p is None for p in parts):
        fmts = [
            "{:d}" if c.dtype == np.bool_ else f"{{:.{d - 1}e}}"
            for c, d in zip(columns, digits, strict=True)
        ]
        values = [c.tolist() for c in columns]
        lines = [
            ",".join(
                [row, *(f.format(v[i]) for f, v in zip(fmts, values, strict=True))]
            )
            + "\n"
            for i, row in enumerate(rows)
        ]
        return "".join(lines)
    n = len(rows)
    # drop the sign slot (column 1 of a block) of non-negative values: at once
    # for a block without negative values, row by row (shift left, NUL-padded)
    # for mixed ones, right to left
    blocks, mixed, start = [], [], 0
    for block, negative in parts:
        if not negative.any():
            block = np.delete(block, 1, axis=1)
        elif not negative.all():
            mixed.append((start + 1, negative))
        blocks.append(block)
        start += block.shape[1]
    newline = np.full((n, 1), ord("\n"), dtype=np.uint32)
    mat = np.concatenate([*blocks, newline], axis=1)
    nul = np.zeros((n, 1), dtype=np.uint32)
    for slot, negative in reversed(mixed):
        shifted = np.concatenate([mat[:, :slot], mat[:, slot + 1 :], nul], axis=1)
        mat = np.where(negative[:, None], mat, shifted)
    width = mat.shape[1]
    # UCS-4 code points viewed as numpy str; trailing NULs are dropped
    text = np.ascontiguousarray(mat, dtype="<u4").view(f"<U{width}")[:, 0]
    return "".join(map(operator.add, rows, text.tolist()))


# code points of "0000" .. "9999", 16 bytes each, viewed as one complex128 per
# group so that a lookup is one 16-byte gather: shape (10^4,)
_FOUR_DIGITS = (
    (np.arange(10**4)[:, None] // np.array([1000, 100, 10, 1]) % 10 + ord("0"))
    .astype(np.uint32)
    .view(np.complex128)
    .ravel()
)


def _flags(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``,0`` or ``,1`` code points of booleans in :func:`_scientific`'s layout.

    Shape ``(N, 3)`` with a sign slot (column 1), and no value negative.
    """
    mat = np.empty((x.shape[0], 3), dtype=np.uint32)
    mat[:, 0] = ord(",")
    mat[:, 1] = ord("-")
    mat[:, 2] = ord("0") + x
    return mat, np.zeros(x.shape[0], dtype=bool)


def _scientific(x: np.ndarray, digits: int) -> tuple[np.ndarray, np.ndarray] | None:
    """``,[-]d.ddde+XX`` code points of each value, shape ``(N, digits + 7)``.

    Returns the matrix (sign slot ``-`` in column 1 for every row) and which
    values are negative, or ``None`` for non-finite values or exponents
    beyond +-99.
    """
    if not 1 <= digits <= 15:
        raise ValueError(f"digits must be in 1..15; got {digits}.")
    if digits == 1 or not np.isfinite(x).all():  # "1e+00" has no point: Python
        return None
    a = np.abs(x)
    zero = a == 0.0
    with np.errstate(divide="ignore"):
        e = np.floor(np.log10(np.where(zero, 1.0, a))).astype(np.int64)
    if (np.abs(e) > 99).any():
        return None
    d = np.rint(a * np.power(10.0, digits - 1 - e))
    high = d >= 10.0**digits  # log10 rounded down, or rounding carried over
    d = np.where(high, np.rint(d / 10.0), d)
    e = e + high
    low = (d < 10.0 ** (digits - 1)) & ~zero  # log10 rounded up
    d = np.where(low, np.rint(a * np.power(10.0, digits - e)), d)
    e = np.where(zero, 0, e - low)
    if (np.abs(e) > 99).any():
        return None
    n = x.shape[0]
    # digits of d < 10^15 as four groups of four, looked up (int64 division
    # is slow): d = ((g0 * 10^4 + g1) * 10^4 + g2) * 10^4 + g3
    d64 = d.astype(np.int64)
    hi, lo = (d64 // 10**8).astype(np.int32), (d64 % 10**8).astype(np.int32)
    groups = np.stack([hi // 10**4, hi % 10**4, lo // 10**4, lo % 10**4], axis=1)
    digit = np.take(_FOUR_DIGITS, groups).view(np.uint32).reshape(n, 16)
    digit = digit[:, 16 - digits :]
    mat = np.empty((n, digits + 7), dtype=np.uint32)
    mat[:, 0] = ord(",")
    mat[:, 1] = ord("-")
    mat[:, 2] = digit[:, 0]
    mat[:, 3] = ord(".")
    mat[:, 4 : digits + 3] = digit[:, 1:]
    mat[:, digits + 3] = ord("e")
    mat[:, digits + 4] = np.where(e < 0, ord("-"), ord("+"))
    mat[:, digits + 5] = np.abs(e) // 10 + ord("0")
    mat[:, digits + 6] = np.abs(e) % 10 + ord("0")
    return mat, np.signbit(x)
