"""Options and output helpers that several commands share."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TypeVar

import click

__all__ = ["echo_lines", "echo_warnings", "seed_option"]

F = TypeVar("F", bound=Callable)


def seed_option(command: F) -> F:
    """The ``--seed`` option (an integer, default 0)."""
    return click.option(
        "--seed",
        type=int,
        default=0,
        show_default=True,
        help="Random seed: the same seed gives the same numbers.",
    )(command)


def echo_lines(lines: Sequence[str], err: bool = False) -> None:
    """Each of ``lines`` on stdout (``err``: on stderr)."""
    for line in lines:
        click.echo(line, err=err)


def echo_warnings(warnings: Sequence[str]) -> None:
    """Each warning on stderr as ``warning: ...``."""
    echo_lines([f"warning: {w}" for w in warnings], err=True)
