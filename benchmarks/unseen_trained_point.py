"""Where does training leave the 6D members along the unseen directions?

After training, ``place_unseen`` moves each member to the prior point along the
directions the AWA 6D scans cannot see (``reconstruction.unseen``). This
diagnostic records, for every member of a default reconstruction, how far from
that point training had left it: the member's covariance minus the prior
point's, regressed on the unseen directions (least squares, correlation units
as ``unseen_directions``), one coefficient per traded pair (``"(1, 5)"``: px-pz,
the direction the probe of ``reconstruction.probe`` moves along; ``"(3, 4)"``:
py-z). Stop 22 (docs/generalisation_6d.md) found that a refitted member's
training-image KL favours the side of that point, whatever the truth; since
stop 23 the default probe looks only on the other side, and records the px-pz
coefficient itself (``info["unseen_probe"]["trained_t"]``, regressed on the
placed member's directions instead of the trained one's: the shared file's
seed 0 at one thread -0.044 / -0.046 / -0.050, where stop 22's computation
gave -0.043 / -0.045 / -0.049).

The members are read where the pipeline hands them to the placement
(``pipeline.place_configured`` wrapped for the first call of each run): the
reconstruction itself is the default one, unchanged. About 2.5 min per run at
one thread.

Usage: ``python benchmarks/unseen_trained_point.py --runs shared:0,draw2026_5:0
[--threads 1] [--out F.json]`` (``beam:seed``, beams of
``reconstruction_6d_beams.py``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
from _meta import emit, git_commit
from reconstruction_6d_beams import beam_scans

import diffaccel.reconstruction.pipeline as pipeline
from diffaccel.reconstruction import ReconstructionConfig, moment_errors, reconstruct
from diffaccel.reconstruction.unseen import (
    PLACEMENT_PARTICLES,
    member_moments,
    place_unseen,
    traded_pairs,
    unseen_directions,
)


def trained_points(snapshots, config, maps) -> list[dict[str, float]]:
    """Each member's displacement from the prior point along each unseen direction."""
    out = []
    for state in snapshots:
        _, cov = member_moments(
            state, 6, config.width, config.depth, PLACEMENT_PARTICLES, config.seed
        )
        v = unseen_directions(maps, cov)
        d = cov - place_unseen(cov, v, prior=config.unseen_prior)
        coef = torch.linalg.lstsq(v.reshape(v.shape[0], -1).T, d.reshape(-1, 1))
        pairs = traded_pairs(v, cov)
        out.append(
            {
                str(p): float(c)
                for p, c in zip(pairs, coef.solution.flatten(), strict=True)
            }
        )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", default="shared:0", help="beam:seed,beam:seed,...")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    found: list[list[dict[str, float]]] = []
    placed = pipeline.place_configured

    def recording(snapshots, config, maps, shift=None):
        if not found:  # the trained members (the probe places again later)
            found.append(trained_points(snapshots, config, maps))
        return placed(snapshots, config, maps, shift)

    pipeline.place_configured = recording
    runs = []
    for item in args.runs.split(","):
        name, seed = item.split(":")
        truth, train, _ = beam_scans(name, held_out=False)
        found.clear()
        result = reconstruct(
            train, ReconstructionConfig(dims=6, seed=int(seed)), uncertainty=False
        )
        errors = moment_errors(result.sample(200_000), truth)
        runs.append(
            {
                "beam": name,
                "seed": int(seed),
                "emit_z": float(errors["emit_z"]),
                "trained_t": found[0] if found else None,
            }
        )
    emit(
        {
            "name": "unseen_trained_point",
            "git_commit": git_commit(),
            "threads": args.threads,
            "runs": runs,
        },
        args.out,
    )


if __name__ == "__main__":
    main()
