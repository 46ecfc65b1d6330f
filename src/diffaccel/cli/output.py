"""What several commands share: path types, the ``--out``, ``--force`` and
``--seed`` options, result folders, library errors as one line, printed lines."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import TypeVar

import click

from diffaccel.data import (
    OptionError,
    ResultFolder,
    ResultFolderError,
    owned_files,
    result_folder,
)
from diffaccel.data.atomic import os_condition

__all__ = [
    "IN_DIR",
    "IN_FILE",
    "OUT_DIR",
    "OUT_FILE",
    "SHOW_DEFAULTS",
    "check_out_file",
    "click_errors",
    "echo_lines",
    "echo_warnings",
    "force_option",
    "out_option",
    "output_folder",
    "seed_option",
]

F = TypeVar("F", bound=Callable)

#: An existing file an argument or option reads.
IN_FILE = click.Path(exists=True, dir_okay=False, path_type=Path)
#: An existing folder (a fit, a reconstruction) a command reads.
IN_DIR = click.Path(exists=True, file_okay=False, path_type=Path)
#: A file a command writes (not a folder).
OUT_FILE = click.Path(dir_okay=False, path_type=Path)
#: A folder a command writes its result into (not a file).
OUT_DIR = click.Path(file_okay=False, path_type=Path)
#: ``context_settings`` of the commands: every option's default in ``--help``.
SHOW_DEFAULTS = {"show_default": True}


def out_option(
    path_type: click.Path, help: str, dest: str | None = None, required: bool = True
) -> Callable[[F], F]:
    """The ``--out`` option of a command: where it writes (``dest``: its parameter)."""
    decls = ("--out",) if dest is None else ("--out", dest)
    return click.option(*decls, type=path_type, required=required, help=help)


def force_option(help: str) -> Callable[[F], F]:
    """The ``--force`` flag: replace what ``--out`` already holds, as ``help`` says."""
    return click.option("--force", is_flag=True, help=help)


def seed_option(command: F) -> F:
    """The ``--seed`` option (an integer, default 0)."""
    return click.option(
        "--seed",
        type=int,
        default=0,
        show_default=True,
        help="Random seed: the same seed gives the same numbers.",
    )(command)


@contextmanager
def click_errors(*errors: type[Exception], prefix: str = "") -> Iterator[None]:
    """Library refusals inside the block as one-line click errors.

    An :class:`~diffaccel.data.OptionError` becomes a usage error naming its
    option; the ``errors`` (default: ``ValueError``) a ``ClickException`` with
    their message after ``prefix``.
    """
    caught = errors or (ValueError,)
    try:
        yield
    except OptionError as err:
        raise click.BadParameter(str(err), param_hint=err.option) from err
    except caught as err:
        raise click.ClickException(f"{prefix}{err}") from err


@contextmanager
def output_folder(
    out: Path,
    command: str,
    *,
    force: bool,
    resume: bool = False,
    keep_partial: bool = False,
    owned: Iterable[str] = (),
    inputs: Iterable[Path] = (),
) -> Iterator[ResultFolder]:
    """:func:`diffaccel.data.result_folder` with its errors as one-line click errors.

    An ``OSError`` while the results are written (disk full, permissions) is
    reported the same way; the earlier result in ``out`` stays as it was.
    """
    try:
        with result_folder(
            out,
            command=command,
            force=force,
            resume=resume,
            keep_partial=keep_partial,
            owned=owned,
            inputs=inputs,
        ) as folder:
            yield folder
    except ResultFolderError as err:
        raise click.ClickException(str(err)) from err
    except OSError as err:
        raise click.ClickException(
            f"writing the results for {out} failed: {os_condition(err) or err}; "
            f"{out} was left as it was."
        ) from err


def check_out_file(out: Path, force: bool, inputs: dict[str, Path | None]) -> None:
    """:func:`diffaccel.data.owned_files.check_out_file`, its refusal as one line."""
    try:
        owned_files.check_out_file(out, force, inputs)
    except owned_files.OutputFileError as err:
        raise click.ClickException(str(err)) from err


def echo_lines(lines: Sequence[str], err: bool = False) -> None:
    """Each of ``lines`` on stdout (``err``: on stderr)."""
    for line in lines:
        click.echo(line, err=err)


def echo_warnings(warnings: Sequence[str]) -> None:
    """Each warning on stderr as ``warning: ...``."""
    echo_lines([f"warning: {w}" for w in warnings], err=True)
