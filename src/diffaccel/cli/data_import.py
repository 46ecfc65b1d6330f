"""``diffaccel data import``: a DAQ folder described in YAML into a quad-scan file."""

from __future__ import annotations

from pathlib import Path

import click
from tqdm import tqdm

from diffaccel.cli.output import (
    IN_FILE,
    OUT_FILE,
    SHOW_DEFAULTS,
    check_out_file,
    echo_lines,
    force_option,
    out_option,
)
from diffaccel.data import FormatError, write_scans
from diffaccel.data.experiment import (
    count_frames,
    import_experiment,
    import_lines,
    load_experiment,
)

__all__ = ["import_command"]


@click.command("import", context_settings=SHOW_DEFAULTS)
@click.argument("experiment", type=IN_FILE)
@out_option(OUT_FILE, "Quad-scan file to write (HDF5, format version 2).")
@force_option("Replace an existing --out file.")
@click.option(
    "--progress/--no-progress",
    default=True,
    help="Show a progress bar while the frames are read.",
)
def import_command(experiment: Path, out: Path, force: bool, progress: bool) -> None:
    """Build a quad-scan file (format 2) from the DAQ files EXPERIMENT.yaml names."""
    check_out_file(out, force, {"EXPERIMENT": experiment})
    try:
        total = count_frames(load_experiment(experiment), experiment.parent)
        with tqdm(
            total=total or None,
            unit="frame",
            desc="reading frames",
            disable=not progress,
            leave=False,
        ) as bar:
            dataset = import_experiment(experiment, progress=bar.update)
        path = write_scans(dataset, out, overwrite=force)
    except (FormatError, FileNotFoundError, ImportError, FileExistsError) as err:
        raise click.ClickException(str(err).strip().splitlines()[0]) from err
    click.echo(f"wrote {path}")
    echo_lines(import_lines(dataset))
