"""Result folders of CLI commands: all-or-nothing, locked, errors as one line."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import click

from diffaccel.data import (
    ResultFolder,
    ResultFolderError,
    atomic_write,
    result_folder,
)

__all__ = ["output_folder", "save_png"]


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
            f"writing the results for {out} failed: {err}; {out} was left as it was."
        ) from err


def save_png(fig: Any, path: Path, dpi: int = 120) -> Path:
    """Write a matplotlib figure as PNG (atomically); returns ``path``."""
    return atomic_write(path, lambda p: fig.savefig(p, format="png", dpi=dpi))
