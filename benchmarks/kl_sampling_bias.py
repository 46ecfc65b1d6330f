"""Where the training's KL image distance puts a sampled beam's size (no training).

Training compares images of ``N`` particles drawn afresh at every step with the
measured images through the KL distance. A noisy simulated image has
``E[log s_hat] < log s``, so the expected distance is lowest for a beam somewhat
*wider* than the one the particles came from. This benchmark measures that on
the AWA 6D audit beams of ``reconstruction_6d_beams.py``: the truth (200 000
particles) is scaled by factors about its mean, ``--draws`` random subsets of
``--particles`` are imaged through the training forward models of the
training scans (the default 6D point spread and 1-pixel loss smoothing), and
the factor of least mean distance (vertex of a parabola through the factors)
is reported for each ``sampling_offset`` ``c`` (``eps = c kappa / N`` added to
every simulated pixel; ``ReconstructionConfig.sampling_offset``). 1 is
unbiased; the rms sizes of a reconstruction follow it.

Usage: ``python benchmarks/kl_sampling_bias.py [--beams a,b] [--particles 16384]
[--draws 8] [--offsets 0,0.125,0.25,0.5]``
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from _meta import emit, git_commit
from reconstruction_6d_beams import BEAM_SEEDS, TRAIN_K1, synthetic_beam

from diffaccel.data import make_synthetic_awa6d
from diffaccel.reconstruction import ReconstructionConfig, ScreenForwardModel
from diffaccel.reconstruction.training import _smoothed  # training's smoothing

SCALES = np.linspace(0.985, 1.025, 9)
DEFAULT_BEAMS = (
    "chirp_negative",
    "chirp_curved",
    "wide",
    "double_horn",
    "nonlinear_ypy",
    "family_draw_b",
)


def training_views(truth: torch.Tensor, seed: int) -> list[tuple]:
    """``(forward, smoothed measured images, settings, kappa)`` per training scan.

    The forward models and measured images are smoothed as training smooths them
    (``training._smoothed``); ``kappa`` is the forward model's
    :meth:`~diffaccel.reconstruction.ScreenForwardModel.pixel_kernel_sum_sq`.
    """
    config = ReconstructionConfig(dims=6)
    data = make_synthetic_awa6d(particles=truth, k1_values=TRAIN_K1, seed=seed)
    scans = [scan for _, scan in data]
    forwards = [
        ScreenForwardModel.from_dataset(scan, blur_pixels=config.blur_for(scan))
        for scan in scans
    ]
    measured = [scan.mean_images().float() for scan in scans]
    forwards, measured = _smoothed(forwards, measured, config.loss_smoothing)
    return [
        (f, m.clamp_min(1e-12), scan.settings, f.pixel_kernel_sum_sq())
        for f, m, scan in zip(forwards, measured, scans, strict=True)
    ]


def best_scales(
    name: str, n: int, draws: int, offsets: list[float]
) -> dict[str, float]:
    """Scale factor of least expected KL distance for each offset ``c``."""
    seed = BEAM_SEEDS[name]
    truth = synthetic_beam(name, 200_000, seed)
    views = training_views(truth, seed)
    g = torch.Generator().manual_seed(seed)
    subsets = [torch.randperm(truth.shape[0], generator=g)[:n] for _ in range(draws)]
    mean = truth.mean(0)
    totals = {c: np.zeros(len(SCALES)) for c in offsets}
    for i, r in enumerate(SCALES):
        scaled = mean + r * (truth - mean)
        for idx in subsets:
            for fwd, m, settings, kappa in views:
                sim = fwd.images(scaled[idx].float(), settings)
                s = sim / sim.sum((-2, -1), keepdim=True).clamp_min(1e-6)
                for c in offsets:
                    q = s + c * kappa / n if c > 0 else s.clamp_min(1e-12)
                    totals[c][i] += float((m * (m / q).log()).sum()) / draws
    out = {}
    for c, v in totals.items():
        a, b, _ = np.polyfit(SCALES, v, 2)
        out[f"{c:g}"] = float(-b / (2 * a))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--beams", default=",".join(DEFAULT_BEAMS))
    ap.add_argument("--particles", type=int, default=16384)
    ap.add_argument("--draws", type=int, default=8)
    ap.add_argument("--offsets", default="0,0.125,0.25,0.5")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    offsets = [float(c) for c in args.offsets.split(",")]
    beams = args.beams.split(",")
    per_beam = {b: best_scales(b, args.particles, args.draws, offsets) for b in beams}
    summary = {
        f"{c:g}": {
            "min": min(v[f"{c:g}"] for v in per_beam.values()),
            "max": max(v[f"{c:g}"] for v in per_beam.values()),
        }
        for c in offsets
    }
    emit(
        {
            "name": "kl_sampling_bias",
            "particles": args.particles,
            "draws": args.draws,
            "scales": SCALES.tolist(),
            "best_scale_by_offset": per_beam,
            "range_by_offset": summary,
            "git_commit": git_commit(),
        },
        args.out,
    )


if __name__ == "__main__":
    main()
