"""Long magnet CSV files in chunks of rows: read, and written back with columns.

:func:`iter_magnet_csv` reads a time-ordered magnet CSV (see
:mod:`~diffaccel.data.magnet_csv`) a chunk of rows at a time, keeping each row's
text; :func:`append_columns` writes rows back with float columns appended,
formatted in bulk. numpy only (no torch), so that a command streaming a long
file (``diffaccel hysteresis predict``) starts fast.
"""

from __future__ import annotations

import csv
import io
import itertools
import operator
import os
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np

from diffaccel.data.errors import FormatError

__all__ = [
    "DEFAULT_INPUT_COLUMN",
    "DEFAULT_OUTPUT_COLUMN",
    "MAX_CELL_CHARS",
    "append_columns",
    "iter_magnet_csv",
]

DEFAULT_INPUT_COLUMN = "current_A"
DEFAULT_OUTPUT_COLUMN = "field_Tm"
# longest accepted cell (a number, a label); longer ones are not magnet data
MAX_CELL_CHARS = 1000


def _parse_column(
    rows: list[list[str]], col: int, name: str, path: str, first: int = 0
) -> np.ndarray:
    """Column ``col`` of ``rows`` as finite float64 numbers, or a clear error."""
    try:
        values = np.array([float(row[col]) for row in rows], dtype=np.float64)
    except (ValueError, IndexError):
        values = None
    if values is not None:
        bad = ~np.isfinite(values)
        if not bad.any():
            return values
        i = int(np.flatnonzero(bad)[0])
        raise FormatError(
            f"{path}: column {name!r}, data row {first + i + 1}: expected a finite "
            f"number; found {rows[i][col]!r}."
        )
    for i, row in enumerate(rows):  # find the first bad cell for the message
        try:
            float(row[col])
        except (ValueError, IndexError):
            cell = row[col] if col < len(row) else "<missing>"
            raise FormatError(
                f"{path}: column {name!r}, data row {first + i + 1}: expected a "
                f"number; found {cell!r}."
            ) from None
    raise AssertionError("unreachable")  # pragma: no cover


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
) -> tuple[list[str], Iterator[tuple[list[str], np.ndarray]]]:
    """Stream a long magnet CSV: its header and chunks of rows with their inputs.

    Checks as :func:`read_magnet_csv` (header and input column up front, each
    chunk's rows as they arrive), holding one chunk in memory. Rows come back
    as CSV text, one string per row without the line end, ready to be written
    back with more cells appended. Plain files (no quotes, no carriage
    returns) are split with ``str`` methods and parsed with ``float`` in bulk;
    a chunk they do not fit (blank lines, bad cells) and everything after a
    quote or a carriage return go through the ``csv`` module, with the same
    checks and errors.

    Args:
        path: CSV file with a header row (UTF-8, with or without a BOM).
        input_column: Name of the input column.
        chunk_rows: Rows per chunk (>= 1).
        drop: Columns left out of the returned row texts (not of ``header``).

    Returns:
        ``(header, chunks)``; ``chunks`` yields ``(rows, inputs)``: the rows as
        CSV text and the inputs as float64, shape ``(len(rows),)``.

    Raises:
        FileNotFoundError: if ``path`` does not exist.
        FormatError: as :func:`read_magnet_csv` (raised while iterating for
            problems in data rows).

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
    stream = _stream_chunks(path, input_column, chunk_rows, tuple(drop))
    header = next(stream)
    return header, stream


def _stream_chunks(
    path: str | os.PathLike, input_column: str, size: int, drop: tuple[str, ...]
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
                    f"{path_s}: no input column {input_column!r}; columns are {header}."
                )
            col = header.index(input_column)
            keep = [i for i, c in enumerate(header) if c not in drop]
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
                        texts, x = _parse_rows(rows, header, col, keep, path_s, done)
                        if texts:
                            yield texts, x
                            done += len(texts)
                    break
                got = _fast_chunk(block, len(header), col, keep)
                if got is None:  # something to skip or report: the careful way
                    rows = _csv_rows(lines, path_s)
                    got = _parse_rows(rows, header, col, keep, path_s, done)
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
    block: str, n_cols: int, col: int, keep: list[int]
) -> tuple[list[str], np.ndarray] | None:
    """Rows and inputs of a plain chunk (no quotes), or ``None`` if it is not clean.

    Clean: no blank lines, ``n_cols`` cells per row, no cell (line) longer
    than ``MAX_CELL_CHARS``, finite numbers in the input column.
    """
    texts = block.split("\n")
    if texts[-1] == "":
        texts.pop()
    if max(map(len, texts)) > MAX_CELL_CHARS:
        return None
    if n_cols == 1:
        if "," in block:
            return None
        cells = texts
    else:
        if block.count(",") != len(texts) * (n_cols - 1) or any(
            t.count(",") != n_cols - 1 for t in texts
        ):
            return None
        cells = [t.split(",", col + 1)[col] for t in texts]
    try:
        x = np.array(list(map(float, cells)), dtype=np.float64)
    except ValueError:  # a blank line or a cell that is not a number
        return None
    if not np.isfinite(x).all():
        return None
    if len(keep) < n_cols:
        texts = [",".join(t.split(",")[i] for i in keep) for t in texts]
    return texts, x


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
) -> tuple[list[str], np.ndarray]:
    """Checked rows of a chunk as CSV text, and their inputs."""
    for i, row in enumerate(rows):
        if len(row) != len(header):
            raise FormatError(
                f"{path_s}: data row {done + i + 1} has {len(row)} cells; "
                f"the header has {len(header)}."
            )
    x = _parse_column(rows, col, header[col], path_s, done)
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
    """CSV text of ``rows`` with float columns appended, formatted in bulk.

    Row ``i`` becomes ``f"{rows[i]},{c1[i]},{c2[i]}...\\n"``, each number in
    scientific notation with ``digits`` significant digits (at most 15, the
    decimal digits a float64 keeps: ``-1.23456789012345e-03``; the last digit
    within one unit of correct rounding, relative error <= 1e-14 at 15). The
    digits come from integer arithmetic on whole columns (numpy), not one
    ``format`` call per number; a chunk holding non-finite values or exponents
    beyond +-99 is formatted by Python's ``format`` instead (``nan``, ``inf``).

    Args:
        rows: CSV text of each row, without the line end.
        columns: Values to append, each shape ``(len(rows),)`` (numpy arrays,
            or anything ``numpy.asarray`` takes, e.g. CPU tensors).
        digits: Significant digits per column, ``1 <= d <= 15``.

    Returns:
        The text, one line per row, each ending in ``"\\n"``.

    Example:
        >>> append_columns(["a", "b"], [np.array([1.5, -0.00025])], [3])
        'a,1.50e+00\\nb,-2.50e-04\\n'
    """
    if not rows:
        return ""
    columns = [np.asarray(c, dtype=np.float64).reshape(-1) for c in columns]
    parts = [_scientific(c, d) for c, d in zip(columns, digits, strict=True)]
    if any(p is None for p in parts):
        fmts = [f"{{:.{d - 1}e}}" for d in digits]
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
