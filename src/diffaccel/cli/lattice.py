"""``diffaccel lattice``: read a lattice file through cheetah and list its elements."""

from __future__ import annotations

import warnings
from pathlib import Path

import click

from diffaccel.cli.output import (
    IN_FILE,
    OUT_FILE,
    check_out_file,
    echo_lines,
    echo_warnings,
    force_option,
    out_option,
)
from diffaccel.data.atomic import atomic_write_json
from diffaccel.dynamics import Beamline
from diffaccel.dynamics.cheetah_interop import LatticeImportError
from diffaccel.dynamics.listing import spec_table

__all__ = ["lattice"]


@click.command("lattice")
@click.argument("file", type=IN_FILE)
@click.option("--start", default=None, help="First element to keep (by name).")
@click.option("--end", default=None, help="Last element to keep (by name).")
@click.option(
    "--line",
    default=None,
    help="Beam line to use (default: the file's USE, else the last line defined).",
)
@click.option(
    "--format",
    "fmt",
    type=click.Choice(["bmad", "elegant", "latticejson"]),
    default=None,
    help="Lattice format (default: by suffix: .bmad/.lat Bmad, .lte/.ele "
    "elegant, .json cheetah LatticeJSON).",
)
@click.option(
    "--screen",
    "screens",
    multiple=True,
    help="Make this marker or monitor a screen (repeat for several).",
)
@click.option(
    "--approximate",
    type=click.Choice(["drift", "linear"]),
    default=None,
    is_flag=False,
    flag_value="drift",
    help="Replace elements diffaccel lacks by a drift of the same length "
    "('--approximate' or '--approximate drift') or by their linear map "
    "('--approximate linear', needs --p0c). Without it such elements are an error.",
)
@click.option(
    "--p0c",
    type=float,
    default=None,
    help="Reference momentum [eV] for linear maps (--approximate linear, EMATRIX).",
)
@out_option(
    OUT_FILE, "Write the beamline spec (JSON list of elements) here.", required=False
)
@force_option("Overwrite --out if it exists.")
def lattice(
    file: Path,
    start: str | None,
    end: str | None,
    line: str | None,
    fmt: str | None,
    screens: tuple[str, ...],
    approximate: str | None,
    p0c: float | None,
    out: Path | None,
    force: bool,
) -> None:
    """List a lattice FILE (Bmad, elegant, LatticeJSON) read through cheetah."""
    if out is not None:
        check_out_file(out, force, {"FILE": file})
    if p0c is not None and not p0c > 0:
        raise click.ClickException(f"--p0c must be > 0 eV; got {p0c}.")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            beamline = Beamline.from_lattice(
                file,
                start,
                end,
                line=line,
                fmt=fmt,
                approximate=approximate,
                p0c=p0c,
                screens=screens,
            )
        except (ImportError, LatticeImportError) as err:
            raise click.ClickException(str(err)) from None
    echo_warnings([str(w.message) for w in caught])
    spec = beamline.to_spec()
    click.echo(f"{file}: {len(spec)} elements, {float(beamline.length):.6g} m")
    echo_lines(spec_table(spec))
    if out is not None:
        atomic_write_json(out, spec, overwrite=True)
        click.echo(f"wrote {out}")
