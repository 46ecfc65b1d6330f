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
from typing import TypeVar

import click
import numpy as np

from diffaccel.data import DEFAULT_RUN_COLUMN, DEFAULT_TIME_COLUMN

__all__ = [
    "check_finite",
    "check_input_range",
    "check_magnitude",
    "check_time_column",
    "hysteresis",
    "time_column_option",
]

F = TypeVar("F", bound=Callable)


#: The library's limit (``diffaccel.hysteresis.fit.MAX_MAGNITUDE``), kept here so
#: that ``hysteresis predict`` streams without importing torch.
MAX_MAGNITUDE = 1e100


@click.group("hysteresis")
def hysteresis() -> None:
    """Preisach hysteresis models of magnets: fit and predict."""


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
    """Refuse a value beyond ``MAX_MAGNITUDE``, naming the file, column and data row.

    Args:
        data: The CSV file the values come from.
        column: Their column name.
        values: The column's values (a numpy array or a CPU tensor), shape ``(T,)``.
        first_row: Data row (1 = the first row below the header) of ``values[0]``.

    Raises:
        click.ClickException: at the first value beyond ``MAX_MAGNITUDE``.
    """
    v = np.asarray(values, dtype=np.float64)
    big = np.flatnonzero(np.abs(v) > MAX_MAGNITUDE)
    if big.size:
        i = int(big[0])
        raise click.ClickException(
            f"{data}: column {column!r}, data row {first_row + i}: "
            f"{float(v[i]):.6g} is beyond {MAX_MAGNITUDE:.0e} in magnitude, "
            "not a measurement (a unit or parsing error?)."
        )


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
    """Refuse a ``--time-column`` that DATA does not have (the default may be absent).

    Raises:
        click.BadParameter: naming the file, the column and the file's columns.
    """
    if name is not None and name not in header:
        raise click.BadParameter(
            f"{data} has no column {name!r}; columns are {header}.",
            param_hint="--time-column",
        )
