"""One beam imaged at camera resolutions: the fitted emittance must not depend on them.

A 4D quadrupole scan (Quadrupole 0.1 m + Drift 1 m, 11 settings k1 = -20 ... 20
1/m^2) of a Gaussian beam with a 12 % halo (0.75 mm / 0.3 mrad core, the halo
2.5 times wider; the halo holds about 45 % of the beam's variance) is imaged on
a 20.48 mm square screen as histograms of 200 000 particles (shot noise of a
camera counting that many electrons), at several pixel counts per axis, and
reconstructed with the default settings, except the loss smoothing
(``--loss-smoothing``, default ``auto``), at several numbers of training
particles per step. Each cell reports the normalised x and y emittance errors
against the truth and their reported std.

Usage: ``python benchmarks/resolution.py [--pixels 64 128 256 400]
[--particles 6144 16384 65536] [--threads 2] [--out FILE.json]``

Prints one JSON object on the last line:
``{"max_abs_emit_rel_err": ..., "grid": [{"pixels": .., "n_particles": ..,
"emit_x_rel_err": .., "emit_y_rel_err": .., "emit_x_rel_std": ..,
"emit_y_rel_std": .., "loss_smoothing_px": .., "seconds": ..}, ...], ...}``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch
from _meta import add_store_flag, emit, span

from diffaccel.data.synthetic import make_synthetic_quad_scan, sample_preset_beam
from diffaccel.reconstruction import ReconstructionConfig, reconstruct
from diffaccel.reconstruction.training import loss_smoothing_for

SCREEN_M = 20.48e-3


def halo_beam(n: int = 200_000, seed: int = 1) -> torch.Tensor:
    """Bmad particles ``(n, 6)``: a Gaussian core with a 12 % halo 2.5x wider."""
    g = torch.Generator().manual_seed(seed)
    beam = sample_preset_beam("gaussian", n, g)
    beam[: int(0.12 * n), :4] *= 2.5
    beam[:, :4] *= 0.5
    return beam - beam.mean(0)


def emittance(p: torch.Tensor, i: int) -> float:
    """Geometric rms emittance [m] of coordinates ``i, i + 1``."""
    c = torch.cov(p[:, i : i + 2].T.to(torch.float64))
    return float(torch.linalg.det(c).sqrt())


def cell(
    truth: torch.Tensor, pixels: int, n_particles: int, seed: int, smoothing: object
) -> dict:
    """Reconstruct the scan imaged on ``pixels`` x ``pixels`` at ``n_particles``."""
    ds = make_synthetic_quad_scan(
        particles=truth,
        n_settings=11,
        k1_range=(-20.0, 20.0),
        screen_shape=(pixels, pixels),
        pixel_size=(SCREEN_M / pixels, SCREEN_M / pixels),
        image_method="histogram",
        seed=seed,
    )
    config = ReconstructionConfig(
        dims=4, n_particles=n_particles, seed=seed, loss_smoothing=smoothing
    )
    t0 = time.perf_counter()
    rec = reconstruct(ds, config)
    seconds = time.perf_counter() - t0
    m = rec.moments(50_000)
    out = {"pixels": pixels, "n_particles": n_particles}
    for axis, i in (("x", 0), ("y", 2)):
        true = emittance(truth, i)
        out[f"emit_{axis}_rel_err"] = round(m[f"emit_{axis}"]["mean"] / true - 1, 4)
        out[f"emit_{axis}_rel_std"] = round(m[f"emit_{axis}"]["std"] / true, 4)
    sm = loss_smoothing_for(config, [ds.mean_images()], [config.blur_for(ds)])[0]
    out["loss_smoothing_px"] = round(sm, 2)
    out["seconds"] = round(seconds, 1)
    return out


def headline(result: dict) -> dict[str, str]:
    """The docs page's figures: the largest emittance error over the grid, std."""
    grid = result["grid"]
    pixels = [c["pixels"] for c in grid]
    particles = [c["n_particles"] / 1024 for c in grid]
    cells = (
        f"{span(pixels, 'd')} pixels x {span(particles, '.0f').replace('-', 'k-')}k "
        "particles"
    )
    std = [100 * c[f"emit_{a}_rel_std"] for c in grid for a in "xy"]
    given = result["loss_smoothing"]
    how = "default settings" if given == "auto" else f"--loss-smoothing {given}"
    return {
        f"largest |emittance error| over {cells}, {how}": (
            f"{100 * result['max_abs_emit_rel_err']:.1f} %"
        ),
        "reported std": f"{span(std, '.0f')} %",
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pixels", type=int, nargs="+", default=[64, 128, 256, 400])
    parser.add_argument(
        "--particles", type=int, nargs="+", default=[6144, 16384, 65536]
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--loss-smoothing",
        default="auto",
        help="'auto' (sized by the data) or a number of pixels; 'default' for the "
        "dims default",
    )
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=None)
    add_store_flag(parser)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    truth = halo_beam()
    smoothing = {"auto": "auto", "default": None}.get(args.loss_smoothing)
    if smoothing is None and args.loss_smoothing != "default":
        smoothing = float(args.loss_smoothing)
    grid = []
    for pixels in args.pixels:
        for n in args.particles:
            grid.append(cell(truth, pixels, n, args.seed, smoothing))
            print(grid[-1], flush=True)
    worst = max(max(abs(c["emit_x_rel_err"]), abs(c["emit_y_rel_err"])) for c in grid)
    emit(
        {
            "name": "resolution",
            "max_abs_emit_rel_err": worst,
            "loss_smoothing": args.loss_smoothing,
            "grid": grid,
        },
        args.out,
        headline=headline,
        store_result=args.store,
    )


if __name__ == "__main__":
    main()
