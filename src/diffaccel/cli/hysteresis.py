"""``diffaccel hysteresis``: the command group of Preisach hysteresis models.

Its subcommands live in their own modules (``hysteresis_fit``,
``hysteresis_predict``, ``hysteresis_gp``) and are imported when they run (see
``cli/main.py``), so that ``hysteresis predict`` does not import the plotting
(matplotlib) that ``fit`` needs or the GP parts (gpytorch, botorch) of
``gp-fit``. The checks of options that several subcommands share live here.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

import click

from diffaccel.cli.main import SUBCOMMANDS, LazyGroup
from diffaccel.data import DEFAULT_RUN_COLUMN, DEFAULT_TIME_COLUMN, magnet_stream

__all__ = [
    "check_finite",
    "check_input_range",
    "checked",
    "hysteresis",
    "time_column_option",
]

F = TypeVar("F", bound=Callable)


#: Largest |value| of a measured series, as the library's fits take them.
MAX_MAGNITUDE = magnet_stream.MAX_MAGNITUDE


@click.group("hysteresis", cls=LazyGroup, table=SUBCOMMANDS["hysteresis"])
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


#: Click callbacks: a finite number; an input range LO < HI of finite numbers.
check_finite = checked(magnet_stream.check_finite)
check_input_range = checked(magnet_stream.check_input_range)


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
