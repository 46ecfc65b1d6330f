"""Bias of background subtraction on camera frames of a known beam.

A 4D quadrupole scan of a Gaussian beam (11 settings, 128 x 128 pixels; the beam
covers a few percent of the frame) is written as a DAQ folder of 16-bit PNG
frames (fixed-pattern pedestal ~400 counts, read noise 8 counts rms, shot noise,
3 shots per setting, 4 background frames) and imported with
``diffaccel.data.experiment.import_experiment`` under three preprocessings:

* ``signed``: the default (mean background frame subtracted, noise kept signed);
* ``clipped``: the same with ``clip: true`` (negative pixels set to 0);
* ``clipped_threshold``: clipped, then a triangle threshold.

For each, the image second moments (rms x, y on the screen over the whole
frame and within 6 rms of the noise-free image, mean over settings), the
emittances of a linear quad-scan fit to the whole-frame moments
(``fit_gaussian``) and, with ``--reconstruct``, the emittances and rms
sizes of a default 4D reconstruction (``reconstruct``, against the ground
truth) are compared with the same on the noise-free images. JSON on the last
line: relative errors per case.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path

import torch
import yaml
from _meta import add_store_flag, emit, git_commit

from diffaccel.data import MultiScanDataset, make_synthetic_quad_scan
from diffaccel.data.experiment import import_experiment
from diffaccel.data.synthetic_daq import write_daq_folder
from diffaccel.reconstruction import (
    ReconstructionConfig,
    ScreenForwardModel,
    fit_gaussian,
    moment_errors,
    reconstruct,
)
from diffaccel.reconstruction.uncertainty import image_moments, moment_window

CASES = {
    "signed": {"background": {"method": "frames"}},
    "clipped": {"background": {"method": "frames", "clip": True}},
    "clipped_threshold": {
        "background": {"method": "frames", "clip": True},
        "threshold": {"method": "triangle"},
    },
}


def _summary(scan, window: torch.Tensor) -> dict[str, float]:
    images = scan.mean_images().double()
    xs, ys = scan.pixel_centers()
    m = image_moments(images, xs, ys)
    mw = image_moments(images, xs, ys, window)
    fwd = ScreenForwardModel.from_dataset(scan, blur_pixels=1.0)
    guess = fit_gaussian(fwd, images, scan.settings)
    c = guess.cov
    return {
        "rms_x_screen": float(m[:, 2].sqrt().mean()),
        "rms_y_screen": float(m[:, 4].sqrt().mean()),
        "rms_x_screen_6sigma": float(mw[:, 2].sqrt().mean()),
        "rms_y_screen_6sigma": float(mw[:, 4].sqrt().mean()),
        "emit_x": math.sqrt(float(torch.linalg.det(c[:2, :2]))),
        "emit_y": math.sqrt(float(torch.linalg.det(c[2:4, 2:4]))),
    }


def _reconstructed(scan, truth: torch.Tensor) -> dict[str, float]:
    result = reconstruct(scan, ReconstructionConfig())
    errors = moment_errors(result.sample(100_000), truth)
    keys = ("rms_x", "rms_px", "rms_y", "rms_py", "emit_x", "emit_y")
    return {k: round(float(errors[k]), 4) for k in keys}


def _pair(errors: dict) -> str:
    return f"{100 * errors['emit_x']:+.1f} / {100 * errors['emit_y']:+.1f} %"


def headline(result: dict) -> dict[str, str]:
    """The docs page's figures: emittance errors x / y of each case.

    With ``--reconstruct`` those of the 4D reconstruction, else those of the
    linear quad-scan fit to the whole-frame moments.
    """
    if "reconstruction" in result:
        cases = result["reconstruction"]
        first = (
            "4D reconstruction emittance error x / y, noise-free images",
            result["reconstruction_noise_free"],
        )
    else:
        cases = result["cases"]
        first = None
    names = {
        "signed": "camera frames, background subtracted, noise kept signed (default)",
        "clipped": "camera frames, negative pixels clipped at 0",
        "clipped_threshold": "camera frames, clipped and triangle threshold",
    }
    figures = {first[0]: _pair(first[1])} if first else {}
    prefix = "" if first else "quad-scan fit emittance error x / y, "
    for key, label in names.items():
        if key in cases:
            figures[prefix + label] = _pair(cases[key])
    return figures


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--read-noise", type=float, default=8.0)
    ap.add_argument(
        "--reconstruct", action="store_true", help="also reconstruct each case"
    )
    add_store_flag(ap)
    args = ap.parse_args()
    t0 = time.perf_counter()
    scan = make_synthetic_quad_scan(
        "gaussian",
        n_particles=100_000,
        n_settings=11,
        k1_range=(-20.0, 10.0),
        screen_shape=(128, 128),
        pixel_size=(5e-4, 5e-4),
        seed=args.seed,
    )
    xs, ys = scan.pixel_centers()
    window = moment_window(scan.mean_images().double(), xs, ys, 6.0)
    truth = _summary(scan, window)
    out: dict = {"name": "background_bias", "noise_free": truth, "cases": {}}
    if args.reconstruct:
        out["reconstruction_noise_free"] = _reconstructed(scan, scan.ground_truth)
        print(
            "noise_free", out["reconstruction_noise_free"], file=sys.stderr, flush=True
        )
        out["reconstruction"] = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "daq"
        yml = write_daq_folder(
            MultiScanDataset.from_scan(scan, "scan"),
            folder,
            read_noise=args.read_noise,
            seed=args.seed,
        )
        doc = yaml.safe_load(yml.read_text())
        for name, pre in CASES.items():
            doc["preprocessing"] = pre
            path = folder / f"{name}.yaml"
            path.write_text(yaml.safe_dump(doc))
            imported = import_experiment(path)["scan"]
            got = _summary(imported, window)
            out["cases"][name] = {k: round(got[k] / truth[k] - 1.0, 4) for k in truth}
            if args.reconstruct:
                out["reconstruction"][name] = _reconstructed(
                    imported, scan.ground_truth
                )
                print(name, out["reconstruction"][name], file=sys.stderr, flush=True)
    out["wall_s"] = round(time.perf_counter() - t0, 1)
    out["commit"] = git_commit()
    emit(out, headline=headline, store_result=args.store)


if __name__ == "__main__":
    main()
