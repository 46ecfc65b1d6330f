"""Where the 6D prior of the unseen directions puts each benchmark beam's truth.

The AWA 6D scans see pz-pz vs px-pz and z-z vs py-z only in one combination
each (``diffaccel.reconstruction.unseen``); ``place_unseen`` decides the rest
by a stated prior. This benchmark applies that decision to the TRUE beams of
``benchmarks/reconstruction_6d_beams.py`` (and the shared training file's
stored truth): each truth is moved to the prior point exactly as a
reconstruction's members are (``place_unseen`` with the residual covariance,
``longitudinal_map``), and the acceptance errors of the moved beam against the
truth are printed. A beam whose errors are large here fails the acceptance
whatever the training does: its longitudinal numbers are not in the data to
first order. No training; about a minute on one core.

Usage: ``python benchmarks/unseen_prior.py [--beams a,b]``
"""

from __future__ import annotations

import argparse
import os

import torch
from _meta import emit, git_commit
from _sixd import LIMITS, TRAIN
from reconstruction_6d_beams import BEAM_SEEDS, TRAIN_K1, synthetic_beam

from diffaccel.data import make_synthetic_awa6d, read_scans
from diffaccel.reconstruction import ScreenForwardModel, moment_errors
from diffaccel.reconstruction.unseen import (
    longitudinal_map,
    place_unseen,
    residual_covariance,
    unseen_directions,
)

KEYS = ("rms_z", "rms_pz", "emit_z", "emit_6d", "corr_diff_z_pz")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--beams", default=",".join(["shared", *BEAM_SEEDS]))
    args = ap.parse_args()
    torch.set_num_threads(1)
    out: dict = {
        "name": "unseen_prior",
        "git_commit": git_commit(),
        "torch": torch.__version__,
        "load_avg_1min_at_start": os.getloadavg()[0],
        "beams": {},
    }
    for name in args.beams.split(","):
        if name == "shared":
            train = read_scans(TRAIN)
            truth = train.ground_truth.to(torch.float64)
        else:
            truth = synthetic_beam(name, 200_000, BEAM_SEEDS[name])
            # the maps depend on the settings only; a small beam images fast
            train = make_synthetic_awa6d(
                particles=truth[:20_000], k1_values=TRAIN_K1, seed=BEAM_SEEDS[name]
            )
        maps = [
            ScreenForwardModel.from_dataset(scan).transfer_maps(scan.settings)
            for _, scan in train
        ]
        x = truth - truth.mean(0)
        cov = torch.cov(x.T)
        directions = unseen_directions(maps, cov)
        target = place_unseen(cov, directions, residual_covariance(x))
        e = moment_errors(x @ longitudinal_map(cov, target).T, x)
        row = {k: float(e[k]) for k in KEYS}
        row["fails"] = [k for k in KEYS if abs(row[k]) > LIMITS[k]]
        out["beams"][name] = row
    out["fails"] = {n: r["fails"] for n, r in out["beams"].items() if r["fails"]}
    emit(out)


if __name__ == "__main__":
    main()
