"""The 4D defaults against their neighbours, judged on held-out camera settings.

Three synthetic beams of their own family (a correlated beam with a 10 % halo
twice as wide, a three-mode beam with curvature, a Gaussian with a 15 % halo
three times as wide; seeds 11-13, none of them a benchmark file) are scanned
(Quadrupole 0.1 m + Drift 1 m, 11 settings k1 = -20 ... 20 1/m^2) and imaged on
a 320 x 320 camera of 64 um pixels as histograms of 250 000 particles (Poisson
counts). Each beam is reconstructed from the even settings with the defaults
and with each setting of ``--sweep`` moved one step down and up; the odd
settings are held out.

The validation score needs no truth: the mean over the held-out settings and
both axes of ``|sigma_pred / sigma_meas - 1|``, the rms sizes of the predicted
and measured held-out images, beside the held-out relative L1. The truth's
emittance errors are reported for reading, not for choosing.

Usage: ``python benchmarks/validate_defaults.py [--beams 0 1 2] [--seeds 0 1]
[--threads 2] [--store]``

Last line: ``{"name": "validate_defaults", "runs": [{"beam": .., "seed": ..,
"setting": .., "value": .., "held_out_rms_err": .., "held_out_l1": ..,
"emit_x_rel_err": .., "emit_y_rel_err": .., "seconds": ..}, ...], "chosen":
{SETTING: VALUE}, "default": {SETTING: VALUE}, "mean_held_out_rms_err":
{SETTING: {VALUE: ..}}}``.
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import replace

import torch
from _meta import add_store_flag, emit

from diffaccel.data.synthetic import make_synthetic_quad_scan, sample_preset_beam
from diffaccel.reconstruction import ReconstructionConfig, reconstruct
from diffaccel.reconstruction.evaluation import predict_dataset
from diffaccel.reconstruction.metrics import image_errors
from diffaccel.reconstruction.uncertainty import image_moments

PIXELS = 320
PIXEL_M = 64e-6
#: (preset, halo fraction, halo width factor) of each validation beam.
BEAMS = (("correlated", 0.10, 2.0), ("nonlinear", 0.0, 1.0), ("gaussian", 0.15, 3.0))
#: Each setting's neighbours (one step down, one step up).
SWEEP = {
    "penalty_end": (3e3, 3e4),
    "n_particles": (3072, 12288),
    "steps": (150, 600),
}


def beam(kind: int, n: int = 250_000) -> torch.Tensor:
    """Bmad particles ``(n, 6)`` of validation beam ``kind`` (0, 1, 2)."""
    g = torch.Generator().manual_seed(11 + kind)
    preset, halo, wide = BEAMS[kind]
    p = sample_preset_beam(preset, n, g)
    p[: int(halo * n), :4] *= wide
    p[:, :4] *= 0.5
    return p - p.mean(0)


def emittance(p: torch.Tensor, i: int) -> float:
    c = torch.cov(p[:, i : i + 2].T.to(torch.float64))
    return float(torch.linalg.det(c).sqrt())


def rms_sizes(images: torch.Tensor) -> torch.Tensor:
    """Rms x and y [m] of images ``(K, H, W)`` -> ``(K, 2)``."""
    xs = (torch.arange(PIXELS, dtype=torch.float64) - (PIXELS - 1) / 2) * PIXEL_M
    m = image_moments(images.to(torch.float64), xs, xs)
    return torch.stack([m[:, 2], m[:, 4]], -1).clamp_min(0).sqrt()


def run(kind: int, config: ReconstructionConfig, seed: int) -> dict:
    """One reconstruction of beam ``kind`` (data and training ``seed``)."""
    truth = beam(kind)
    ds = make_synthetic_quad_scan(
        particles=truth,
        n_settings=11,
        k1_range=(-20.0, 20.0),
        screen_shape=(PIXELS, PIXELS),
        pixel_size=(PIXEL_M, PIXEL_M),
        image_method="histogram",
        seed=100 * seed + kind,
    )
    t0 = time.perf_counter()
    rec = reconstruct(
        ds,
        replace(config, seed=seed),
        train_indices=list(range(0, 11, 2)),
        uncertainty=False,
    )
    seconds = time.perf_counter() - t0
    held = list(range(1, 11, 2))
    pred = next(iter(predict_dataset(rec, ds, n_particles=200_000).values()))
    meas = ds.mean_images()
    size_err = rms_sizes(pred[held]) / rms_sizes(meas[held]) - 1
    m = rec.moments(50_000)
    return {
        "held_out_rms_err": round(float(size_err.abs().mean()), 4),
        "held_out_l1": round(image_errors(pred[held], meas[held])["relative_l1"], 4),
        "emit_x_rel_err": round(m["emit_x"]["mean"] / emittance(truth, 0) - 1, 4),
        "emit_y_rel_err": round(m["emit_y"]["mean"] / emittance(truth, 2) - 1, 4),
        "seconds": round(seconds, 1),
    }


def headline(result: dict) -> dict[str, str]:
    """The docs page's figures: each setting's mean held-out rms error by value."""
    figures = {}
    for name, by_value in result["mean_held_out_rms_err"].items():
        cells = ", ".join(f"{v}: {100 * e:.2f} %" for v, e in by_value.items())
        key = f"{name} (default {result['default'][name]:g}): held-out rms error"
        figures[key] = f"{cells}; lowest at {result['chosen'][name]:g}"
    return figures


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--beams", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument(
        "--seeds",
        type=int,
        nargs="+",
        default=[0, 1],
        help="Data (images) and training seeds; every beam is run at each.",
    )
    add_store_flag(ap)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    base = ReconstructionConfig(dims=4)
    runs = []
    cases = [("default", None, base)]
    for name, values in SWEEP.items():
        cases += [(name, v, replace(base, **{name: v})) for v in values]
    for kind in args.beams:
        for seed in args.seeds:
            for name, value, config in cases:
                r = {"beam": kind, "seed": seed, "setting": name, "value": value}
                r.update(run(kind, config, seed))
                runs.append(r)
                print(r, flush=True)
    chosen, default, means = {}, {}, {}
    for name in SWEEP:
        default[name] = getattr(base, name)
        score = {default[name]: []}
        for r in runs:
            if r["setting"] == "default":
                score[default[name]].append(r["held_out_rms_err"])
            elif r["setting"] == name:
                score.setdefault(r["value"], []).append(r["held_out_rms_err"])
        means[name] = {
            f"{v:g}": round(statistics.fmean(e), 4) for v, e in score.items()
        }
        chosen[name] = min(score, key=lambda v: statistics.fmean(score[v]))
    emit(
        {
            "name": "validate_defaults",
            "runs": runs,
            "chosen": chosen,
            "default": default,
            "mean_held_out_rms_err": means,
        },
        headline=headline,
        store_result=args.store,
    )


if __name__ == "__main__":
    main()
