"""``diffaccel design``: what the scans determine, and which settings to add."""

from __future__ import annotations

import json
from pathlib import Path

import click
import torch

from diffaccel.data import FormatError
from diffaccel.data.atomic import atomic_write
from diffaccel.data.scans import read_scans
from diffaccel.plotting.design import design_figures
from diffaccel.reconstruction import design as dz
from diffaccel.reconstruction import load
from diffaccel.reconstruction.design_report import (
    design_json,
    design_lines,
    posterior_beam,
)

__all__ = ["design_command"]


def _load(data: Path, result: Path | None) -> tuple[list, torch.Tensor, object]:
    """Layouts, beam covariance and moment posterior (or None) of the inputs."""
    posterior = rel = None
    if data.suffix.lower() == ".json":
        try:
            spec = json.loads(data.read_text())
        except (OSError, json.JSONDecodeError) as err:
            raise click.ClickException(
                f"{data}: not a readable JSON file ({err})"
            ) from None
        if not isinstance(spec, dict):
            raise click.ClickException(f"{data}: expected a JSON object")
        try:
            layouts, cov = dz.layouts_from_spec(spec)
        except ValueError as err:
            raise click.ClickException(f"{data}: {err}") from None
    else:
        try:
            ds = read_scans(data)
        except (FormatError, OSError, ValueError) as err:
            raise click.ClickException(f"{data}: {err}") from None
        layouts = dz.layouts_from_dataset(ds)
        cov = None
        if result is None:
            try:
                cov = dz.beam_from_images(ds)
            except ValueError as err:
                raise click.ClickException(f"{data}: {err}") from None
    if result is not None:
        try:
            rec = load(result)
        except (FileNotFoundError, ValueError, OSError) as err:
            raise click.ClickException(f"--result {result}: {err}") from None
        unc = rec.uncertainty
        if unc is None:
            raise click.ClickException(
                f"--result {result}: the reconstruction has no moment posterior "
                "(run reconstruct without --no-uncertainty)"
            )
        cov, posterior, rel = posterior_beam(unc)
    return layouts, cov, (posterior, rel)


@click.command("design")
@click.argument("data", type=click.Path(exists=True, dir_okay=False, path_type=Path))
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
    type=click.Path(exists=True, file_okay=False, path_type=Path),
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
    show_default=True,
    help="Most added images per scan.",
)
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of a table.")
@click.option(
    "--plots",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    help="Folder for the singular-value spectrum and the std-vs-images figure.",
)
def design_command(
    data: Path,
    knobs: tuple[str, ...],
    targets: tuple[str, ...],
    result: Path | None,
    relative_error: float | None,
    max_images_per_scan: int,
    as_json: bool,
    plots: Path | None,
) -> None:
    """What the scans in DATA determine and which settings to add.

    DATA is a scan file (HDF5) or a JSON spec of planned scans (beamlines,
    knob grids, a prior beam; docs/methods/design.md). Without --knob: which second
    moments and quantities the scans determine and which they leave to the
    prior. With --knob: also the added settings, ranked by the reduction of
    the targets' posterior std per image. No training.
    """
    layouts, cov, (posterior, rel) = _load(data, result)
    r = relative_error or rel or dz.RELATIVE_ERROR
    try:
        parsed = [dz.parse_knob(k) for k in knobs]
        obs = dz.observability(layouts, cov, relative_error=r, posterior=posterior)
        report = None
        if parsed:
            report = dz.recommend(
                layouts,
                cov,
                parsed,
                targets=targets or dz.DEFAULT_TARGETS,
                relative_error=r,
                posterior=posterior,
                max_images_per_scan=max_images_per_scan,
            )
    except ValueError as err:
        raise click.ClickException(str(err)) from None
    od = obs.to_dict()
    if plots is not None:
        plots.mkdir(parents=True, exist_ok=True)
        for name, fig in design_figures(od, report):
            try:
                atomic_write(
                    plots / name,
                    lambda p, f=fig: f.savefig(p, format="png", dpi=120),
                    overwrite=False,
                )
            except FileExistsError:
                raise click.ClickException(
                    f"--plots: {plots / name} exists; remove it or choose another "
                    "folder"
                ) from None
    if as_json:
        click.echo(json.dumps(design_json(report, od), indent=1))
    else:
        for line in design_lines(report, od):
            click.echo(line)
