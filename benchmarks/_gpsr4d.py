"""gpsr 0.2.0's documented 4D recipe on a quad-scan file (used by two benchmarks).

``benchmarks/reconstruction.py`` calls :func:`train` in its own process;
``benchmarks/reconstruction_process.py`` runs this file as a whole process, the
way a gpsr user would (imports, data loading, training, saving the model), and
times it from outside. The recipe: ``NNParticleBeamGenerator`` (10 000
particles), ``GPSRQuadScanLattice`` (quadrupole + drift) with a cheetah
cloud-in-cell ``Screen``, ``train_gpsr`` (Adam 1e-3, MAE on sum-normalised
images, one batch of all training images) for 2000 epochs.

The data are read with h5py only (the layout of ``data/README.md``),
so this process imports neither diffaccel nor anything gpsr does not need.

``--device cuda`` trains on the GPU (Lightning's ``accelerator="gpu"``); the
default ``cpu`` keeps it on the CPU even where a GPU is present.

Usage: ``python benchmarks/_gpsr4d.py TRAIN.h5 OUT_DIR [--epochs 2000] [--device cpu]``
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

ELECTRON_MASS_EV = 0.51099895e6


def read_h5(path: str | Path) -> dict:
    """Images (mean over shots, sum-normalised), settings and geometry of a file."""
    import h5py

    with h5py.File(path, "r") as h5:
        spec = {e["name"]: e for e in json.loads(h5.attrs["beamline"])}
        images = torch.as_tensor(h5["images"][()], dtype=torch.float32).mean(1)
        settings = torch.as_tensor(h5["settings"][()], dtype=torch.float64)
        scr = h5["screen"].attrs
        pixel = (float(scr["pixel_size_x"]), float(scr["pixel_size_y"]))
        p0c = float(h5.attrs["p0c"])
    images = images / images.sum((-2, -1), keepdim=True)
    quad = next(e for e in spec.values() if e["type"] == "Quadrupole")
    drift = next(e for e in spec.values() if e["type"] == "Drift")
    return {
        "images": images,
        "settings": settings,
        "pixel_size": pixel,
        "screen_shape": tuple(images.shape[-2:]),
        "p0c": p0c,
        "quad_length": float(quad["length"]),
        "drift_length": float(drift["length"]),
    }


def screen(data: dict):
    """A fresh cheetah cloud-in-cell screen of the data's geometry."""
    from cheetah.accelerator import Screen

    h, w = data["screen_shape"]
    return Screen(
        resolution=(w, h),
        pixel_size=torch.tensor(data["pixel_size"], dtype=torch.float32),
        method="cloud-in-cell",
        is_active=True,
    )


def lattice(data: dict, scr=None):
    """gpsr's quad-scan lattice; with a fresh screen unless one is given (trained
    models can return stale images for new settings, ANCHORS.md)."""
    from gpsr.modeling import GPSRQuadScanLattice

    scr = screen(data) if scr is None else scr
    return GPSRQuadScanLattice(data["quad_length"], data["drift_length"], scr)


def train(
    data: dict, epochs: int, log_dir: str | Path, seed: int = 0, device: str = "cpu"
):
    """Train gpsr's recipe on all images of ``data``; returns gpsr's Lightning module.

    ``train_gpsr`` writes its CSV log and a final checkpoint under ``log_dir``.
    """
    import lightning as L  # noqa: F401  (gpsr's trainer)
    from gpsr.beams import NNParticleBeamGenerator
    from gpsr.datasets import QuadScanDataset
    from gpsr.modeling import GPSR
    from gpsr.train import train_gpsr
    from lightning.pytorch.loggers import CSVLogger
    from torch.utils.data import DataLoader

    energy = (data["p0c"] ** 2 + ELECTRON_MASS_EV**2) ** 0.5
    scr = screen(data)
    lat = lattice(data, scr)
    train_set = QuadScanDataset(data["settings"].float(), (data["images"],), scr)
    loader = DataLoader(train_set, batch_size=len(train_set))
    torch.manual_seed(seed)
    model = GPSR(NNParticleBeamGenerator(10_000, energy), lat)
    return train_gpsr(
        model,
        loader,
        n_epochs=epochs,
        logger=CSVLogger(str(log_dir)),
        checkpoint_period_epochs=epochs,
        enable_progress_bar=False,
        enable_model_summary=False,
        accelerator="gpu" if device.startswith("cuda") else "cpu",
        devices=1,
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("train", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--epochs", type=int, default=2000)
    ap.add_argument("--device", default="cpu", help="cpu (default) or cuda")
    args = ap.parse_args()
    t0 = time.perf_counter()
    data = read_h5(args.train)
    args.out.mkdir(parents=True, exist_ok=True)
    lit = train(data, args.epochs, args.out, device=args.device)
    torch.save(lit.gpsr_model.state_dict(), args.out / "gpsr_model.pt")
    print(json.dumps({"in_process_s": time.perf_counter() - t0}))


if __name__ == "__main__":
    main()
