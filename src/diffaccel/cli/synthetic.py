"""``diffaccel synthetic``: write a simulated quad scan with its ground-truth beam."""

from __future__ import annotations

from pathlib import Path

import click

from diffaccel.data import FormatError, make_synthetic_quad_scan, write_quad_scan
from diffaccel.data.synthetic import PRESETS

__all__ = ["synthetic"]


@click.command("synthetic")
@click.argument("out", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--preset",
    type=click.Choice(PRESETS),
    default="gaussian",
    show_default=True,
    help="Ground-truth beam (6D, with energy spread).",
)
@click.option(
    "--particle-file",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="openPMD-beamphysics HDF5 beam to use instead of a preset.",
)
@click.option(
    "--particles",
    "n_particles",
    type=click.IntRange(min=2),
    default=10_000,
    show_default=True,
    help="Number of preset particles.",
)
@click.option(
    "--settings",
    "n_settings",
    type=click.IntRange(min=1),
    default=20,
    show_default=True,
    help="Number of quadrupole settings K.",
)
@click.option("--k1-min", type=float, default=-25.0, show_default=True, help="[1/m^2]")
@click.option("--k1-max", type=float, default=15.0, show_default=True, help="[1/m^2]")
@click.option(
    "--shape",
    type=(click.IntRange(min=2), click.IntRange(min=2)),
    default=(64, 64),
    show_default=True,
    help="Screen rows H and columns W [pixels].",
)
@click.option(
    "--pixel-size",
    type=click.FloatRange(min=0, min_open=True),
    default=1e-3,
    show_default=True,
    help="Pixel size [m] (square pixels).",
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
    type=click.Choice(["kde", "cic"]),
    default="kde",
    show_default=True,
    help="Screen image model (KDE bandwidth: one pixel).",
)
@click.option(
    "--noise",
    type=click.FloatRange(min=0),
    default=0.0,
    show_default=True,
    help="Relative noise at the peak pixel (0: none).",
)
@click.option(
    "--noise-model",
    type=click.Choice(["poisson", "gaussian"]),
    default="poisson",
    show_default=True,
)
@click.option(
    "--shots",
    type=click.IntRange(min=1),
    default=1,
    show_default=True,
    help="Shots per setting.",
)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--force", is_flag=True, help="Overwrite OUT if it exists.")
def synthetic(
    out: Path,
    preset: str,
    particle_file: Path | None,
    n_particles: int,
    n_settings: int,
    k1_min: float,
    k1_max: float,
    shape: tuple[int, int],
    pixel_size: float,
    p0c: float | None,
    image_method: str,
    noise: float,
    noise_model: str,
    shots: int,
    seed: int,
    force: bool,
) -> None:
    """Simulate a quadrupole scan of a known beam and write it to OUT (HDF5)."""
    if out.exists() and not force:
        raise click.ClickException(f"{out} exists; pass --force to overwrite it")
    try:
        ds = make_synthetic_quad_scan(
            preset,  # type: ignore[arg-type]
            particle_file=particle_file,
            n_particles=n_particles,
            p0c=p0c,
            n_settings=n_settings,
            k1_range=(k1_min, k1_max),
            screen_shape=shape,
            pixel_size=(pixel_size, pixel_size),
            image_method=image_method,  # type: ignore[arg-type]
            noise=noise,
            noise_model=noise_model,  # type: ignore[arg-type]
            shots=shots,
            seed=seed,
        )
        write_quad_scan(ds, out, overwrite=force)
    except (FormatError, ValueError, FileExistsError) as err:
        raise click.ClickException(str(err)) from err
    beam = f"preset {preset}" if particle_file is None else f"beam {particle_file}"
    k, s, h, w = ds.shape
    click.echo(
        f"wrote {out}: {k} settings (k1 {k1_min:g} .. {k1_max:g} 1/m^2) x {s} shot(s) "
        f"of {h}x{w} px at {pixel_size * 1e3:g} mm, {beam}, "
        f"{ds.ground_truth.shape[0]} particles, p0c {ds.p0c / 1e6:g} MeV, "
        f"{image_method} images, noise {noise:g} ({noise_model}), seed {seed}"
    )
