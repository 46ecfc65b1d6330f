"""``diffaccel predict``: screen images of a reconstruction for new settings."""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np
import torch

from diffaccel.cli.options import echo_warnings, seed_option
from diffaccel.cli.output import check_out_file, os_error
from diffaccel.data import FormatError, read_scans, write_scans
from diffaccel.data.owned_files import save_arrays
from diffaccel.reconstruction import check_on_screen, load, predicted_dataset
from diffaccel.reconstruction.prediction import predict_scans, predict_settings

__all__ = ["parse_settings", "predict"]


def _save(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """:func:`~diffaccel.data.owned_files.save_arrays`; OS conditions as one line."""
    try:
        save_arrays(path, arrays)
    except OSError as err:  # read-only folder, disk full...
        raise os_error(err, path) from err


def _write_spread(path: Path, spread: dict[str, torch.Tensor]) -> None:
    """Per-pixel spreads as .npy (one scan) or .npz (one array per scan)."""
    arrays = {k: v.detach().cpu().numpy().astype(np.float32) for k, v in spread.items()}
    _save(path, arrays)
    click.echo(f"wrote {path}: per-pixel spread of {len(arrays)} scan(s)")


def parse_settings(text: str, names: list[str]) -> torch.Tensor:
    """``--settings`` text as a ``(K, P)`` float64 tensor for scanned ``names``.

    One parameter: ``"-3,0,2.5"`` (or one row per ``;``); several: rows
    separated by ``;``, the values of a row by ``:`` (``"1:2;3:4"``).

    Raises:
        ValueError: naming the value that is not a number, a row of the wrong
            length, an empty row or value (a stray ``;`` or ``,``), or an empty
            list.
    """
    if not text.replace(" ", "").strip(";,"):
        raise ValueError(f"--settings {text!r} holds no value; e.g. '-3,0,2.5'.")
    rows = text.replace(" ", "").split(";")
    if len(names) == 1 and len(rows) == 1:
        rows = rows[0].split(",")
        what, sep = "value", ","
    else:
        what, sep = "row", ";"
    for i, row in enumerate(rows):
        if not row:  # a stray separator would silently drop a setting
            raise ValueError(
                f"--settings {text!r}: {what} {i + 1} is empty (a stray {sep!r}?)."
            )
    out = []
    for i, row in enumerate(rows):
        cells = row.split(":")
        if len(cells) != len(names):
            raise ValueError(
                f"--settings row {i + 1} {row!r} has {len(cells)} value(s); "
                f"expected {len(names)} ({':'.join(names)}), rows separated by ';'."
            )
        try:
            out.append([float(c) for c in cells])
        except ValueError:
            raise ValueError(
                f"--settings row {i + 1} {row!r}: not a number; expected e.g. "
                f"'-3,0,2.5' or '1:2;3:4'."
            ) from None
    return torch.tensor(out, dtype=torch.float64)


@click.command("predict")
@click.argument(
    "result_dir", type=click.Path(exists=True, file_okay=False, path_type=Path)
)
@click.option(
    "--dataset",
    "dataset_path",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="Predict every scan and setting of this file (version 1 or 2), on its "
    "screen grids.",
)
@click.option(
    "--settings",
    "settings_text",
    default=None,
    help="Instead of --dataset: values of the scanned parameter(s) of the "
    "(first) training scan, e.g. '-3,0,2.5' (one parameter) or '1:2;3:4' (rows ';').",
)
@click.option(
    "--out",
    type=click.Path(dir_okay=False, path_type=Path),
    required=True,
    help="Output file: .h5 writes a quad-scan file of the same format version as "
    "--dataset with the predicted images (one shot, each summing to 1); .npy "
    "writes (K, H, W) float32 (one scan only). Settings where less than half of "
    "the beam lands on the screen are warned (and recorded in the .h5).",
)
@click.option(
    "--particles",
    type=click.IntRange(min=100),
    default=50_000,
    show_default=True,
    help="Particles per ensemble member.",
)
@seed_option
@click.option(
    "--std-out",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Also write the per-pixel spread (1-sigma) of the predicted images, on "
    "their unit-sum scale: .npy (K, H, W) float32 for one scan, or .npz with one "
    "such array per scan name (ensemble scatter and the moment-space posterior; "
    "see docs/methods/uncertainty.md).",
)
@click.option("--force", is_flag=True, help="Overwrite --out (and --std-out).")
def predict(
    result_dir: Path,
    dataset_path: Path | None,
    settings_text: str | None,
    out: Path,
    particles: int,
    seed: int,
    std_out: Path | None,
    force: bool,
) -> None:
    """Ensemble-mean screen images of a reconstruction (RESULT_DIR) for new settings."""
    check_out_file(out, force, {"--dataset": dataset_path})
    if std_out is not None:
        check_out_file(
            std_out, force, {"--dataset": dataset_path, "--out": out}, "--std-out"
        )
        if std_out.suffix.lower() not in (".npy", ".npz"):
            raise click.ClickException(
                f"--std-out {std_out}: expected a .npy (one scan) or .npz file name"
            )
    if (dataset_path is None) == (settings_text is None):
        raise click.ClickException("give exactly one of --dataset or --settings")
    suffix = out.suffix.lower()
    if suffix not in (".h5", ".hdf5", ".npy"):
        raise click.ClickException(
            f"--out {out}: expected a .h5 (quad-scan file) or .npy file name"
        )
    if suffix != ".npy" and dataset_path is None:
        raise click.ClickException(
            "--out .h5 needs --dataset (the file whose settings and screens to "
            "predict); with --settings write .npy"
        )
    want_std = std_out is not None
    try:
        result = load(result_dir)
        if dataset_path is not None:
            other = read_scans(dataset_path)
            pred = predict_scans(
                result, other, n_particles=particles, seed=seed, return_std=want_std
            )
        else:
            settings = parse_settings(settings_text, result.forward.names)
            pred = predict_settings(
                result, settings, n_particles=particles, seed=seed, return_std=want_std
            )
    except (FormatError, ValueError, FileNotFoundError, OSError) as err:
        raise click.ClickException(str(err)) from err
    predicted, spread, warnings = pred.images, pred.spread, pred.warnings
    # every refusal before the first file or folder is made
    if std_out is not None and std_out.suffix.lower() == ".npy" and len(spread) != 1:
        raise click.ClickException(
            f"--std-out {std_out}: {len(spread)} scans; write them to an .npz file"
        )
    if suffix == ".npy":
        images = next(iter(predicted.values()))
        if dataset_path is not None:
            if len(predicted) != 1:
                raise click.ClickException(
                    f"{dataset_path} holds {len(predicted)} scans; write them to an "
                    ".h5 file (--out PRED.h5)"
                )
            try:
                check_on_screen(images, other[other.names[0]].settings)
            except ValueError as err:
                raise click.ClickException(str(err)) from err
        _save(out, {"images": images.numpy().astype(np.float32)})
        k, h, w = images.shape
        click.echo(f"wrote {out}: {k} images of {h} x {w} pixels")
        if std_out is not None:
            _write_spread(std_out, spread)
        echo_warnings(warnings)
        return
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        written = write_scans(
            predicted_dataset(
                other, predicted, source=str(result_dir), on_screen=pred.on_screen
            ),
            out,
            overwrite=force,
        )
    except (FormatError, ValueError) as err:
        raise click.ClickException(str(err)) from err
    except OSError as err:  # read-only folder, disk full...
        raise os_error(err, out) from err
    n = sum(v.shape[0] for v in predicted.values())
    click.echo(
        f"wrote {written}: {n} predicted images in {len(predicted)} scan(s) "
        f"(format version {other.format_version})"
    )
    if std_out is not None:
        _write_spread(std_out, spread)
    echo_warnings(warnings)
