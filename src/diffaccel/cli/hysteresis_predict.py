"""``diffaccel hysteresis predict``: predict a long magnet history, streamed.

Imports only what predicting needs: numpy, the streaming prediction of a CSV
(:mod:`diffaccel.hysteresis.stream_csv`) and the CSV streaming of
:mod:`diffaccel.data.magnet_stream`; no torch (~2 s of start-up), no plotting,
no GP libraries (see ``benchmarks/preisach_stream.py``). A fit folder saved
before ``stream.npz`` existed is read with torch instead. The command's help
says how rows beyond the fit's input range are predicted
(:mod:`diffaccel.hysteresis.band` derives their band).
"""

from __future__ import annotations

from pathlib import Path

import click

from diffaccel.cli.hysteresis import time_column_option
from diffaccel.cli.output import (
    IN_DIR,
    IN_FILE,
    OUT_FILE,
    SHOW_DEFAULTS,
    click_errors,
    force_option,
    out_option,
)
from diffaccel.data import DEFAULT_INPUT_COLUMN
from diffaccel.hysteresis.stream_csv import (
    COLUMNS,
    check_csv_output,
    outside_warning,
    predict_csv,
    read_ahead,
)
from diffaccel.hysteresis.stream_csv import stream_fit as _load  # tests replace it

__all__ = ["predict_command", "read_ahead"]

CHUNK_ROWS = 20_000
# cap of --chunk-rows: a chunk is held in memory (10^9 rows: tens of GB)
MAX_CHUNK_ROWS = 10**9


@click.command("predict", context_settings=SHOW_DEFAULTS)
@click.argument("fit_dir", type=IN_DIR)
@click.option(
    "--input",
    "data",
    type=IN_FILE,
    required=True,
    help="CSV with the input column of the fit, rows in time order (any length).",
)
@time_column_option
@out_option(
    OUT_FILE,
    "CSV file to write: the input's columns plus the predicted ones.",
    "out_file",
)
@click.option(
    "--chunk-rows",
    type=click.IntRange(min=1, max=MAX_CHUNK_ROWS),
    default=CHUNK_ROWS,
    help="Rows read, predicted and written at a time (memory grows with it).",
)
@force_option(
    f"Overwrite OUT if it exists, and replace the columns {', '.join(COLUMNS)} "
    "of the input."
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
    with click_errors():
        check_csv_output(out_file, data, force)
    try:
        spec, config = _load(fit_dir)
    except ValueError as err:
        raise click.ClickException(f"cannot load a fit from {fit_dir}: {err}") from err
    with click_errors(OSError, ValueError):
        stats = predict_csv(
            spec,
            config,
            data,
            out_file,
            chunk_rows=chunk_rows,
            time_column=time_column,
            force=force,
        )
    in_col = config.get("input_column", DEFAULT_INPUT_COLUMN)
    warning = outside_warning(stats, spec.input_range, in_col)
    if warning:
        click.echo(f"warning: {warning}", err=True)
    click.echo(f"predicted {stats.rows} rows ({', '.join(COLUMNS)}); wrote {out_file}")
    if not stats.finite:
        raise click.ClickException("predictions contain non-finite values.")
