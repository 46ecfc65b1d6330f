"""``diffaccel synthetic``: write a simulated quad scan with its ground-truth beam."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from diffaccel.cli.output import (
    IN_FILE,
    OUT_FILE,
    SHOW_DEFAULTS,
    click_errors,
    force_option,
)
from diffaccel.data import FormatError
from diffaccel.data.atomic import os_error_text
from diffaccel.data.quad_scan import PARAMETER_LIMITS
from diffaccel.data.synthetic import PRESETS
from diffaccel.data.synthetic_file import (
    SyntheticRequest,
    check_synthetic,
    write_synthetic,
)

__all__ = ["synthetic"]

#: Largest screen side accepted by ``--shape`` [pixels] (a 4096 x 4096 float32
#: image is 64 MiB per setting and shot).
MAX_SHAPE = 4096
_K1 = PARAMETER_LIMITS["k1"]


@click.command("synthetic", context_settings=SHOW_DEFAULTS)
@click.argument("out", type=OUT_FILE)
@click.option(
    "--layout",
    type=click.Choice(["quad", "awa6d", "rf6d"]),
    default="quad",
    help="quad: Quadrupole 0.1 m + Drift 1 m + Screen (format version 1). awa6d: "
    "the AWA 6D layout (quadrupole 0.11 m, 1.3 GHz TDC off/4 MV, 20 degree "
    "dipole off/on, screens DYG1/DYG2 of 96 x 96 pixels; two scans, format "
    "version 2; k1 -12 ... 12 in 9 steps unless given). rf6d: the same without "
    "a deflecting cavity: a 2.856 GHz accelerating cavity, off or 4 MV at the "
    "zero crossing (phase 0 or pi), chirps the bunch and the dipole maps the "
    "chirp to x (RF phase plus dipole).",
)
@click.option(
    "--preset",
    type=click.Choice(PRESETS),
    default="gaussian",
    help="Ground-truth beam (6D, with energy spread).",
)
@click.option(
    "--particle-file",
    type=IN_FILE,
    default=None,
    help="openPMD-beamphysics HDF5 beam to use instead of a preset.",
)
@click.option(
    "--particles",
    "n_particles",
    type=click.IntRange(min=2),
    default=10_000,
    help="Number of preset particles.",
)
@click.option(
    "--settings",
    "n_settings",
    type=click.IntRange(min=1),
    default=None,
    help="Number of quadrupole settings K [default: 20; awa6d, rf6d: 9].",
)
@click.option(
    "--k1-min",
    type=click.FloatRange(-_K1, _K1),
    default=None,
    help="[1/m^2] [default: -25; awa6d, rf6d: -12]",
)
@click.option(
    "--k1-max",
    type=click.FloatRange(-_K1, _K1),
    default=None,
    help="[1/m^2] [default: 15; awa6d, rf6d: 12]",
)
@click.option(
    "--shape",
    type=(click.IntRange(2, MAX_SHAPE), click.IntRange(2, MAX_SHAPE)),
    default=None,
    help="Screen rows H and columns W [pixels] [default: 64 64; awa6d, rf6d: 96 96].",
)
@click.option(
    "--pixel-size",
    type=click.FloatRange(min=0, min_open=True),
    default=None,
    help="Pixel size [m] (square pixels) [default: 1e-3; awa6d, rf6d: the DYG1/DYG2 "
    "calibration scaled to --shape].",
)
@click.option(
    "--p0c",
    type=click.FloatRange(min=0, min_open=True),
    default=None,
    help="Reference momentum times c [eV]; default 43.36e6.",
)
@click.option(
    "--method",
    "image_method",
    type=click.Choice(["kde", "cic", "histogram"]),
    default=None,
    help="Screen image model (KDE bandwidth: one pixel; histogram: nearest-pixel "
    "counts) [default: kde; awa6d, rf6d: histogram].",
)
@click.option(
    "--noise",
    type=click.FloatRange(min=0),
    default=0.0,
    help="Relative noise at the peak pixel (0: none).",
)
@click.option(
    "--noise-model",
    type=click.Choice(["poisson", "gaussian"]),
    default="poisson",
    help="poisson: counts scaled so that the peak pixel has relative rms --noise; "
    "gaussian: zero-mean noise of rms --noise times the peak on every pixel.",
)
@click.option(
    "--shots",
    type=click.IntRange(min=1),
    default=1,
    help="Shots per setting.",
)
@click.option(
    "--seed", type=int, default=0, help="Seed of the beam sample and the noise."
)
@force_option("Overwrite OUT if it exists.")
def synthetic(out: Path, force: bool, **options: Any) -> None:
    """Simulate a quadrupole scan of a known beam and write it to OUT (HDF5)."""
    opts = SyntheticRequest(**options)
    with click_errors():
        check_synthetic(opts, out, force)
    try:
        click.echo(write_synthetic(opts, out, force))
    except (FormatError, ValueError, FileExistsError) as err:
        raise click.ClickException(str(err)) from err
    except OSError as err:  # a read-only folder, a full disk, a locked file
        raise click.ClickException(os_error_text(err, out)) from err
    except (MemoryError, RuntimeError) as err:
        if not isinstance(err, MemoryError) and "alloc" not in str(err):
            raise
        raise click.ClickException(
            "not enough memory for the images and tracking asked for (--shape, "
            "--settings, --shots, --particles); reduce them"
        ) from err
