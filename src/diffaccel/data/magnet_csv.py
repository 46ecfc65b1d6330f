"""Magnet histories in CSV files: time-ordered input (current) and output (field).

A magnet CSV has a header row and one row per measurement, in time order.
Column names are free; the defaults follow the SLAC rotating-coil files:
``current_A`` (input [A]) and ``field_Tm`` (integrated gradient [T m]). Other
columns (run labels, times, uncertainties) are kept as text so that they can be
written back unchanged. A time column (``time_s``) must increase within each
run (``run``); see :mod:`~diffaccel.data.magnet_stream` for what is checked
and what cannot be.
"""

from __future__ import annotations

import csv
import io
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from diffaccel.data.atomic import atomic_write_text
from diffaccel.data.errors import FormatError
from diffaccel.data.magnet_stream import (
    DEFAULT_INPUT_COLUMN,
    DEFAULT_OUTPUT_COLUMN,
    DEFAULT_RUN_COLUMN,
    DEFAULT_TIME_COLUMN,
    _header,
    _OrderCheck,
    _parse_column,
    _reader_batches,
    separator_hint,
)

__all__ = [
    "MagnetHistory",
    "read_magnet_csv",
    "write_csv_atomic",
]


@dataclass
class MagnetHistory:
    """A measured magnet history read from CSV.

    Attributes:
        input: Input column in time order [its unit, e.g. A], shape ``(T,)``.
        output: Output column [its unit, e.g. T m], shape ``(T,)``, or ``None``
            when the file has no such column.
        input_column: Name of the input column.
        output_column: Name of the output column.
        header: All column names, in file order.
        rows: All cells as text, ``T`` rows in file order.
    """

    input: Tensor
    output: Tensor | None
    input_column: str
    output_column: str
    header: list[str] = field(default_factory=list)
    rows: list[list[str]] = field(default_factory=list)

    def __len__(self) -> int:
        return self.input.numel()


def _row_batches(path: str | os.PathLike, size: int) -> Iterator[list[list[str]]]:
    """Non-blank CSV rows in batches of up to ``size``; a UTF-8 BOM is accepted.

    Cells longer than ``MAX_CELL_CHARS`` are refused by the C parser itself
    (its field size limit, set only while this reader parses).
    """
    path_s = str(path)
    try:
        with open(path, encoding="utf-8-sig", newline="") as f:
            yield from _reader_batches(csv.reader(f), size, path_s)
    except UnicodeDecodeError as err:
        raise FormatError(f"{path_s}: not UTF-8 text ({err.reason}).") from None


def read_magnet_csv(
    path: str | os.PathLike,
    input_column: str = DEFAULT_INPUT_COLUMN,
    output_column: str = DEFAULT_OUTPUT_COLUMN,
    require_output: bool = True,
    time_column: str | None = DEFAULT_TIME_COLUMN,
    run_column: str | None = DEFAULT_RUN_COLUMN,
) -> MagnetHistory:
    """Read a time-ordered magnet history from a CSV file.

    Args:
        path: CSV file with a header row (UTF-8, with or without a BOM).
        input_column: Name of the input column (e.g. current [A]).
        output_column: Name of the output column (e.g. field [T m]).
        require_output: Raise if the output column is missing; otherwise
            ``output`` is ``None`` (files to predict on).
        time_column: Time column whose values must increase within each run,
            checked if the file has it; ``None``: no order check.
        run_column: Column of run labels (the time may restart where it
            changes), used if the file has it; ``None``: one run.

    Returns:
        A :class:`MagnetHistory` with float64 tensors.

    Raises:
        FileNotFoundError: if ``path`` does not exist.
        FormatError: (a ``ValueError``) for an empty file, a missing or
            repeated column, ragged rows, cells longer than ``MAX_CELL_CHARS``,
            cells that are not finite numbers, or a time that does not increase
            within a run (rows not in measurement order, or repeated).

    Example:
        >>> import tempfile, pathlib
        >>> p = pathlib.Path(tempfile.mkdtemp()) / "m.csv"
        >>> _ = p.write_text("current_A,field_Tm\\n0,0.03\\n10,0.35\\n")
        >>> h = read_magnet_csv(p)
        >>> h.input.tolist(), h.output.tolist()
        ([0.0, 10.0], [0.03, 0.35])
    """
    path_s = str(path)
    if not Path(path).is_file():
        raise FileNotFoundError(f"{path_s}: no such file.")
    rows = [r for batch in _row_batches(path, 65536) for r in batch]
    if not rows:
        raise FormatError(f"{path_s}: empty file; expected a header row and data.")
    header = _header(path_s, rows[0])
    data = rows[1:]
    if not data:
        raise FormatError(f"{path_s}: header only; expected at least one data row.")
    for i, row in enumerate(data):
        if len(row) != len(header):
            raise FormatError(
                f"{path_s}: data row {i + 1} has {len(row)} cells; the header has "
                f"{len(header)}{separator_hint(header)}."
            )
    if input_column not in header:
        raise FormatError(
            f"{path_s}: no input column {input_column!r}; columns are "
            f"{header}{separator_hint(header)}."
        )
    if output_column == input_column:
        raise FormatError(
            f"{path_s}: input and output are the same column {input_column!r}; "
            "name the measured output column."
        )
    u = torch.from_numpy(
        _parse_column(data, header.index(input_column), input_column, path_s)
    )
    y = None
    if output_column in header:
        col = header.index(output_column)
        y = torch.from_numpy(_parse_column(data, col, output_column, path_s))
    elif require_output:
        raise FormatError(
            f"{path_s}: no output column {output_column!r}; columns are "
            f"{header}{separator_hint(header)}."
        )
    order = _OrderCheck(path_s, header, time_column, run_column)
    if order.time is not None:
        order([row[order.time] for row in data], data.__getitem__, 0)
    return MagnetHistory(
        input=u,
        output=y,
        input_column=input_column,
        output_column=output_column,
        header=header,
        rows=[list(r) for r in data],
    )


def write_csv_atomic(
    path: str | os.PathLike,
    header: Sequence[str],
    rows: Sequence[Sequence[object]],
    overwrite: bool = False,
) -> Path:
    """Write a CSV file atomically (temporary file in the same folder, then rename).

    Args:
        path: Destination.
        header: Column names.
        rows: Rows of cells (converted with ``str``; floats with ``repr``).
        overwrite: Replace an existing file.

    Returns:
        The destination path.

    Raises:
        FileExistsError: if ``path`` exists and ``overwrite`` is false.
        ValueError: if a row's length differs from the header's.
    """
    dest = Path(path)
    if dest.exists() and not overwrite:
        raise FileExistsError(f"{dest} exists; pass overwrite=True to replace it.")
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(list(header))
    for i, row in enumerate(rows):
        if len(row) != len(header):
            raise ValueError(
                f"row {i} has {len(row)} cells; the header has {len(header)}."
            )
        writer.writerow([repr(c) if isinstance(c, float) else str(c) for c in row])
    dest.parent.mkdir(parents=True, exist_ok=True)
    return atomic_write_text(dest, buf.getvalue())
