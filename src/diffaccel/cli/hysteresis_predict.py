"""``diffaccel hysteresis predict``: predict a long magnet history, streamed.

Imports only what predicting needs: numpy, the streaming prediction of a CSV
(:mod:`diffaccel.hysteresis.stream_csv`) and the CSV streaming of
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

from pathlib import Path

import click

from diffaccel.cli.hysteresis import (
    check_magnitude,
    check_time_column,
    time_column_option,
)
from diffaccel.cli.output import check_out_file, os_error
from diffaccel.data import (
    DEFAULT_INPUT_COLUMN,
    DEFAULT_TIME_COLUMN,
    atomic_write,
    iter_magnet_csv,
)
from diffaccel.data.atomic import os_condition
from diffaccel.hysteresis.stream_csv import (
    COLUMNS,
    StreamStats,
    outside_warning,
    read_ahead,
    write_predictions,
)
from diffaccel.hysteresis.stream_csv import stream_fit as _load  # tests replace it

__all__ = ["predict_command", "read_ahead"]

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
    warning = outside_warning(stats, spec.input_range, in_col)
    if warning:
        click.echo(f"warning: {warning}", err=True)
    click.echo(f"predicted {stats.rows} rows ({', '.join(COLUMNS)}); wrote {out_file}")
    if not stats.finite:
        raise click.ClickException("predictions contain non-finite values.")
