"""Options and checks that several commands share, each error as one line."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar

import click
import torch

from diffaccel.data import FormatError, MultiScanDataset, read_scans
from diffaccel.reconstruction import ReconstructionConfig, as_scans
from diffaccel.reconstruction.runtime import (
    init_distributed,
    memory_shortfall,
    resolve_device,
)
from diffaccel.reconstruction.runtime import shared_refusal as _shared_refusal

__all__ = [
    "check_device",
    "check_memory",
    "echo_lines",
    "echo_warnings",
    "join_distributed",
    "read_dataset",
    "seed_option",
    "shared_refusal",
]

F = TypeVar("F", bound=Callable)


def seed_option(command: F) -> F:
    """The ``--seed`` option (an integer, default 0)."""
    return click.option("--seed", type=int, default=0, show_default=True)(command)


def echo_lines(lines: Sequence[str], err: bool = False) -> None:
    """Each of ``lines`` on stdout (``err``: on stderr)."""
    for line in lines:
        click.echo(line, err=err)


def echo_warnings(warnings: Sequence[str]) -> None:
    """Each warning on stderr as ``warning: ...``."""
    echo_lines([f"warning: {w}" for w in warnings], err=True)


def check_device(device: str) -> torch.device:
    """``--device`` as a torch device that exists here (one-line error otherwise)."""
    try:
        return resolve_device(device)
    except ValueError as err:
        raise click.BadParameter(str(err), param_hint="--device") from err


def check_memory(config: ReconstructionConfig, n_images: int) -> None:
    """Refuse (one line, ``--particles``) a run of ``config`` that cannot fit in RAM.

    ``n_images``: training images (settings over all scans).
    """
    problem = memory_shortfall(config, n_images)
    if problem is not None:
        raise click.BadParameter(problem, param_hint="--particles")


def read_dataset(path: Path) -> MultiScanDataset:
    """The scans of a quad-scan file.

    Raises:
        click.ClickException: ``cannot read PATH: ...`` naming the problem.
    """
    try:
        return as_scans(read_scans(path))
    except (FormatError, OSError) as err:
        text = str(err)  # reader errors already read "PATH: field: problem"
        if not text.startswith(str(path)):
            text = f"{path}: {text}"
        raise click.ClickException(f"cannot read {text}") from err


def join_distributed(device: str) -> str:
    """Join the process group that torchrun describes; this process's device."""
    try:
        return init_distributed(device)
    except ValueError as err:
        raise click.ClickException(str(err)) from err


def shared_refusal(target: Any, distributed: bool) -> Any:
    """Enter ``target`` (process 0's result folder); every process learns a refusal.

    See :func:`~diffaccel.reconstruction.runtime.shared_refusal`; the others
    raise ``process 0 stopped: <its one-line error>``.
    """
    return _shared_refusal(
        target,
        distributed,
        refusal=click.ClickException,
        text=lambda err: err.format_message(),
        stopped=lambda text: click.ClickException(f"process 0 stopped: {text}"),
    )
