"""``diffaccel hysteresis``: the command group of Preisach hysteresis models.

Its subcommands live in their own modules (``hysteresis_fit``,
``hysteresis_predict``, ``hysteresis_gp``) and are imported when they run (see
``cli/main.py``), so that ``hysteresis predict`` does not import the plotting
(matplotlib) that ``fit`` needs or the GP parts (gpytorch, botorch) of
``gp-fit``. The checks of options that several subcommands share live here.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import click
import numpy as np

from diffaccel.cli.output import click_errors
from diffaccel.data import DEFAULT_RUN_COLUMN, DEFAULT_TIME_COLUMN, magnet_stream

__all__ = [
    "check_finite",
    "check_input_range",
    "check_magnitude",
    "check_time_column",
    "checked",
    "hysteresis",
    "time_column_option",
]

F = TypeVar("F", bound=Callable)


#: Largest |value| of a measured series, as the library's fits take them.
MAX_MAGNITUDE = magnet_stream.MAX_MAGNITUDE


@click.group("hysteresis")
def hysteresis() -> None:
    """Preisach hysteresis models of magnets: fit and predict."""


def checked(
    check: Callable[[Any], Any],
) -> Callable[[click.Context, click.Parameter, Any], Any]:
    """A click callback: ``check(value)``, its ``ValueError`` as the option's error."""

    def callback(ctx: click.Context, param: click.Parameter, value: Any) -> Any:
        try:
            return check(value)
        except ValueError as err:
            raise click.BadParameter(str(err)) from err

    return callback


def check_finite(
    ctx: click.Context, param: click.Parameter, value: float | None
) -> float | None:
    """Click callback: refuse a NaN or infinite number (the option is named)."""
    if value is not None and not math.isfinite(value):
        raise click.BadParameter(f"expected a finite number; got {value}.")
    return value


def check_input_range(
    ctx: click.Context, param: click.Parameter, value: tuple[float, float] | None
) -> tuple[float, float] | None:
    """Click callback: ``--input-range LO HI`` finite, with ``LO < HI``."""
    if value is None:
        return None
    lo, hi = value
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise click.BadParameter(f"expected finite numbers; got {lo} {hi}.")
    if not lo < hi:
        raise click.BadParameter(f"expected LO < HI; got {lo} {hi}.")
    if not math.isfinite(hi - lo):
        raise click.BadParameter(
            f"HI - LO overflows (got {lo} {hi}); expected a range of finite width."
        )
    return value


def check_magnitude(
    data: Path, column: str, values: np.ndarray, first_row: int = 1
) -> None:
    """:func:`diffaccel.data.magnet_stream.check_magnitude` as a click error."""
    with click_errors():
        magnet_stream.check_magnitude(data, column, values, first_row)


def time_column_option(command: F) -> F:
    """The ``--time-column NAME`` option of the commands reading magnet CSV files."""
    return click.option(
        "--time-column",
        default=None,
        metavar="NAME",
        help="Column of measurement times [s, or any increasing unit]; they must "
        f"increase within each run (column {DEFAULT_RUN_COLUMN!r}, where the "
        "time may restart), so that shuffled or repeated rows are refused. "
        f"Default: {DEFAULT_TIME_COLUMN!r} if the file has it; without a time "
        "column the row order cannot be checked.",
    )(command)


def check_time_column(data: Path, header: list[str], name: str | None) -> None:
    """:func:`diffaccel.data.magnet_stream.check_time_column` as a usage error."""
    with click_errors():
        magnet_stream.check_time_column(data, header, name)
