"""Screen images of a reconstruction for new settings, with their warnings.

:func:`predict_scans` images every scan and setting of a dataset (its
beamlines and screens); :func:`predict_settings` images settings of the
result's own (first) training beamline. Both return a :class:`Prediction`:
the ensemble-mean images (each summing to 1), optionally their per-pixel
spread, the fraction of the beam on the screen at each setting, and the
warnings (settings where less than half of the beam lands on the screen, a
4D result imaged through z or pz readers). :func:`predict_files` writes them
as ``diffaccel predict`` does (a quad-scan file or ``.npy`` images, the spread
as ``.npy``/``.npz``); :func:`parse_settings` reads its ``--settings`` text.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from diffaccel.data.atomic import OutputWriteError, os_error_text
from diffaccel.data.owned_files import OutputFileError, check_out_file, save_arrays
from diffaccel.data.scans import MultiScanDataset, read_scans, write_scans
from diffaccel.reconstruction.alarms import prediction_alarms
from diffaccel.reconstruction.ensemble import Reconstruction, load
from diffaccel.reconstruction.evaluation import (
    MAX_PREDICTION_PARTICLES,
    PREDICTION_NOISE_L1,
    check_on_screen,
    off_screen_warnings,
    predict_dataset,
    predicted_dataset,
)

__all__ = [
    "Prediction",
    "check_prediction_files",
    "parse_settings",
    "predict_files",
    "predict_scans",
    "predict_settings",
]

#: Posterior beams per ensemble member for the per-pixel spread.
N_DRAWS = 4


@dataclass(frozen=True)
class Prediction:
    """Predicted screen images per scan.

    Attributes:
        images: ``{scan: (K, H, W)}`` float32 images, each summing to 1.
        spread: ``{scan: (K, H, W)}`` per-pixel spread (1 sigma, on the scale
            of the unit-sum images); None where it was not asked for.
        on_screen: ``{scan: (K,)}`` fraction of the beam on the screen.
        warnings: One line each (no ``warning:`` prefix).
    """

    images: dict[str, Tensor]
    spread: dict[str, Tensor] | None
    on_screen: dict[str, Tensor]
    warnings: list[str]


def predict_scans(
    result: Reconstruction,
    dataset: MultiScanDataset,
    *,
    n_particles: int = 50_000,
    seed: int = 0,
    return_std: bool = False,
) -> Prediction:
    """Images of every scan and setting of ``dataset``, on its screen grids.

    See :func:`~diffaccel.reconstruction.predict_dataset` (at least
    ``n_particles`` per ensemble member, more where the images' own noise
    needs them; sampling ``seed``; ``return_std``: also the spread).

    Raises:
        ValueError: a dataset the result cannot image (e.g. other scanned
            names).
    """
    out = predict_dataset(
        result,
        dataset,
        n_particles=n_particles,
        seed=seed,
        return_std=return_std,
        return_on_screen=True,
    )
    if return_std:
        images, spread, on_screen = out
    else:
        (images, on_screen), spread = out, None
    warnings = [
        w
        for name, scan in dataset
        for w in off_screen_warnings(
            on_screen[name], scan.settings, scan.setting_names, scan=name
        )
    ]
    warnings += [a.text() for a in prediction_alarms(result, dataset)]
    return Prediction(images, spread, on_screen, warnings)


def predict_settings(
    result: Reconstruction,
    settings: Tensor,
    *,
    n_particles: int = 50_000,
    seed: int = 0,
    return_std: bool = False,
) -> Prediction:
    """Images at ``settings`` of the result's own (first) training beamline.

    Args:
        result: The reconstruction.
        settings: ``(K, P)`` values of its scanned parameters.
        n_particles: Particles per ensemble member, at least; more (up to
            :data:`~diffaccel.reconstruction.evaluation.MAX_PREDICTION_PARTICLES`)
            where the images' own sampling noise would add more than
            :data:`~diffaccel.reconstruction.evaluation.PREDICTION_NOISE_L1`
            relative L1.
        seed: Sampling seed.
        return_std: Also the per-pixel spread.

    Returns:
        A :class:`Prediction` of one scan, the result's first.

    Raises:
        ValueError: settings where the beam misses the screen entirely
            (:func:`~diffaccel.reconstruction.check_on_screen`), or of the
            wrong shape.
    """
    fwd = result.forward
    name = result.scan_names[0]
    out = result.predict_images(
        settings,
        forward=fwd,
        n_particles=n_particles,
        seed=seed,
        return_std=return_std,
        n_draws=N_DRAWS,
        return_on_screen=True,
        noise_l1=PREDICTION_NOISE_L1,
        max_particles=max(MAX_PREDICTION_PARTICLES, n_particles),
    )
    if return_std:
        images, std, fraction = out
        spread = {name: std}
    else:
        (images, fraction), spread = out, None
    check_on_screen(images, settings)
    warnings = off_screen_warnings(fraction, settings, fwd.names, scan=name)
    warnings += [a.text() for a in prediction_alarms(result, None, settings)]
    return Prediction({name: images}, spread, {name: fraction}, warnings)


def parse_settings(text: str, names: list[str]) -> Tensor:
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


def check_prediction_files(
    out: Path,
    std_out: Path | None,
    dataset: Path | None,
    settings_given: bool,
    force: bool,
) -> None:
    """Refuse output files and inputs of :func:`predict_files` before any work.

    ``out`` and ``std_out`` as :func:`~diffaccel.data.owned_files.check_out_file`
    allows them (never the ``dataset`` file); ``std_out`` a ``.npy`` or
    ``.npz`` name; exactly one of ``dataset`` and ``settings_given``; ``out``
    a ``.h5``/``.hdf5`` (which needs ``dataset``) or ``.npy`` name.

    Raises:
        ValueError: the first of these refusals, naming the option
            (:class:`~diffaccel.data.owned_files.OutputFileError` for a file).
    """
    check_out_file(out, force, {"--dataset": dataset})
    if std_out is not None:
        inputs = {"--dataset": dataset, "--out": out}
        check_out_file(std_out, force, inputs, "--std-out")
        if std_out.suffix.lower() not in (".npy", ".npz"):
            raise OutputFileError(
                f"--std-out {std_out}: expected a .npy (one scan) or .npz file name"
            )
    if (dataset is None) == (not settings_given):
        raise ValueError("give exactly one of --dataset or --settings")
    suffix = out.suffix.lower()
    if suffix not in (".h5", ".hdf5", ".npy"):
        raise OutputFileError(
            f"--out {out}: expected a .h5 (quad-scan file) or .npy file name"
        )
    if suffix != ".npy" and dataset is None:
        raise ValueError(
            "--out .h5 needs --dataset (the file whose settings and screens to "
            "predict); with --settings write .npy"
        )


def _save(path: Path, arrays: Mapping[str, np.ndarray]) -> None:
    """:func:`~diffaccel.data.owned_files.save_arrays`; OS conditions as one line."""
    try:
        save_arrays(path, arrays)
    except OSError as err:  # read-only folder, disk full...
        raise OutputWriteError(os_error_text(err, path)) from err


def predict_files(
    result_dir: Path,
    out: Path,
    *,
    dataset: Path | None = None,
    settings: str | None = None,
    std_out: Path | None = None,
    n_particles: int = 50_000,
    seed: int = 0,
    force: bool = False,
    echo: Callable[[str], object] = print,
) -> list[str]:
    """Predict the images of the reconstruction in ``result_dir`` into ``out``.

    Images every scan and setting of the quad-scan file ``dataset``
    (:func:`predict_scans`), or the ``settings`` text (:func:`parse_settings`)
    on the result's first training beamline (:func:`predict_settings`).
    ``out``: ``.h5`` writes a quad-scan file of ``dataset``'s format version
    with the predicted images; ``.npy`` the ``(K, H, W)`` float32 images of
    one scan. ``std_out``: also the per-pixel spread (``.npy`` for one scan,
    ``.npz`` one array per scan). Each file written is reported through
    ``echo`` (``wrote PATH: ...``) as soon as it is; call
    :func:`check_prediction_files` first. Every refusal comes before the
    first file is made.

    Returns:
        The warnings (settings off the screen, alarms), one line each.

    Raises:
        ValueError: a result or dataset that cannot be read or imaged as asked.
        OSError: a file that cannot be read; one that cannot be written as
            :class:`~diffaccel.data.atomic.OutputWriteError` (its condition
            in words).
    """
    want_std = std_out is not None
    result = load(result_dir)
    if dataset is not None:
        other = read_scans(dataset)
        pred = predict_scans(
            result, other, n_particles=n_particles, seed=seed, return_std=want_std
        )
    else:
        values = parse_settings(settings or "", result.forward.names)
        pred = predict_settings(
            result, values, n_particles=n_particles, seed=seed, return_std=want_std
        )
    predicted, spread = pred.images, pred.spread
    if std_out is not None and std_out.suffix.lower() == ".npy" and len(spread) != 1:
        raise ValueError(
            f"--std-out {std_out}: {len(spread)} scans; write them to an .npz file"
        )
    if out.suffix.lower() == ".npy":
        images = next(iter(predicted.values()))
        if dataset is not None:
            if len(predicted) != 1:
                raise ValueError(
                    f"{dataset} holds {len(predicted)} scans; write them to an "
                    ".h5 file (--out PRED.h5)"
                )
            check_on_screen(images, other[other.names[0]].settings)
        _save(out, {"images": images.numpy().astype(np.float32)})
        k, h, w = images.shape
        echo(f"wrote {out}: {k} images of {h} x {w} pixels")
    else:
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
            written = write_scans(
                predicted_dataset(
                    other, predicted, source=str(result_dir), on_screen=pred.on_screen
                ),
                out,
                overwrite=force,
            )
        except OSError as err:  # read-only folder, disk full...
            raise OutputWriteError(os_error_text(err, out)) from err
        n = sum(v.shape[0] for v in predicted.values())
        echo(
            f"wrote {written}: {n} predicted images in {len(predicted)} scan(s) "
            f"(format version {other.format_version})"
        )
    if std_out is not None:
        arrays = {
            k: v.detach().cpu().numpy().astype(np.float32) for k, v in spread.items()
        }
        _save(std_out, arrays)
        echo(f"wrote {std_out}: per-pixel spread of {len(arrays)} scan(s)")
    return pred.warnings
