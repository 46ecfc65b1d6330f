"""Result folders of CLI commands: all-or-nothing, locked, errors as one line."""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import click

from diffaccel.data import (
    ResultFolder,
    ResultFolderError,
    result_folder,
)
from diffaccel.data.atomic import os_condition
from diffaccel.data.owned_files import written_by_diffaccel
from diffaccel.data.result_folder import MARKER

__all__ = [
    "check_out_file",
    "os_error",
    "output_folder",
]


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
    """Refuse an output file that would replace something the user gave.

    ``out`` may replace an existing file only with ``force`` and only if
    diffaccel wrote it (:func:`~diffaccel.data.owned_files.written_by_diffaccel`;
    ``csv_columns``: the columns a CSV output ends with), never one of the
    ``inputs`` (``{"--dataset": path}``; None entries are skipped), and is never
    written into a diffaccel result folder (a fit, a reconstruction), ``force``
    or not: the command could destroy the result it reads, and a foreign file
    there makes the folder refuse a later ``--force``. ``option`` names ``out``
    in the messages.

    Raises:
        click.ClickException: naming the option and the file.
    """
    for name, path in inputs.items():
        if path is not None and out.resolve() == path.resolve():
            raise click.ClickException(
                f"{option} {out} is the {name} file; write the output elsewhere."
            )
    if (out.resolve().parent / MARKER).exists():
        # a result folder holds what its command wrote, nothing else: a new
        # file there would make a later --force refuse the folder as foreign
        raise click.ClickException(
            f"{option} {out} is inside the result folder {out.parent}; write the "
            "output elsewhere."
        )
    if out.exists() and not force:
        raise click.ClickException(f"{out} exists; pass --force to overwrite it")
    try:
        ours = not out.exists() or written_by_diffaccel(out, csv_columns=csv_columns)
    except OSError as err:  # locked, no permission
        raise os_error(err, out, doing="read") from err
    if not ours:
        raise click.ClickException(
            f"{out} exists and was not written by diffaccel; --force "
            "replaces only diffaccel's own output files: move it or choose "
            "another name."
        )


def os_error(
    err: BaseException, path: Path, doing: str = "write"
) -> click.ClickException:
    """A one-line error for an OS condition while reading or writing ``path``.

    Names the condition (:func:`os_condition`) and what to do, e.g. ``cannot
    write out.h5: read-only file system (the folder out/ cannot be written
    here); choose another --out``; other errors keep their own text.
    """
    condition = os_condition(err)
    if condition is None:
        return click.ClickException(f"cannot {doing} {path}: {err}")
    if doing == "write":
        hint = {
            "permission denied": f"the folder {path.parent} is not writable by you",
            "read-only file system": f"{path.parent} lies on a read-only file system",
        }.get(condition, "")
        where = f" ({hint})" if hint else ""
        return click.ClickException(
            f"cannot write {path}: {condition}{where}; nothing was replaced."
        )
    return click.ClickException(f"cannot {doing} {path}: {condition}.")
