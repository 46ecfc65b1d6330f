"""A DAQ-like folder made from noise-free scans: camera frames with camera noise.

:func:`write_daq_folder` writes what a camera DAQ leaves behind for each scan
of a :class:`~diffaccel.data.MultiScanDataset`: integer frames (PNG, TIFF or
``.npy``) with a fixed-pattern pedestal, shot noise and read noise, several
shots per setting, background frames, a CSV table of frames and knob values,
the beamline as JSON, and the ``experiment.yaml`` that
``diffaccel data import`` reads. Camera row 0 is the top of the screen (+y).
"""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path

import numpy as np

from diffaccel.data.scans import MultiScanDataset

__all__ = ["write_daq_folder"]


def _write_frame(path: Path, pixels: np.ndarray) -> None:
    if path.suffix == ".npy":
        np.save(path, pixels)
        return
    try:
        import imageio.v3 as iio
    except ImportError as err:
        raise ImportError(
            "writing PNG/TIFF frames needs imageio: pip install diffaccel[images]"
        ) from err
    iio.imwrite(path, pixels)


def write_daq_folder(
    dataset: MultiScanDataset,
    folder: str | os.PathLike,
    *,
    shots: int = 3,
    n_background: int = 4,
    pedestal: float = 400.0,
    pedestal_pattern: float = 30.0,
    read_noise: float = 8.0,
    peak_electrons: float = 4000.0,
    gain: float = 4.0,
    bits: int = 16,
    suffix: str = ".png",
    seed: int = 0,
) -> Path:
    """Write camera frames of each scan's shot-averaged images, with noise.

    Per pixel, a frame holds ``pedestal_map + gain * Poisson(electrons) +
    Normal(0, read_noise)`` counts, rounded and clipped to ``[0, 2**bits - 1]``,
    with ``electrons = peak_electrons * image / max`` (``max`` the largest pixel
    of the scan's mean images) and ``pedestal_map`` the pedestal plus a fixed
    pattern (a left-to-right ramp of ``pedestal_pattern`` counts), which the
    background frames (pedestal and read noise only) record.

    Args:
        dataset: Noise-free scans (``mean_images()`` of each is imaged).
        folder: Destination folder (created; must not hold an
            ``experiment.yaml`` already).
        shots: Frames per setting.
        n_background: Background frames per scan.
        pedestal: Mean camera offset [counts].
        pedestal_pattern: Peak-to-peak of the pedestal's fixed pattern [counts].
        read_noise: Rms read noise [counts].
        peak_electrons: Mean signal of the brightest pixel [electrons].
        gain: Counts per electron.
        bits: Integer depth of the frames (8 or 16).
        suffix: ``".png"``, ``".tif"`` or ``".npy"``.
        seed: Seed of the noise.

    Returns:
        The path of ``experiment.yaml``.

    Raises:
        FileExistsError: if ``folder/experiment.yaml`` exists.
        ValueError: for ``bits`` other than 8 or 16 or an unknown suffix.
    """
    if bits not in (8, 16):
        raise ValueError(f"bits: expected 8 or 16; got {bits}")
    if suffix not in (".png", ".tif", ".npy"):
        raise ValueError(f"suffix: expected .png, .tif or .npy; got {suffix!r}")
    try:
        import yaml
    except ImportError as err:
        raise ImportError(
            "writing experiment.yaml needs PyYAML: pip install diffaccel[images]"
        ) from err
    folder = Path(folder)
    out = folder / "experiment.yaml"
    if out.exists():
        raise FileExistsError(f"{out} exists")
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    dtype = np.uint8 if bits == 8 else np.uint16
    top = float(2**bits - 1)
    scans = {}
    for name, scan in dataset:
        mean = scan.mean_images().double().numpy()  # (K, H, W), rows = y up
        k, h, w = mean.shape
        ped = pedestal + pedestal_pattern * (np.arange(w) / max(w - 1, 1) - 0.5)
        ped_map = np.broadcast_to(ped[None, :], (h, w))
        electrons = peak_electrons * mean / mean.max()
        sub = folder / name
        sub.mkdir(exist_ok=True)

        def camera(signal: np.ndarray, ped_map: np.ndarray = ped_map) -> np.ndarray:
            noise = rng.normal(0.0, read_noise, ped_map.shape)
            counts = ped_map + signal + noise
            # camera row 0 is the top of the screen: +y
            return np.clip(np.rint(counts), 0, top).astype(dtype)[::-1, :]

        names, units = scan.setting_names, scan.setting_units
        header = ["file", "shot"] + [
            f"{n} [{u}]" for n, u in zip(names, units, strict=True)
        ]
        rows = []
        for i in range(k):
            for s in range(shots):
                rel = f"{name}/frame_{i:03d}_{s}{suffix}"
                signal = gain * rng.poisson(electrons[i]).astype(np.float64)
                _write_frame(folder / rel, camera(signal))
                rows.append(
                    [rel, s, *(repr(float(v)) for v in scan.settings[i].tolist())]
                )
        for b in range(n_background):
            _write_frame(sub / f"background_{b:02d}{suffix}", camera(np.zeros((h, w))))
        with (folder / f"{name}.csv").open("w", newline="") as fh:
            writer = csv.writer(fh)
            writer.writerow(header)
            writer.writerows(rows)
        (folder / f"{name}_beamline.json").write_text(
            json.dumps(scan.beamline_spec, indent=1)
        )
        scans[name] = {
            "beamline": {"file": f"{name}_beamline.json"},
            "screen": {
                "pixel_size": [float(v) for v in scan.pixel_size],
                "center": [float(v) for v in scan.center],
                "row0": "top",
                "col0": "left",
            },
            "images": f"{name}.csv",
            "background": f"{name}/background_*{suffix}",
        }
    doc = {
        "p0c": float(dataset.p0c),
        "species": dataset.species,
        "description": "camera frames with pedestal, shot and read noise",
        "scans": scans,
    }
    out.write_text(yaml.safe_dump(doc, sort_keys=False))
    return out
