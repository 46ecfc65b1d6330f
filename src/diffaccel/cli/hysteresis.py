"""``diffaccel hysteresis``: the command group of Preisach hysteresis models.

Its subcommands live in their own modules (``hysteresis_fit``,
``hysteresis_predict``, ``hysteresis_gp``) and are imported when they run (see
``cli/main.py``), so that ``hysteresis predict`` does not import the plotting
(matplotlib) that ``fit`` needs or the GP parts (gpytorch, botorch) of
``gp-fit``. The checks of options that several subcommands share live here.
"""

from __future__ import annotations

import math

import click

__all__ = [
    "check_finite",
    "check_input_range",
    "hysteresis",
]


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
