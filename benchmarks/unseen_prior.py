"""Where each prior of the 6D unseen directions puts a beam's truth (no training).

``place_unseen`` moves every 6D ensemble member along the longitudinal
covariance directions the AWA 6D scans cannot see (``reconstruction.unseen``)
to a prior point. A reconstruction cannot do better there than the prior does
on the true beam, so this benchmark applies each prior (``"pair"``, the
default, and the earlier ``"gaussian"``) to the truth itself: the beams of
``reconstruction_6d_beams.py`` and random draws of the shared file's README
family (the ranges of ``reconstruction_6d_beams.FAMILY``'s comment; fresh
draws of ``--rng``, no screen-fraction cut). Errors are of the moved truth
against the truth, with the issue-9 limits of the quantities the move changes
(rms pz and z, z and 6D emittance, z-pz correlation).

Usage: ``python benchmarks/unseen_prior.py [--draws 30] [--rng 777]``
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from _meta import emit, git_commit
from _sixd import LIMITS
from reconstruction_6d_beams import (
    BEAM_SEEDS,
    TRAIN_K1,
    family_beam,
    family_draw,
    synthetic_beam,
)

from diffaccel.data import make_synthetic_awa6d
from diffaccel.reconstruction import ScreenForwardModel, moment_errors
from diffaccel.reconstruction.unseen import (
    UNSEEN_PRIORS,
    place_unseen,
    transport_map,
    unseen_directions,
)

KEYS = ("rms_z", "rms_pz", "emit_z", "emit_6d", "corr_diff_z_pz")


def placed_errors(truth: torch.Tensor, maps: list[torch.Tensor]) -> dict:
    """Errors of the truth moved to each prior's point, and whether within limits."""
    x = truth - truth.mean(0)
    cov = torch.cov(x.T)
    directions = unseen_directions(maps, cov)
    out = {}
    for prior in UNSEEN_PRIORS:
        a = transport_map(cov, place_unseen(cov, directions, prior=prior))
        e = moment_errors(x @ a.T, x)
        row = {k: e[k] for k in KEYS}
        row["within_limits"] = all(abs(row[k]) <= LIMITS[k] for k in KEYS)
        out[prior] = row
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--draws", type=int, default=30)
    ap.add_argument("--rng", type=int, default=777)
    ap.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = ap.parse_args()
    torch.set_num_threads(1)
    probe = make_synthetic_awa6d(
        particles=synthetic_beam("correlated", 20_000, 0), k1_values=TRAIN_K1, seed=0
    )
    maps = [
        ScreenForwardModel.from_dataset(s).transfer_maps(s.settings) for _, s in probe
    ]
    beams = {
        name: placed_errors(synthetic_beam(name, 200_000, seed), maps)
        for name, seed in BEAM_SEEDS.items()
    }
    rng = np.random.default_rng(args.rng)
    draws = []
    for k in range(args.draws):
        params = family_draw(rng)
        g = torch.Generator().manual_seed(args.rng + k)
        draws.append(
            {"params": params, **placed_errors(family_beam(params, 200_000, g), maps)}
        )
    summary = {
        prior: {
            "draws_within_limits": sum(d[prior]["within_limits"] for d in draws),
            "worst_abs_emit_z": max(abs(d[prior]["emit_z"]) for d in draws),
            "median_abs_emit_z": float(
                np.median([abs(d[prior]["emit_z"]) for d in draws])
            ),
            "beams_within_limits": [
                n for n, b in beams.items() if b[prior]["within_limits"]
            ],
        }
        for prior in UNSEEN_PRIORS
    }
    out = {
        "name": "unseen_prior",
        "git_commit": git_commit(),
        "draws": args.draws,
        "rng": args.rng,
        "summary": summary,
        "beams": beams,
        "family_draws": draws,
    }
    emit(out, args.out)


if __name__ == "__main__":
    main()
