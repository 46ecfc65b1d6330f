"""Do the image *shapes* tell a beam from itself moved along the px-pz unseen direction?

The AWA 6D scans leave the trade of rms pz against the px-pz covariance unseen
in the screens' second moments (``reconstruction.unseen``); ``place_unseen``
puts it at a prior point. A beam whose px and pz both depend on x^2 is not at
that point (``family_draw_b``: emit_z -35 % there). This benchmark asks whether
the images could say so:

* **truth** (default): the beam (400 000 particles) and the same particles
  moved by the transport map to the pair prior's point, each imaged at the
  training and held-out settings and compared with a 200 000-particle
  "measurement" of the beam (another sample): relative L1 per scan and the
  Poisson log-likelihood of the measured images (200 000 counts each).
* **profile** (``--profile``, about 80 s per beam): the default reconstruction
  (``--seed``); each member moved along its own px-pz direction by ``t``
  (correlation units, -0.2 to 0.2; transport map, no refit) and its training
  images' KL distance to the measured ones (16 384 quasi-random particles, the
  same at every ``t``); where that is smallest, and the member's z emittance
  against the truth there and at ``t = 0`` (the landed placement).
* **refitted profile** (``--refit``, about 3 min per beam at one thread): the
  same members moved to ``t`` = -0.1 ... 0.1, each refitted there as the
  pipeline's refit does (covariance held), then the KL on 200 000 particles.

Usage: ``python benchmarks/unseen_shapes.py [--beams family_draw_b,...]
[--profile] [--refit] [--seed 0] [--out F.json]``
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
from _meta import emit, git_commit
from reconstruction_6d_beams import TEST_K1, TRAIN_K1, beam_seed, synthetic_beam

from diffaccel.data import make_synthetic_awa6d
from diffaccel.reconstruction import (
    ReconstructionConfig,
    ScreenForwardModel,
    image_errors,
    moment_errors,
    reconstruct,
)
from diffaccel.reconstruction.generator import BeamGenerator
from diffaccel.reconstruction.initial import fit_gaussian
from diffaccel.reconstruction.pipeline import member_refit
from diffaccel.reconstruction.unseen import (
    PLACEMENT_PARTICLES,
    _fold,
    member_moments,
    place_unseen,
    traded_pairs,
    transport_map,
    unseen_directions,
)

MEASURED_PARTICLES = 200_000
MODEL_PARTICLES = 400_000
PX_PZ = (1, 5)


def _unit_images(dataset) -> dict[str, torch.Tensor]:
    out = {}
    for name, scan in dataset:
        m = scan.mean_images().double()
        out[name] = m / m.sum((-2, -1), keepdim=True)
    return out


def _maps(dataset) -> list[torch.Tensor]:
    return [
        ScreenForwardModel.from_dataset(s).transfer_maps(s.settings) for _, s in dataset
    ]


def truth_against_moved(name: str) -> dict:
    """The truth and the truth at the pair prior's point against a measurement."""
    seed = beam_seed(name)
    k1 = TRAIN_K1 + TEST_K1
    measured = make_synthetic_awa6d(
        particles=synthetic_beam(name, MEASURED_PARTICLES, seed),
        k1_values=k1,
        seed=seed,
    )
    meas = _unit_images(measured)
    big = synthetic_beam(name, MODEL_PARTICLES, seed + 999).double()
    mu, cov = big.mean(0), torch.cov(big.T)
    a = transport_map(cov, place_unseen(cov, unseen_directions(_maps(measured), cov)))
    moved = mu + (big - mu) @ a.T
    errors = moment_errors(moved, big)
    out: dict = {
        "moved_errors": {k: errors[k] for k in ("rms_pz", "emit_z", "emit_6d")},
        "models": {},
    }
    for label, particles in (("truth", big), ("moved", moved)):
        model = _unit_images(
            make_synthetic_awa6d(particles=particles, k1_values=k1, seed=seed + 5)
        )
        out["models"][label] = {
            "relative_l1": {
                s: image_errors(model[s], meas[s])["relative_l1"] for s in meas
            },
            "log_likelihood": {
                s: float(
                    (
                        MEASURED_PARTICLES * meas[s] * model[s].clamp_min(1e-12).log()
                    ).sum()
                )
                for s in meas
            },
        }
    models = out["models"]
    out["log_likelihood_moved_minus_truth"] = {
        s: models["moved"]["log_likelihood"][s] - models["truth"]["log_likelihood"][s]
        for s in meas
    }
    return out


def reconstruction(name: str, seed: int) -> tuple:
    """The beam, its training scans and the default reconstruction of them."""
    bs = beam_seed(name)
    truth = synthetic_beam(name, MEASURED_PARTICLES, bs)
    train = make_synthetic_awa6d(particles=truth, k1_values=TRAIN_K1, seed=bs)
    result = reconstruct(
        train, ReconstructionConfig(dims=6, seed=seed), uncertainty=False
    )
    return truth, train, result


def _kl(result, train, meas: dict, particles: torch.Tensor) -> float:
    """KL distance of the measured training images to those of ``particles``
    (per image, averaged over each scan, summed over the scans)."""
    total = 0.0
    for s, scan in train:
        pred = result.forwards[s].images(particles.float(), scan.settings).double()
        pred = pred / pred.sum((-2, -1), keepdim=True)
        ratio = (meas[s] + 1e-9) / (pred + 1e-9)
        total += float((meas[s] * ratio.log()).sum((-2, -1)).mean())
    return total


def member_profiles(truth, train, result) -> dict:
    """Training-image KL of each reconstructed member along its px-pz direction."""
    maps = [result.forwards[s].transfer_maps(scan.settings) for s, scan in train]
    meas = _unit_images(train)
    ts = torch.linspace(-0.2, 0.2, 17, dtype=torch.float64)
    zero = int((ts.abs()).argmin())
    members = []
    for x in result.sample(16384, per_snapshot=True, seed=3).double():
        mu, cov = x.mean(0), torch.cov(x.T)
        v = unseen_directions(maps, cov)
        direction = v[traded_pairs(v, cov).index(PX_PZ)]
        kl, emit_z = [], []
        for t in ts:
            moved = mu + (x - mu) @ transport_map(cov, cov + t * direction).T
            kl.append(_kl(result, train, meas, moved))
            emit_z.append(float(moment_errors(moved, truth.double())["emit_z"]))
        best = min(range(len(kl)), key=kl.__getitem__)
        members.append(
            {
                "t_at_min": float(ts[best]),
                "emit_z_at_min": emit_z[best],
                "emit_z_at_0": emit_z[zero],
                "kl_gain_at_min": kl[zero] - kl[best],
                "kl": kl,
                "emit_z": emit_z,
            }
        )
    return {"t": ts.tolist(), "members": members}


REFIT_T = (-0.1, -0.05, -0.025, 0.0, 0.025, 0.05, 0.1)


def refitted_profiles(truth, train, result) -> dict:
    """As :func:`member_profiles`, each moved member refitted before its KL.

    Each member is moved to ``t`` (its covariance plus ``t`` times the unit
    px-pz direction) and refitted as the pipeline's refit does (``refit_steps``
    with the covariance held there); then its KL on 200 000 particles (the
    16 384-particle KL carries about 0.15 of shot noise, too much once the
    members differ). Points where the moved covariance is not positive
    definite are skipped (strong chirps).
    """
    config = result.config
    scans = [scan for _, scan in train]
    forwards = [result.forwards[s] for s, _ in train]
    measured = [scan.mean_images() for scan in scans]
    settings = [scan.settings for scan in scans]
    maps = [f.transfer_maps(x) for f, x in zip(forwards, settings, strict=True)]
    guess = fit_gaussian(forwards, measured, settings, maps=maps)
    meas = _unit_images(train)
    refit_member = member_refit(forwards, measured, settings, guess, config, maps)
    members = []
    for k, state in enumerate(result.snapshots):
        mu, cov = member_moments(
            state, 6, config.width, config.depth, PLACEMENT_PARTICLES, config.seed
        )
        v = unseen_directions(maps, cov)
        direction = v[traded_pairs(v, cov).index(PX_PZ)]
        rows = []
        for t in REFIT_T:
            target = cov + t * direction
            if float(torch.linalg.eigvalsh(target).min()) <= 0:
                continue
            # the move folded into the generator, as place_members does
            moved = _fold(state, transport_map(cov, target), mu)
            refit = refit_member(k, moved, target.float().double())
            gen = BeamGenerator(
                6, width=config.width, depth=config.depth, scale=torch.ones(6)
            )
            gen.load_state_dict(refit)
            with torch.no_grad():
                x = gen(MEASURED_PARTICLES, generator=torch.Generator().manual_seed(3))
            rows.append(
                {
                    "t": t,
                    "kl": _kl(result, train, meas, x),
                    "emit_z": float(
                        moment_errors(x.double(), truth.double())["emit_z"]
                    ),
                }
            )
        members.append(rows)
    return {"members": members}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--beams", default="family_draw_b,draw2028_3,chirp_curved")
    ap.add_argument("--profile", action="store_true", help="also reconstruct")
    ap.add_argument(
        "--refit", action="store_true", help="also the refitted profile (slow)"
    )
    ap.add_argument("--seed", type=int, default=0, help="training seed")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    beams = {}
    for name in args.beams.split(","):
        beams[name] = {"truth": truth_against_moved(name)}
        if args.profile or args.refit:
            built = reconstruction(name, args.seed)
        if args.profile:
            beams[name]["profile"] = member_profiles(*built)
        if args.refit:
            beams[name]["refit_profile"] = refitted_profiles(*built)
    emit(
        {
            "name": "unseen_shapes",
            "git_commit": git_commit(),
            "threads": args.threads,
            "beams": beams,
        },
        args.out,
    )


if __name__ == "__main__":
    main()
