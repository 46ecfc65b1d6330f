"""``diffaccel hysteresis predict``: predict a long magnet history, streamed.

Imports only what predicting needs: numpy, the streaming code of fitted models
(:mod:`diffaccel.hysteresis.stream`) and the CSV streaming of
:mod:`diffaccel.data.magnet_stream`; no torch (~2 s of start-up), no plotting,
no GP libraries (see ``benchmarks/preisach_stream.py``). A fit folder saved
before ``stream.npz`` existed is read with torch instead.

Rows whose input lies beyond the fit's input range are extrapolated: every
hysteron switched (saturation) plus the linear term. They are flagged per row
(``outside_input_range``) and counted in a warning; their ``prediction_std``
widens only with the uncertainty of the model's linear term (see
:mod:`diffaccel.hysteresis.band`), not with any doubt about the saturation,
which no fitted number can measure. Rows inside the range are unaffected.
"""

from __future__ import annotations

import csv
import math
import queue
import threading
import warnings
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import TypeVar

import click
import numpy as np

import diffaccel.hysteresis as hysteresis
from diffaccel.cli.hysteresis import (
    check_magnitude,
    check_time_column,
    time_column_option,
)
from diffaccel.cli.output import check_out_file, os_error
from diffaccel.data import (
    DEFAULT_INPUT_COLUMN,
    DEFAULT_TIME_COLUMN,
    append_columns,
    atomic_write,
    iter_magnet_csv,
)
from diffaccel.data.atomic import os_condition
from diffaccel.hysteresis import (
    InputRangeWarning,
    StreamPredictor,
    StreamSpec,
    load_stream_fit,
    outside_input_range,
)

__all__ = ["predict_command", "read_ahead"]

PREDICTION = "prediction"
PREDICTION_STD = "prediction_std"
OUTSIDE = "outside_input_range"
COLUMNS = (PREDICTION, PREDICTION_STD, OUTSIDE)
CHUNK_ROWS = 20_000
# cap of --chunk-rows: a chunk is held in memory (10^9 rows: tens of GB)
MAX_CHUNK_ROWS = 10**9


@click.command("predict")
@click.argument(
    "fit_dir", type=click.Path(exists=True, file_okay=False, path_type=Path)
)
@click.option(
    "--input",
    "data",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    required=True,
    help="CSV with the input column of the fit, rows in time order (any length).",
)
@time_column_option
@click.option(
    "--out", "out_file", type=click.Path(dir_okay=False, path_type=Path), required=True
)
@click.option(
    "--chunk-rows",
    type=click.IntRange(min=1, max=MAX_CHUNK_ROWS),
    default=CHUNK_ROWS,
    show_default=True,
    help="Rows read, predicted and written at a time (memory grows with it).",
)
@click.option(
    "--force",
    is_flag=True,
    help=f"Overwrite OUT if it exists, and replace the columns {', '.join(COLUMNS)} "
    "of the input.",
)
def predict_command(
    fit_dir: Path,
    data: Path,
    time_column: str | None,
    out_file: Path,
    chunk_rows: int,
    force: bool,
) -> None:
    """Predict every row of a CSV (streamed), from the fit's initial state.

    Writes the input's columns plus ``prediction`` and ``prediction_std`` (one
    standard deviation, including measurement noise) [output units] and
    ``outside_input_range`` (1 where the input lies beyond the fit's input
    range, else 0; the range is ``input_range`` of its model.json: the
    training inputs +- 1 % unless the fit was given --input-range). Such rows
    are extrapolated as saturated (every hysteron switched) plus the linear
    term, with a warning giving their count; their ``prediction_std`` widens
    with the linear term's uncertainty only, not with any doubt about the
    saturation. A missing folder of OUT is created.
    """
    # the refusals --force does not lift come first, so that the first is true
    check_out_file(out_file, True, {"--input": data}, csv_columns=COLUMNS)
    if out_file.suffix.lower() != ".csv":
        raise click.ClickException(
            f"--out {out_file}: expected a .csv file name (the output is CSV text)."
        )
    check_out_file(out_file, force, {"--input": data}, csv_columns=COLUMNS)
    try:
        spec, config = _load(fit_dir)
    except ValueError as err:
        raise click.ClickException(f"cannot load a fit from {fit_dir}: {err}") from err
    in_col = config.get("input_column", DEFAULT_INPUT_COLUMN)
    try:
        header, chunks = iter_magnet_csv(
            data,
            in_col,
            chunk_rows=chunk_rows,
            drop=COLUMNS,
            time_column=time_column or DEFAULT_TIME_COLUMN,
        )
    except (OSError, ValueError) as err:
        raise click.ClickException(str(err)) from err
    check_time_column(data, header, time_column)
    clash = [c for c in COLUMNS if c in header]
    if clash and not force:
        raise click.ClickException(
            f"{data} already has column(s) {clash}; pass --force to replace them "
            "in the output (the input file is never changed)."
        )
    out_header = [c for c in header if c not in clash] + list(COLUMNS)
    stats = {"rows": 0, "finite": True, "min": math.inf, "max": -math.inf}
    outside = {"rows": 0, "first": 0}  # count, first data row (0: none)

    def write(path: Path) -> None:
        pending: list[list[str]] = []

        def inputs():
            first_row = 1  # data row of the chunk's first row (1: below the header)
            for rows, x in chunks:
                check_magnitude(data, in_col, x, first_row)
                first_row += len(rows)
                pending.append(rows)
                stats["min"] = min(stats["min"], float(x.min()))
                stats["max"] = max(stats["max"], float(x.max()))
                yield x

        def texts():
            predictor = StreamPredictor(spec)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", InputRangeWarning)  # noted below
                # CSV parsing (next chunk) overlaps the model (this chunk):
                # numpy and scipy release the GIL
                for x in read_ahead(inputs()):
                    pred, std = predictor(x)
                    flag = outside_input_range(x, spec.input_range)
                    n_out = int(flag.sum())
                    if n_out and not outside["first"]:
                        outside["first"] = stats["rows"] + int(flag.argmax()) + 1
                    outside["rows"] += n_out
                    rows = pending.pop(0)
                    stats["rows"] += len(rows)
                    stats["finite"] &= bool(np.isfinite(pred).all())
                    if std is None:
                        std = np.full_like(pred, math.nan)
                    # 15 significant digits (all a float64 keeps in decimal);
                    # the std (float32 sums) to 7; the flag as 0 or 1
                    yield rows, [pred, std, flag]

        with open(path, "w", newline="", encoding="utf-8") as f:
            csv.writer(f, lineterminator="\n").writerow(out_header)
            for rows, columns in read_ahead(texts()):
                f.write(append_columns(rows, columns, [15, 7, 1]))

    try:
        # as fit and gp-fit create their --out folder
        out_file.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        if os_condition(err) is not None:  # read-only, no space...
            raise os_error(err, out_file) from err
        raise click.ClickException(
            f"--out {out_file}: cannot create its folder {out_file.parent}: {err}"
        ) from err
    try:
        atomic_write(out_file, write)
    except ValueError as err:
        raise click.ClickException(str(err)) from err
    except OSError as err:  # a read-only folder, a full disk
        raise os_error(err, out_file) from err
    if outside["rows"]:
        lo, hi = spec.input_range
        beyond = max(lo - stats["min"], stats["max"] - hi, 0.0)
        click.echo(
            f"warning: {outside['rows']} of {stats['rows']} rows (the first: data "
            f"row {outside['first']}) have {in_col} outside the fit's input range "
            f"[{lo:.6g}, {hi:.6g}] {in_col}, by up to {beyond:.4g} {in_col} "
            f"({100 * beyond / (hi - lo):.3g} % of the range); {OUTSIDE} = 1 "
            "there. They are extrapolated as saturated (every hysteron switched) "
            f"plus the linear term; their {PREDICTION_STD} widens with the linear "
            "term's uncertainty only, not with any doubt about the saturation.",
            err=True,
        )
    click.echo(
        f"predicted {stats['rows']} rows ({', '.join(COLUMNS)}); wrote {out_file}"
    )
    if not stats["finite"]:
        raise click.ClickException("predictions contain non-finite values.")


_DONE = object()
T = TypeVar("T")


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


def _load(fit_dir: Path) -> tuple[StreamSpec, dict]:
    """The fit's stream spec and settings: from ``stream.npz`` without torch, or
    (a folder saved before that file existed) from the model with torch."""
    try:
        return load_stream_fit(fit_dir)
    except FileNotFoundError:
        pass
    model, band, config = hysteresis.load_fit(fit_dir)
    spec = band.stream_spec(model) if band is not None else model.stream_spec()
    return spec, config
