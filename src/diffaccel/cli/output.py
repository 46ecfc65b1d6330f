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
from diffaccel.data.result_folder import MARKER

__all__ = ["check_out_file", "output_folder", "save_png"]


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


#: zlib level of the PNG figures: 3 encodes ~2x faster than PIL's default 6
#: for ~20 % larger files (the same pixels); a reconstruct's wall time includes its
#: figures in its whole time
PNG_COMPRESS_LEVEL = 3


def save_png(fig: Any, path: Path, dpi: int = 120) -> Path:
    """Write a matplotlib figure as PNG (atomically); returns ``path``."""
    return atomic_write(
        path,
        lambda p: fig.savefig(
            p,
            format="png",
            dpi=dpi,
            pil_kwargs={"compress_level": PNG_COMPRESS_LEVEL},
        ),
    )


def check_out_file(
    out: Path, force: bool, inputs: dict[str, Path | None], option: str = "--out"
) -> None:
    """Refuse an output file that would replace something the user gave.

    ``out`` may replace an existing file only with ``force``, never one of the
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
