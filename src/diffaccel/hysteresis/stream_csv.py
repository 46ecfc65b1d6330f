"""Predicting a magnet CSV of any length, chunk by chunk, with numpy only.

:func:`write_predictions` streams the chunks of
:func:`~diffaccel.data.iter_magnet_csv` through a fitted model's
:class:`~diffaccel.hysteresis.StreamPredictor` and writes each row back with
three columns appended: :data:`PREDICTION` and :data:`PREDICTION_STD` [output
units] and the flag :data:`OUTSIDE` (1 where the input lies beyond the fit's
input range). CSV parsing, the model and the formatting overlap in threads
(:func:`read_ahead`); numpy releases the GIL. No torch is imported, except by
:func:`stream_fit` for a fit folder saved without ``stream.npz``.
:func:`predict_csv` is ``hysteresis predict``: it checks the output file, reads
the input CSV and writes the predictions atomically.
"""

from __future__ import annotations

import csv
import math
import queue
import threading
import warnings
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

import diffaccel.hysteresis as hysteresis
from diffaccel.data.atomic import (
    OutputWriteError,
    atomic_write,
    os_condition,
    os_error_text,
)
from diffaccel.data.magnet_stream import (
    DEFAULT_INPUT_COLUMN,
    DEFAULT_TIME_COLUMN,
    append_columns,
    check_magnitude,
    check_time_column,
    iter_magnet_csv,
)
from diffaccel.data.owned_files import OutputFileError, check_out_file
from diffaccel.hysteresis.fit_folder import load_stream_fit
from diffaccel.hysteresis.stream import (
    InputRangeWarning,
    StreamPredictor,
    StreamSpec,
    outside_input_range,
)

__all__ = [
    "COLUMNS",
    "OUTSIDE",
    "PREDICTION",
    "PREDICTION_STD",
    "StreamStats",
    "check_csv_output",
    "outside_warning",
    "predict_csv",
    "read_ahead",
    "stream_fit",
    "write_predictions",
]

PREDICTION = "prediction"
PREDICTION_STD = "prediction_std"
OUTSIDE = "outside_input_range"
#: The columns :func:`write_predictions` appends, in order.
COLUMNS = (PREDICTION, PREDICTION_STD, OUTSIDE)
#: Significant digits of the appended columns: 15 (all a float64 keeps in
#: decimal) for the prediction, 7 for its std (float32 sums), the flag as 0/1.
DIGITS = (15, 7, 1)

_DONE = object()
T = TypeVar("T")


@dataclass
class StreamStats:
    """What :func:`write_predictions` saw, updated as it streams.

    Attributes:
        rows: Rows predicted.
        finite: Whether every prediction was finite.
        min: Smallest input [input units] (``inf`` before the first row).
        max: Largest input (``-inf`` before the first row).
        outside_rows: Rows with the input beyond the fit's input range.
        outside_first: Data row (1: the first below the header) of the first
            such row; 0 where there is none.
    """

    rows: int = 0
    finite: bool = True
    min: float = math.inf
    max: float = -math.inf
    outside_rows: int = 0
    outside_first: int = 0


def read_ahead(items: Iterable[T], depth: int = 2) -> Iterator[T]:
    """Iterate ``items`` in a background thread, up to ``depth`` items ahead.

    Lets Python work (CSV parsing, formatting) overlap torch and numpy work,
    which releases the GIL. An exception raised by ``items`` is raised here,
    in the caller's thread, when its turn comes.
    """
    buffer: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def work() -> None:
        try:
            for item in items:
                while not stop.is_set():
                    try:
                        buffer.put((item, None), timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
                    return
        except BaseException as err:  # handed over to the consumer
            buffer.put((_DONE, err))
            return
        buffer.put((_DONE, None))

    thread = threading.Thread(target=work, daemon=True)
    thread.start()
    try:
        while True:
            item, err = buffer.get()
            if err is not None:
                raise err
            if item is _DONE:
                return
            yield item
    finally:
        stop.set()


def stream_fit(fit_dir: Path) -> tuple[StreamSpec, dict[str, Any]]:
    """A fit folder's stream spec and settings (``model.json``).

    Read from ``stream.npz`` without torch; a folder saved before that file
    existed is read with torch (:func:`~diffaccel.hysteresis.load_fit`).

    Raises:
        ValueError: a folder that holds no fit, or files of different fits.
    """
    try:
        return load_stream_fit(fit_dir)
    except FileNotFoundError:
        pass
    # the package loads its torch parts on this first use (see its docstring)
    model, band, config = hysteresis.load_fit(fit_dir)
    spec = band.stream_spec(model) if band is not None else model.stream_spec()
    return spec, config


def write_predictions(
    path: Path,
    spec: StreamSpec,
    header: list[str],
    chunks: Iterable[tuple[list[str], np.ndarray]],
    *,
    check: Callable[[np.ndarray, int], None] | None = None,
    stats: StreamStats | None = None,
) -> StreamStats:
    """Predict every row of a magnet CSV from the fit's initial state into ``path``.

    Args:
        path: The CSV file to write (replaced; write it through
            :func:`~diffaccel.data.atomic_write`).
        spec: The fit (:func:`stream_fit`).
        header: The input's header; its columns named in :data:`COLUMNS` are
            left out (the row texts of ``chunks`` must leave them out too).
        chunks: ``(row texts, inputs (R,))`` per chunk, in time order
            (:func:`~diffaccel.data.iter_magnet_csv`).
        check: Called with each chunk's inputs and the data row of its first
            row (1: below the header) before it is predicted, to refuse bad
            values.
        stats: Updated as rows are written (a new one where None).

    Returns:
        ``stats``: rows, input extremes, rows beyond the input range.
    """
    stats = StreamStats() if stats is None else stats
    pending: list[list[str]] = []

    def inputs() -> Iterator[np.ndarray]:
        first_row = 1  # data row of the chunk's first row (1: below the header)
        for rows, x in chunks:
            if check is not None:
                check(x, first_row)
            first_row += len(rows)
            pending.append(rows)
            stats.min = min(stats.min, float(x.min()))
            stats.max = max(stats.max, float(x.max()))
            yield x

    def texts() -> Iterator[tuple[list[str], list[np.ndarray]]]:
        predictor = StreamPredictor(spec)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", InputRangeWarning)  # in stats
            # CSV parsing (next chunk) overlaps the model (this chunk)
            for x in read_ahead(inputs()):
                pred, std = predictor(x)
                flag = outside_input_range(x, spec.input_range)
                n_out = int(flag.sum())
                if n_out and not stats.outside_first:
                    stats.outside_first = stats.rows + int(flag.argmax()) + 1
                stats.outside_rows += n_out
                rows = pending.pop(0)
                stats.rows += len(rows)
                stats.finite &= bool(np.isfinite(pred).all())
                if std is None:
                    std = np.full_like(pred, math.nan)
                yield rows, [pred, std, flag]

    out_header = [c for c in header if c not in COLUMNS] + list(COLUMNS)
    with open(path, "w", newline="", encoding="utf-8") as f:
        csv.writer(f, lineterminator="\n").writerow(out_header)
        for rows, columns in read_ahead(texts()):
            f.write(append_columns(rows, columns, DIGITS))
    return stats


def outside_warning(
    stats: StreamStats, input_range: tuple[float, float], column: str
) -> str | None:
    """The warning on rows beyond the fit's input range; None where there is none.

    Names their count, the first such row, how far beyond the range they go
    (in input units and as a share of the range) and how they were predicted.
    """
    if not stats.outside_rows:
        return None
    lo, hi = input_range
    beyond = max(lo - stats.min, stats.max - hi, 0.0)
    return (
        f"{stats.outside_rows} of {stats.rows} rows (the first: data "
        f"row {stats.outside_first}) have {column} outside the fit's input range "
        f"[{lo:.6g}, {hi:.6g}] {column}, by up to {beyond:.4g} {column} "
        f"({100 * beyond / (hi - lo):.3g} % of the range); {OUTSIDE} = 1 "
        "there. They are extrapolated as saturated (every hysteron switched) "
        f"plus the linear term; their {PREDICTION_STD} widens with the linear "
        "term's uncertainty only, not with any doubt about the saturation."
    )


def check_csv_output(out: Path, data: Path, force: bool) -> None:
    """Refuse the output file ``out`` of :func:`predict_csv` before any work.

    The refusals ``force`` does not lift come first (the input itself, a file
    inside a result folder), then a name that is not ``.csv``, then what
    ``force`` allows (:func:`~diffaccel.data.owned_files.check_out_file`).

    Raises:
        OutputFileError: naming ``--out`` and the file.
    """
    check_out_file(out, True, {"--input": data}, csv_columns=COLUMNS)
    if out.suffix.lower() != ".csv":
        raise OutputFileError(
            f"--out {out}: expected a .csv file name (the output is CSV text)."
        )
    check_out_file(out, force, {"--input": data}, csv_columns=COLUMNS)


def predict_csv(
    spec: StreamSpec,
    config: dict[str, Any],
    data: Path,
    out: Path,
    *,
    chunk_rows: int = 20_000,
    time_column: str | None = None,
    force: bool = False,
) -> StreamStats:
    """Predict every row of the CSV ``data`` into ``out`` (:func:`write_predictions`).

    The input column is the fit's (``config``, its ``model.json``);
    ``time_column`` None checks the default time column where the file has
    it. The input's columns named in :data:`COLUMNS` are replaced only with
    ``force``. ``out`` is written atomically, its folder made where missing.

    Raises:
        OptionError: a missing ``time_column`` (``--time-column``).
        ValueError: an input that cannot be read, a value beyond
            :data:`~diffaccel.data.magnet_stream.MAX_MAGNITUDE`, columns of
            :data:`COLUMNS` without ``force``.
        OSError: a file that cannot be read; an
            :class:`~diffaccel.data.atomic.OutputWriteError` (the condition in
            words) where ``out`` cannot be written.
    """
    in_col = config.get("input_column", DEFAULT_INPUT_COLUMN)
    header, chunks = iter_magnet_csv(
        data,
        in_col,
        chunk_rows=chunk_rows,
        drop=COLUMNS,
        time_column=time_column or DEFAULT_TIME_COLUMN,
    )
    check_time_column(data, header, time_column)
    clash = [c for c in COLUMNS if c in header]
    if clash and not force:
        raise ValueError(
            f"{data} already has column(s) {clash}; pass --force to replace them "
            "in the output (the input file is never changed)."
        )
    stats = StreamStats()

    def write(path: Path) -> None:
        write_predictions(
            path,
            spec,
            header,
            chunks,
            check=lambda x, first_row: check_magnitude(data, in_col, x, first_row),
            stats=stats,
        )

    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        if os_condition(err) is not None:  # read-only, no space...
            raise OutputWriteError(os_error_text(err, out)) from err
        raise OutputWriteError(
            f"--out {out}: cannot create its folder {out.parent}: {err}"
        ) from err
    try:
        atomic_write(out, write)
    except OSError as err:  # a read-only folder, a full disk
        raise OutputWriteError(os_error_text(err, out)) from err
    return stats
