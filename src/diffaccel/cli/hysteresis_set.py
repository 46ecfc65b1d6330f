"""``diffaccel hysteresis set``: the input that gives a target output after a history.

numpy only, as ``hysteresis predict``: the fit's ``stream.npz`` numbers and
:func:`diffaccel.hysteresis.plan_setpoint`, whose answer is the streamed
prediction ``predict`` makes after the same history and the returned inputs.
"""

from __future__ import annotations

import json
from pathlib import Path

import click

from diffaccel.cli.hysteresis import (
    check_finite,
    check_input_range,
    time_column_option,
)
from diffaccel.cli.output import IN_DIR, IN_FILE, click_errors, echo_lines
from diffaccel.data import DEFAULT_INPUT_COLUMN, DEFAULT_TIME_COLUMN, iter_magnet_csv
from diffaccel.data.magnet_stream import check_time_column
from diffaccel.hysteresis import field_for_k1
from diffaccel.hysteresis.setpoint_report import (
    check_limits,
    plan_history_setpoint,
    setpoint_lines,
    setpoint_summary,
)
from diffaccel.hysteresis.stream_csv import stream_fit

__all__ = ["set_command"]


@click.command("set")
@click.argument("fit_dir", type=IN_DIR)
@click.option(
    "--history",
    "data",
    type=IN_FILE,
    required=True,
    help="CSV with the input column of the fit: every input applied since the "
    "fit's initial state, in time order.",
)
@time_column_option
@click.option(
    "--target",
    type=float,
    required=True,
    callback=check_finite,
    help="Target output [units of the fit's output column], or k1 [1/m^2] with --k1.",
)
@click.option(
    "--k1",
    "is_k1",
    is_flag=True,
    help="TARGET is a quadrupole strength k1 [1/m^2]; the output is the "
    "integrated gradient G [T] = k1 * LENGTH * p0c / c (needs --length, --p0c).",
)
@click.option(
    "--length",
    type=float,
    default=None,
    callback=check_finite,
    help="Magnetic length [m] for --k1.",
)
@click.option(
    "--p0c",
    type=float,
    default=None,
    callback=check_finite,
    help="Reference momentum times c [eV] for --k1 (charge 1 e).",
)
@click.option(
    "--limits",
    type=(float, float),
    default=None,
    callback=check_input_range,
    help="Allowed inputs LO HI [input units] (e.g. the power supply's); "
    "default: the fit's input range. Degaussing cycles go to these limits.",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def set_command(
    fit_dir: Path,
    data: Path,
    time_column: str | None,
    target: float,
    is_k1: bool,
    length: float | None,
    p0c: float | None,
    limits: tuple[float, float] | None,
    as_json: bool,
) -> None:
    """The input that brings a fitted magnet to TARGET after its history.

    Prints the input to set, the approach (from below or from above; first a
    degaussing cycle to the input limits, or an overshoot that turns back,
    where one step from the present state cannot reach the target: exact
    relays switch whole hysterons, so some outputs lie in a jump), the
    predicted output there with its band (1 std), and the outputs reachable
    within the limits. ``hysteresis predict`` on the history followed by the
    printed inputs gives TARGET there within 1e-6 of the fit's output range.
    """
    if is_k1:
        missing = [o for o, v in (("--length", length), ("--p0c", p0c)) if v is None]
        if missing:
            raise click.UsageError(f"--k1 needs {' and '.join(missing)}.")
        try:
            field = field_for_k1(target, length, p0c)
        except ValueError as err:
            raise click.ClickException(f"--k1 calibration: {err}") from err
    else:
        given = [o for o, v in (("--length", length), ("--p0c", p0c)) if v is not None]
        if given:
            raise click.UsageError(f"{' and '.join(given)} only go with --k1.")
        field = target
    try:
        spec, config = stream_fit(fit_dir)
    except ValueError as err:
        raise click.ClickException(f"cannot load a fit from {fit_dir}: {err}") from err
    in_col = config.get("input_column", DEFAULT_INPUT_COLUMN)
    out_col = config.get("output_column", "output")
    with click_errors(OSError, ValueError):
        check_limits(spec, limits, in_col)
        header, chunks = iter_magnet_csv(
            data, in_col, time_column=time_column or DEFAULT_TIME_COLUMN
        )
        check_time_column(data, header, time_column)
    # a k1 target: its calibration; an output target: none
    k1 = {"length": length, "p0c": p0c} if is_k1 else {}
    with click_errors():
        plan, notes = plan_history_setpoint(
            spec,
            data,
            chunks,
            input_column=in_col,
            output_column=out_col,
            target=target,
            output=field,
            limits=limits,
            **k1,
        )
    if as_json:
        summary = setpoint_summary(
            plan, fit=str(fit_dir), history=str(data), input_column=in_col,
            output_column=out_col, target=target, output=field,
            output_scale=spec.output_scale, notes=notes, **k1,
        )  # fmt: skip
        click.echo(json.dumps(summary, allow_nan=False))
        return
    echo_lines([f"note: {note}" for note in notes], err=True)
    lines = setpoint_lines(
        plan, input_column=in_col, output_column=out_col,
        k1=target if is_k1 else None,
    )  # fmt: skip
    echo_lines(lines)
