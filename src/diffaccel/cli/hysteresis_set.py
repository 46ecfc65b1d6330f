"""``diffaccel hysteresis set``: the input that gives a target output after a history.

numpy only, as ``hysteresis predict``: the fit's ``stream.npz`` numbers and
:func:`diffaccel.hysteresis.plan_setpoint`, whose answer is the streamed
prediction ``predict`` makes after the same history and the returned inputs.
"""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import click

from diffaccel.cli.hysteresis import (
    check_finite,
    check_input_range,
    check_magnitude,
    check_time_column,
    time_column_option,
)
from diffaccel.cli.hysteresis_predict import _load
from diffaccel.data import DEFAULT_INPUT_COLUMN, DEFAULT_TIME_COLUMN, iter_magnet_csv
from diffaccel.hysteresis import (
    InputRangeWarning,
    UnreachableTargetError,
    field_for_k1,
    plan_setpoint,
)

__all__ = ["set_command"]

#: largest |error| of a set point accepted, as a fraction of the output range
ACCEPT = 1e-6


def _g(v: float) -> str:
    """A number to 12 significant digits (set again, it gives the same output)."""
    return f"{v:.12g}"


@click.command("set")
@click.argument(
    "fit_dir", type=click.Path(exists=True, file_okay=False, path_type=Path)
)
@click.option(
    "--history",
    "data",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
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
        spec, config = _load(fit_dir)
    except ValueError as err:
        raise click.ClickException(f"cannot load a fit from {fit_dir}: {err}") from err
    in_col = config.get("input_column", DEFAULT_INPUT_COLUMN)
    out_col = config.get("output_column", "output")
    r_lo, r_hi = spec.input_range
    if limits is not None and not (limits[0] < r_hi and limits[1] > r_lo):
        raise click.BadParameter(
            f"{limits[0]:g} {limits[1]:g} leave no {in_col} inside the fit's input "
            f"range [{r_lo:.6g}, {r_hi:.6g}].",
            param_hint="--limits",
        )
    try:
        header, chunks = iter_magnet_csv(
            data, in_col, time_column=time_column or DEFAULT_TIME_COLUMN
        )
    except (OSError, ValueError) as err:
        raise click.ClickException(str(err)) from err
    check_time_column(data, header, time_column)

    def inputs():
        first_row = 1
        for rows, x in chunks:
            check_magnitude(data, in_col, x, first_row)
            first_row += len(rows)
            yield x

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", InputRangeWarning)
        try:
            plan = plan_setpoint(spec, inputs(), field, limits)
        except UnreachableTargetError as err:
            lo, hi = err.reachable
            what = f"{out_col} {_g(target)}"
            span = f"{out_col} {lo:.6g} .. {hi:.6g}"
            if is_k1:
                per = field / target if target else field_for_k1(1.0, length, p0c)
                what = f"k1 {_g(target)} 1/m^2 ({out_col} {field:.6g})"
                span = f"k1 {lo / per:.6g} .. {hi / per:.6g} 1/m^2 ({span})"
            raise click.ClickException(
                f"{what} cannot be reached: the fit reaches {span} within "
                f"{in_col} {err.limits[0]:.6g} .. {err.limits[1]:.6g} after this "
                "history."
            ) from err
        except ValueError as err:
            raise click.ClickException(f"{data}: {err}") from err
    notes = sorted({str(w.message) for w in caught if w.category is InputRangeWarning})
    span = spec.output_scale
    if abs(plan.error) > ACCEPT * abs(span):
        raise click.ClickException(
            f"{out_col} {_g(field)} lies in a jump of the fitted model (a row of "
            f"hysterons switching) for every approach tried; nearest: {in_col} "
            f"{_g(plan.input)} gives {plan.output:.6g}."
        )
    if as_json:
        summary = {
            "fit": str(fit_dir),
            "history": str(data),
            "input_column": in_col,
            "output_column": out_col,
            "target": target,
            "target_kind": "k1" if is_k1 else "output",
            "target_output": field,
            "input": plan.input,
            "approach": plan.approach,
            "kind": plan.kind,
            "cycle": list(plan.cycle),
            "sequence": list(plan.sequence),
            "predicted_output": plan.output,
            "predicted_std": plan.std,
            "error": plan.error,
            "error_fraction_of_range": plan.error / span,
            "reachable": list(plan.reachable),
            "limits": list(plan.limits),
            "present_input": plan.present_input,
            "present_output": plan.present_output,
            "notes": notes,
        }
        if is_k1:
            summary.update(length=length, p0c=p0c)
        click.echo(json.dumps(summary, allow_nan=False))
        return
    for note in notes:
        click.echo(f"note: {note}", err=True)
    if plan.kind == "cycle":
        first = (
            f"first a degaussing cycle: {in_col} {_g(plan.cycle[0])}, then "
            f"{_g(plan.cycle[1])}; then "
        )
    elif plan.kind == "overshoot":
        steps = ", then ".join(_g(v) for v in plan.cycle)
        first = f"first {in_col} {steps} (overshoot); then "
    else:
        first = ""
    std = "" if plan.std is None or math.isnan(plan.std) else f" +- {plan.std:.4g}"
    want = f"k1 {_g(target)} 1/m^2: " if is_k1 else ""
    click.echo(
        f"{first}set {in_col} to {_g(plan.input)} {plan.approach} (present "
        f"{in_col} {_g(plan.present_input)}, {out_col} {plan.present_output:.6g}): "
        f"{want}{out_col} {plan.output:.8g}{std} (1 std) predicted there"
    )
    lo, hi = plan.reachable
    click.echo(
        f"reachable {out_col} {lo:.6g} .. {hi:.6g} within {in_col} "
        f"{plan.limits[0]:.6g} .. {plan.limits[1]:.6g}; inputs to apply: "
        f"{', '.join(_g(v) for v in plan.sequence)}"
    )
