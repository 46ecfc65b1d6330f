"""The image-moment Gaussian placed at the pair prior's point, against the truth.

A 6D run starts from :func:`~diffaccel.reconstruction.initial.fit_gaussian`,
the Gaussian that fits the training images' second moments with the largest
determinant, and places its members along the unseen directions at the end
(``reconstruction.unseen``). This benchmark places the *initial guess* there
too, with no training, and prints its longitudinal errors against the beam's
truth: what the image moments alone say about z, pz and the chirp. Stop 29
(docs/generalisation_6d.md) used it to find that on tilted3100_2 training
moved the seen z-pz correlation by +0.03 (emit_z -30 %) where the guess is
within 0.007 (+7 %).

Usage: ``python benchmarks/guess_placed.py --beams tilted3100_2,tilted3000_13``
(a few seconds per beam: the data set is simulated, nothing is trained).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
from _meta import emit, git_commit
from reconstruction_6d_beams import beam_scans

from diffaccel.reconstruction import ReconstructionConfig, ScreenForwardModel
from diffaccel.reconstruction.initial import fit_gaussian
from diffaccel.reconstruction.unseen import place_unseen, unseen_directions


def _longitudinal(cov: torch.Tensor) -> dict[str, float]:
    s = cov.diagonal().sqrt()
    return {
        "rms_z": float(s[4]),
        "rms_pz": float(s[5]),
        "corr_z_pz": float(cov[4, 5] / (s[4] * s[5])),
        "emit_z": float(torch.linalg.det(cov[4:6, 4:6]).sqrt()),
    }


def guess_placed(name: str) -> dict:
    """Relative errors (fractions; z-pz as a difference) of the placed guess and
    of the placed truth covariance (what the prior alone costs)."""
    truth, train, _ = beam_scans(name, held_out=False)
    config = ReconstructionConfig(dims=6)
    forwards, measured, settings = [], [], []
    for _, scan in train:
        forwards.append(
            ScreenForwardModel.from_dataset(scan, blur_pixels=config.blur_for(scan))
        )
        measured.append(scan.mean_images())
        settings.append(scan.settings)
    maps = [f.transfer_maps(s) for f, s in zip(forwards, settings, strict=True)]
    guess = fit_gaussian(forwards, measured, settings, maps=maps).cov.double()
    cov = torch.cov(truth.T.double())
    t = _longitudinal(cov)
    out = {"truth_corr_z_pz": t["corr_z_pz"]}
    for label, c in (("guess_placed", guess), ("truth_placed", cov)):
        p = _longitudinal(place_unseen(c, unseen_directions(maps, c)))
        out[label] = {
            "rms_z": p["rms_z"] / t["rms_z"] - 1,
            "rms_pz": p["rms_pz"] / t["rms_pz"] - 1,
            "emit_z": p["emit_z"] / t["emit_z"] - 1,
            "corr_diff_z_pz": p["corr_z_pz"] - t["corr_z_pz"],
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--beams", default="tilted3100_2,tilted3100_7,tilted3000_13")
    ap.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = ap.parse_args()
    torch.set_num_threads(1)
    beams = {name: guess_placed(name) for name in args.beams.split(",")}
    emit(
        {"name": "guess_placed", "git_commit": git_commit(), "beams": beams},
        args.out,
    )


if __name__ == "__main__":
    main()
