"""``diffaccel predict``: screen images of a reconstruction for new settings."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from diffaccel.cli.output import (
    IN_DIR,
    IN_FILE,
    OUT_FILE,
    SHOW_DEFAULTS,
    echo_warnings,
    force_option,
    out_option,
    seed_option,
)
from diffaccel.data import FormatError
from diffaccel.reconstruction.evaluation import (
    MAX_PREDICTION_PARTICLES,
    PREDICTION_NOISE_L1,
)
from diffaccel.reconstruction.prediction import check_prediction_files, predict_files

__all__ = ["predict"]


@click.command("predict", context_settings=SHOW_DEFAULTS)
@click.argument("result_dir", type=IN_DIR)
@click.option(
    "--dataset",
    "dataset",
    type=IN_FILE,
    default=None,
    help="Predict every scan and setting of this file (version 1 or 2), on its "
    "screen grids.",
)
@click.option(
    "--settings",
    "settings",
    default=None,
    help="Instead of --dataset: values of the scanned parameter(s) of the "
    "(first) training scan, e.g. '-3,0,2.5' (one parameter) or '1:2;3:4' (rows ';').",
)
@out_option(
    OUT_FILE,
    "Output file: .h5 writes a quad-scan file of the same format version as "
    "--dataset with the predicted images (one shot, each summing to 1); .npy "
    "writes (K, H, W) float32 (one scan only). Settings where less than half of "
    "the beam lands on the screen are warned (and recorded in the .h5).",
)
@click.option(
    "--particles",
    "n_particles",
    type=click.IntRange(min=100),
    default=50_000,
    help="Particles per ensemble member, at least: fine screens get more (up to "
    f"{MAX_PREDICTION_PARTICLES:.0e}), until the images' own sampling noise adds "
    f"at most {PREDICTION_NOISE_L1:g} relative L1.",
)
@seed_option
@click.option(
    "--std-out",
    type=OUT_FILE,
    default=None,
    help="Also write the per-pixel spread (1-sigma) of the predicted images, on "
    "their unit-sum scale: .npy (K, H, W) float32 for one scan, or .npz with one "
    "such array per scan name (ensemble scatter and the moment-space posterior; "
    "see docs/methods/uncertainty.md).",
)
@force_option("Overwrite --out (and --std-out).")
def predict(result_dir: Path, out: Path, force: bool, **options: Any) -> None:
    """Ensemble-mean screen images of a reconstruction (RESULT_DIR) for new settings."""
    dataset, std_out = options["dataset"], options["std_out"]
    given = options["settings"] is not None
    try:
        check_prediction_files(out, std_out, dataset, given, force)
        # --dataset or --settings, --std-out, --particles, --seed
        warnings = predict_files(
            result_dir, out, force=force, echo=click.echo, **options
        )
    except (FormatError, ValueError, FileNotFoundError, OSError) as err:
        raise click.ClickException(str(err)) from err
    echo_warnings(warnings)
