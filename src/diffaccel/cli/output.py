"""Result folders, output files and path types of CLI commands; library errors
as one line."""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import click

from diffaccel.data import (
    OptionError,
    ResultFolder,
    ResultFolderError,
    owned_files,
    result_folder,
)
from diffaccel.data.atomic import os_condition, os_error_text

__all__ = [
    "IN_DIR",
    "IN_FILE",
    "OUT_DIR",
    "OUT_FILE",
    "SHOW_DEFAULTS",
    "check_out_file",
    "click_errors",
    "os_error",
    "output_folder",
]

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


def check_out_file(
    out: Path,
    force: bool,
    inputs: dict[str, Path | None],
    option: str = "--out",
    csv_columns: Sequence[str] = (),
) -> None:
    """:func:`diffaccel.data.owned_files.check_out_file`, its refusal as one line."""
    try:
        owned_files.check_out_file(out, force, inputs, option, csv_columns)
    except owned_files.OutputFileError as err:
        raise click.ClickException(str(err)) from err


def os_error(
    err: BaseException, path: Path, doing: str = "write"
) -> click.ClickException:
    """:func:`diffaccel.data.atomic.os_error_text` as a click error."""
    return click.ClickException(os_error_text(err, path, doing))
