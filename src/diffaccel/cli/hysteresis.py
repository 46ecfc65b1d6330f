"""``diffaccel hysteresis``: the command group of Preisach hysteresis models.

Its subcommands live in their own modules (``hysteresis_fit``,
``hysteresis_predict``, ``hysteresis_gp``) and are imported when they run (see
``cli/main.py``), so that ``hysteresis predict`` does not import the plotting
(matplotlib) that ``fit`` needs or the GP parts (gpytorch, botorch) of
``gp-fit``.
"""

from __future__ import annotations

import click

__all__ = ["hysteresis"]


@click.group("hysteresis")
def hysteresis() -> None:
    """Preisach hysteresis models of magnets: fit and predict."""
