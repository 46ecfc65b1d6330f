"""``diffaccel design``: what the scans determine, and which settings to add."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import click

from diffaccel.cli.output import (
    IN_DIR,
    IN_FILE,
    OUT_DIR,
    SHOW_DEFAULTS,
    click_errors,
    echo_lines,
)
from diffaccel.plotting.design import write_design_figures
from diffaccel.reconstruction.design_report import (
    design_answers,
    design_json,
    design_lines,
)

__all__ = ["design_command"]


@click.command("design", context_settings=SHOW_DEFAULTS)
@click.argument("data", type=IN_FILE)
@click.option(
    "--knob",
    "knobs",
    multiple=True,
    metavar="ELEMENT.param=LOW:HIGH[:N]",
    help="Candidate knob and the range the hardware allows (repeatable), e.g. "
    "SCAN_TDC.voltage=-4e6:4e6 or SCAN_DIPOLE.angle=-0.40:-0.30; N grid values "
    "(default 5).",
)
@click.option(
    "--target",
    "targets",
    multiple=True,
    help="Quantity whose posterior std the added settings reduce (repeatable; "
    "default emit_z and emit_6d).",
)
@click.option(
    "--result",
    type=IN_DIR,
    default=None,
    help="Result folder of reconstruct: use its beam and moment posterior "
    "(default: the Gaussian fit of the images, or the spec's beam).",
)
@click.option(
    "--relative-error",
    type=click.FloatRange(min=1e-6, max=1.0),
    default=None,
    help="Relative error of each screen second moment [default: the result's "
    "fitted error scale, else 0.01].",
)
@click.option(
    "--max-images-per-scan",
    type=click.IntRange(min=1),
    default=8,
    help="Most added images per scan.",
)
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of a table.")
@click.option(
    "--plots",
    type=OUT_DIR,
    default=None,
    help="Folder for the singular-value spectrum and the std-vs-images figure.",
)
def design_command(
    data: Path, as_json: bool, plots: Path | None, **answers: Any
) -> None:
    """What the scans in DATA determine and which settings to add.

    DATA is a scan file (HDF5) or a JSON spec of planned scans (beamlines,
    knob grids, a prior beam; docs/methods/design.md). Without --knob: which second
    moments and quantities the scans determine and which they leave to the
    prior. With --knob: also the added settings, ranked by the reduction of
    the targets' posterior std per image. No training.
    """
    with click_errors():  # --knob, --target, --result, ...: design_answers's
        od, report = design_answers(data, **answers)
    if plots is not None:
        try:
            write_design_figures(plots, od, report)
        except FileExistsError as err:
            raise click.ClickException(
                f"--plots: {err.filename} exists; remove it or choose another folder"
            ) from None
    if as_json:
        click.echo(json.dumps(design_json(report, od), indent=1))
    else:
        echo_lines(design_lines(report, od))
