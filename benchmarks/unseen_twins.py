"""Gaussian twins: two beams the AWA 6D training images cannot tell apart.

Along the px-pz unseen direction (``reconstruction.unseen``) the screens'
second moments do not change to first order. For a Gaussian beam they are all
the images show, so the Gaussian with a beam's covariance and its twin moved
to the pair prior's point (the same normal draws mapped by ``transport_map``)
image almost alike, however far apart their z emittances are. This benchmark
measures, per beam of ``reconstruction_6d_beams.py``: the twins' z and 6D
emittance difference, and the relative L1 between their training images at
growing particle counts, next to that between two independent samples of the
same Gaussian (sampling noise). A twin difference that halves when the
particles quadruple is sampling noise too: no reconstruction can meet a limit
on both twins that is tighter than their emittance difference.

Usage: ``python benchmarks/unseen_twins.py [--beams family_draw_b,draw2033_1]
[--particles 500000,2000000]`` (about 4 minutes per beam and million
particles at one thread).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
from _meta import emit, git_commit
from reconstruction_6d_beams import TRAIN_K1, beam_scans

from diffaccel.data import make_synthetic_awa6d
from diffaccel.reconstruction import ScreenForwardModel, image_errors, moment_errors
from diffaccel.reconstruction.unseen import (
    place_unseen,
    transport_map,
    unseen_directions,
)


def _images(particles: torch.Tensor) -> dict[str, torch.Tensor]:
    scans = make_synthetic_awa6d(particles=particles, k1_values=TRAIN_K1, seed=0)
    return {name: scan.mean_images().double() for name, scan in scans}


def _l1(a: dict, b: dict) -> dict[str, float]:
    return {n: image_errors(a[n], b[n])["relative_l1"] for n in a}


def twins(name: str, counts: list[int]) -> dict:
    """Emittance difference and image distances of a beam's Gaussian twins."""
    truth, train, _ = beam_scans(name, held_out=False)
    x = truth - truth.mean(0)
    cov = torch.cov(x.T)
    maps = [
        ScreenForwardModel.from_dataset(s).transfer_maps(s.settings) for _, s in train
    ]
    move = transport_map(cov, place_unseen(cov, unseen_directions(maps, cov)))
    chol = torch.linalg.cholesky(cov)
    e = moment_errors(x @ move.T, x)
    out = {
        "twin_minus_beam": {k: e[k] for k in ("emit_z", "emit_6d", "rms_pz")},
        "images": [],
    }
    for n in counts:
        g = torch.Generator().manual_seed(11)
        first = torch.randn(n, 6, generator=g, dtype=torch.float64) @ chol.T
        a, b = _images(first), _images(first @ move.T)
        del first
        again = _images(torch.randn(n, 6, generator=g, dtype=torch.float64) @ chol.T)
        out["images"].append(
            {"particles": n, "twin_l1": _l1(b, a), "resample_l1": _l1(again, a)}
        )
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--beams", default="family_draw_b,draw2033_1")
    ap.add_argument("--particles", default="500000,2000000")
    ap.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = ap.parse_args()
    torch.set_num_threads(1)
    counts = [int(v) for v in args.particles.split(",")]
    beams = {name: twins(name, counts) for name in args.beams.split(",")}
    emit(
        {"name": "unseen_twins", "git_commit": git_commit(), "beams": beams},
        args.out,
    )


if __name__ == "__main__":
    main()
