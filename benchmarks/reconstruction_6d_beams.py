"""6D reconstruction over several beams and seeds: is the default robust?

The 6D acceptance numbers must hold "on other beams in this
geometry" and not only on the shared file. This benchmark reconstructs, with the
default 6D settings (``ReconstructionConfig(dims=6, seed=s)``, in-process),
each beam with several training seeds and reports every error of the
acceptance (rms sizes, emittances, correlations) per run and as mean, std and
worst |error| over the seeds, next to the limits. Each run also reports the
relative std of its rms sizes and emittances (the moment posterior of
``reconstruct``'s default, attached after the timed training) and, for every
error outside its limit, that error in units of the reported std.

Beams (all in the AWA 6D layout of ``data.make_synthetic_awa6d``: quadrupole x
TDC off/on x dipole off/on, 96 x 96 pixel histogram images as in the shared
files; training on the even quadrupole settings k1 = -12, -6, 0, 6, 12,
held-out images on the odd ones):

- ``shared``: the shared training file ``sixd_synthetic_train.h5`` (its stored
  ground truth; no held-out images, the test file is the acceptance's, not
  ours to tune on);
- ``correlated``: the ``correlated`` preset (x-px -0.6, y-py 0.5, chirp -0.7);
- ``nonlinear_ypy``: the three-mode ``nonlinear`` preset with y-py correlation
  0.93 and half the energy spread;
- ``gaussian_coupled``: a Gaussian with y-py 0.69, chirp (z-pz 0.38) and an
  x-z tilt (0.30);
- the shared file's family as its README describes it (non-Gaussian, energy
  chirp with curvature, x-z tilt, correlated in all six dimensions), our own
  construction (:data:`FAMILY`, :func:`family_beam`): ``chirp_curved``
  (z-pz 0.79), ``chirp_negative`` (-0.61, transverse curvature) and
  ``chirp_weak_tilted`` (0.23, strong curvature, y-pz term), and two random
  draws of its parameters and sizes (``family_draw_a``: z-pz 0.57, y-pz term;
  ``family_draw_b``: z-pz -0.95, x-z -0.48, px-pz 0.27), see :data:`FAMILY`;
- beams of other kinds (:data:`OTHER_KINDS`): ``double_horn`` (double-horn
  current profile of a compressed bunch) and ``wide`` (2x the shared file's rms
  x, 1.6x its rms y, a third of its energy spread);
- ``draw<R>_<K>`` (not in the default list): the K-th random README-family beam
  of numpy seed R (:func:`family_draw`, the ranges of ``family_draw_a/b``;
  ``draw2026_0`` ... ``draw2026_5``: beams no default was chosen on);
- ``tilted<R>_<K>`` (not in the default list): the K-th random beam of numpy
  seed R built as the shared file's stored truth is (:func:`tilted_beam`,
  :func:`tilted_draw`): a Gaussian 4D transverse beam, z tilted along a mix of
  x and px, and pz = h z + c (z^2 - <z^2>) + spread, with no transverse
  curvature (the family draws' ``kappa``), so its px-pz partial correlation is
  zero;
- ``xyrot<D>_<beam>`` (not in the default list): any of the above turned in
  x-y by D degrees (x, px and y, py rotated together, as a solenoid leaves a
  beam): a beam with real x-y coupling, e.g. ``xyrot45_correlated``.

Their fails are listed apart (``fails_family``, ``fails_other_kinds``,
``fails_presets``); a run fails where any seed exceeds a limit, the held-out
relative L1 (limit 0.15 per scan) included (``held_out_l1_<scan>``).

The synthetic beams have 200 000 particles (truth and images). Prints one JSON
object (benchmarks/_meta.py). Times are in-process training times; under load
they are inflated (``load_avg_1min_*``).

Usage: ``python benchmarks/reconstruction_6d_beams.py [--beams a,b] [--set F=V] [--seeds
0,1,2] [--threads N]``
"""

from __future__ import annotations

import argparse
import math
import os
import re
import time
from pathlib import Path

import numpy as np
import torch
from _meta import add_store_flag, emit, git_commit
from _sixd import HELD_OUT_L1, KEYS, LIMITS, TRAIN

from diffaccel.data import make_synthetic_awa6d, read_scans
from diffaccel.data.synthetic import AWA6D_BEAM_SCALE, sample_preset_beam
from diffaccel.reconstruction import (
    ReconstructionConfig,
    image_errors,
    moment_errors,
    reconstruct,
)
from diffaccel.reconstruction.pipeline import attach_uncertainty
from diffaccel.reconstruction.prior_dependence import prior_dependence

TRAIN_K1 = (-12.0, -6.0, 0.0, 6.0, 12.0)
TEST_K1 = (-9.0, -3.0, 3.0, 9.0)
#: Seed of each synthetic beam (its particles and image noise).
BEAM_SEEDS = {
    "correlated": 2,
    "nonlinear_ypy": 3,
    "gaussian_coupled": 4,
    "chirp_curved": 5,
    "chirp_negative": 6,
    "chirp_weak_tilted": 7,
    # the generalisation beams: two
    # family draws (FAMILY) and two of other kinds (OTHER_KINDS)
    "family_draw_a": 11,
    "family_draw_b": 12,
    "double_horn": 13,
    "wide": 14,
}
#: Beams of the shared file's family as its README describes it (non-Gaussian,
#: energy chirp with curvature, x-z tilt, correlated in all six dimensions), our
#: own construction and parameters (not fitted to that file): chirp h [1/m],
#: curvature c [1/m^2] (pz += h z + c (z^2 - <z^2>)), uncorrelated energy
#: spread, x-z tilt (z += tilt x), x-px and y-py correlations, a transverse
#: curvature (px += kappa x^2) and a weak y-pz term.
FAMILY = {
    "chirp_curved": dict(
        h=2.0,
        c=800.0,
        spread=1.0e-3,
        tilt=0.4,
        xpx=-0.4,
        ypy=0.5,
        kappa=0.0,
        ypz=0.0,
    ),
    "chirp_negative": dict(
        h=-1.5,
        c=-1500.0,
        spread=0.6e-3,
        tilt=-0.6,
        xpx=0.3,
        ypy=-0.3,
        kappa=300.0,
        ypz=0.0,
    ),
    "chirp_weak_tilted": dict(
        h=0.8,
        c=2500.0,
        spread=1.5e-3,
        tilt=0.25,
        xpx=-0.6,
        ypy=0.2,
        kappa=-200.0,
        ypz=0.5,
    ),
    # Two further members for the generalisation check, NOT chosen by hand:
    # draws of numpy.random.default_rng(20261123), uniform in ranges plausible
    # for AWA at 43 MeV (rounded to 3 digits; per draw in this order): sign of
    # h, |h| 0.5-4 1/m, sign of c, |c| 300-3000 1/m^2, spread 0.3-2e-3, sign of
    # tilt, |tilt| 0.1-0.7, xpx, ypy -0.95..0.95, kappa -400..400 1/m, ypz
    # -0.5..0.5 1/m, sizes (rms before the correlations) sx 0.35-0.7 mm, spx
    # 0.18-0.35 mrad, sy, spy likewise, sz 0.5-0.9 mm (the three beams above:
    # 0.5 mm, 0.26 mrad, 0.8 mm). Kept: the first two draws with at least
    # 99.8 % of the beam on both screens at every setting (the shared file's
    # truth: 99.9 %): draws 2 and 3; draw 1 lost 0.27 % at k1 = -12, 4 MV (an
    # earlier sz range up to 1.2 mm lost 0.3-0.8 % on most draws: the TDC
    # streak overfills the 96-pixel screens).
    "family_draw_a": dict(
        h=2.14,
        c=507.0,
        spread=1.86e-3,
        tilt=0.18,
        xpx=-0.788,
        ypy=-0.187,
        kappa=135.0,
        ypz=0.473,
        sx=6.71e-4,
        spx=1.98e-4,
        sy=6.98e-4,
        spy=2.50e-4,
        sz=6.05e-4,
    ),
    "family_draw_b": dict(
        h=-2.41,
        c=-539.0,
        spread=0.315e-3,
        tilt=-0.548,
        xpx=0.597,
        ypy=-0.84,
        kappa=-220.0,
        ypz=0.365,
        sx=6.92e-4,
        spx=3.32e-4,
        sy=5.41e-4,
        spy=3.05e-4,
        sz=7.17e-4,
    ),
}
#: Beams of other kinds a user would plausibly measure (generalisation check):
#: ``double_horn`` (:func:`double_horn_beam`: the current profile of a
#: magnetically compressed bunch, arcsine-like with spikes at head and tail,
#: residual chirp with curvature; z kurtosis 1.6) and ``wide`` (a family beam
#: with 2.0x the shared file's rms x, 1.6x its rms y, 1.35x its rms px, 0.37x
#: its energy spread, converging in y: it fills the screens differently, rms
#: 1.9-14 pixels where the shared file's truth has 0.4-15; 99.88 % on screen).
OTHER_KINDS = {
    "double_horn": dict(
        half_length=1.3e-3, horn_width=0.08, h=-2.5, c=1200.0, spread=0.7e-3
    ),
    "wide": dict(
        h=1.5,
        c=600.0,
        spread=0.6e-3,
        tilt=0.3,
        xpx=-0.85,
        ypy=-0.6,
        kappa=0.0,
        ypz=0.0,
        sx=1.0e-3,
        spx=3.5e-4,
        sy=0.75e-3,
        spy=2.6e-4,
        sz=0.7e-3,
    ),
}


def curved_chirp(params: dict, z: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
    """pz = h z + c (z^2 - <z^2>) + spread * noise (``params`` h, c, spread)."""
    return (
        params["h"] * z
        + params["c"] * (z**2 - (z**2).mean())
        + params["spread"] * noise
    )


def family_beam(params: dict, n: int, g: torch.Generator) -> torch.Tensor:
    """A beam of the shared file's family (see :data:`FAMILY`), Bmad ``(n, 6)``.

    Sizes ``sx, spx, sy, spy, sz`` [m, 1, m, 1, m] default to 0.5 mm, 0.26 mrad,
    0.5 mm, 0.26 mrad, 0.8 mm.
    """
    u = torch.randn(n, 6, generator=g, dtype=torch.float64)
    sx, sy = params.get("sx", 5e-4), params.get("sy", 5e-4)
    spx, spy = params.get("spx", 2.6e-4), params.get("spy", 2.6e-4)
    sz = params.get("sz", 8e-4)
    x = sx * u[:, 0]
    px = spx * (params["xpx"] * u[:, 0] + (1 - params["xpx"] ** 2) ** 0.5 * u[:, 1])
    px = px + params["kappa"] * (x**2 - (x**2).mean())
    y = sy * u[:, 2]
    py = spy * (params["ypy"] * u[:, 2] + (1 - params["ypy"] ** 2) ** 0.5 * u[:, 3])
    z = sz * u[:, 4] + params["tilt"] * x
    pz = curved_chirp(params, z, u[:, 5]) + params["ypz"] * y
    return torch.stack([x, px, y, py, z, pz], -1)


def double_horn_beam(params: dict, n: int, g: torch.Generator) -> torch.Tensor:
    """A compressed bunch with a double-horn current profile, Bmad ``(n, 6)``.

    z = half_length sin(theta) with theta uniform in (-pi/2, pi/2) (the
    arcsine profile of a folded chirp: current spikes at head and tail),
    smeared by ``horn_width`` x half_length; pz = h z + c (z^2 - <z^2>) +
    spread; transverse Gaussian of the shared file's sizes with x-px -0.7,
    y-py 0.8 and a weak x-z tilt (z += 0.2 x).
    """
    u = torch.randn(n, 6, generator=g, dtype=torch.float64)
    theta = (torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * math.pi
    a = params["half_length"]
    x = 5e-4 * u[:, 0]
    px = 2.6e-4 * (-0.7 * u[:, 0] + 0.51**0.5 * u[:, 1])
    y = 4.6e-4 * u[:, 2]
    py = 2.6e-4 * (0.8 * u[:, 2] + 0.6 * u[:, 3])
    z = a * torch.sin(theta) + params["horn_width"] * a * u[:, 4] + 0.2 * x
    pz = curved_chirp(params, z, u[:, 5])
    return torch.stack([x, px, y, py, z, pz], -1)


def _sign(rng: np.random.Generator) -> float:
    return 1.0 if rng.random() < 0.5 else -1.0


def _chirp_draw(rng: np.random.Generator) -> dict:
    """Chirp h [1/m], curvature c [1/m^2] and spread of a random draw."""
    return {
        "h": _sign(rng) * rng.uniform(0.5, 4.0),
        "c": _sign(rng) * rng.uniform(300.0, 3000.0),
        "spread": rng.uniform(0.3e-3, 2e-3),
    }


def family_draw(rng: np.random.Generator) -> dict:
    """Parameters of one README-family beam (ranges of the two family draws above)."""
    return {
        **_chirp_draw(rng),
        "tilt": _sign(rng) * rng.uniform(0.1, 0.7),
        "xpx": rng.uniform(-0.95, 0.95),
        "ypy": rng.uniform(-0.95, 0.95),
        "kappa": rng.uniform(-400.0, 400.0),
        "ypz": rng.uniform(-0.5, 0.5),
        "sx": rng.uniform(3.5e-4, 7e-4),
        "spx": rng.uniform(1.8e-4, 3.5e-4),
        "sy": rng.uniform(3.5e-4, 7e-4),
        "spy": rng.uniform(1.8e-4, 3.5e-4),
        "sz": rng.uniform(5e-4, 9e-4),
    }


def tilted_beam(params: dict, n: int, g: torch.Generator) -> torch.Tensor:
    """A beam built as the shared file's stored truth reads, Bmad ``(n, 6)``.

    That truth (50 000 particles) is Gaussian in x, px, y, py (kurtosis within
    0.03; px and py carry no x^2 or y^2 term), its z is a tilt along x and px
    plus an independent part (z = 3.3 x + 5.7 px + 0.33 mm rms), and
    pz = 4.0 z + 2000 (z^2 - <z^2>) + 0.50e-3 rms. Here: x-px and y-py
    correlations ``xpx``, ``ypy``; z = sz (f d + sqrt(1 - f^2) u) with d the
    unit-variance mix cos(phi) x-part + sin(phi) px-part, ``f`` = ``tilt_fraction``
    and ``phi`` = ``tilt_angle``; pz = h z + c (z^2 - <z^2>) + spread.
    """
    u = torch.randn(n, 6, generator=g, dtype=torch.float64)
    r, q = params["xpx"], params["ypy"]
    x = params["sx"] * u[:, 0]
    px = params["spx"] * (r * u[:, 0] + (1 - r**2) ** 0.5 * u[:, 1])
    y = params["sy"] * u[:, 2]
    py = params["spy"] * (q * u[:, 2] + (1 - q**2) ** 0.5 * u[:, 3])
    phi, f = params["tilt_angle"], params["tilt_fraction"]
    d = math.cos(phi) * u[:, 0] + math.sin(phi) * u[:, 1]
    z = params["sz"] * (f * d + (1 - f**2) ** 0.5 * u[:, 4])
    pz = curved_chirp(params, z, u[:, 5])
    return torch.stack([x, px, y, py, z, pz], -1)


def tilted_draw(rng: np.random.Generator) -> dict:
    """Parameters of one :func:`tilted_beam` (the family draws' ranges for
    sizes, correlations, chirp and spread; the shared truth's tilt fraction is
    about 0.91)."""
    return {
        **_chirp_draw(rng),
        "tilt_angle": rng.uniform(0.0, 2 * math.pi),
        "tilt_fraction": rng.uniform(0.2, 0.95),
        "xpx": rng.uniform(-0.95, 0.95),
        "ypy": rng.uniform(-0.95, 0.95),
        "sx": rng.uniform(3.5e-4, 7e-4),
        "spx": rng.uniform(1.8e-4, 3.5e-4),
        "sy": rng.uniform(3.5e-4, 7e-4),
        "spy": rng.uniform(1.8e-4, 3.5e-4),
        "sz": rng.uniform(5e-4, 9e-4),
    }


def drawn_params(name: str) -> tuple[dict, int]:
    """``draw<R>_<K>``: the K-th (from 0) random README-family beam of numpy
    seed R (:func:`family_draw`), and its sampling and data seed ``R + K``;
    ``tilted<R>_<K>`` likewise with :func:`tilted_draw`.

    Beams no default was tuned on ("other beams"): e.g. ``--beams
    draw2026_0,draw2026_1``.
    """
    m = re.fullmatch(r"(draw|tilted)(\d+)_(\d+)", name)
    if m is None:
        raise ValueError(f"unknown beam {name!r}")
    base, k = int(m.group(2)), int(m.group(3))
    rng = np.random.default_rng(base)
    draw = family_draw if m.group(1) == "draw" else tilted_draw
    for _ in range(k + 1):
        params = draw(rng)
    return params, base + k


def _rotated(name: str) -> tuple[float, str] | None:
    """``xyrot<D>_<beam>``: the angle [deg] and the beam turned; else None."""
    m = re.fullmatch(r"xyrot(-?\d+(?:\.\d+)?)_(.+)", name)
    return (float(m.group(1)), m.group(2)) if m else None


def beam_seed(name: str) -> int:
    """Sampling and data seed of a benchmark beam."""
    rot = _rotated(name)
    if rot is not None:
        return beam_seed(rot[1])
    return BEAM_SEEDS[name] if name in BEAM_SEEDS else drawn_params(name)[1]


def synthetic_beam(name: str, n: int, seed: int) -> torch.Tensor:
    """One of the benchmark's synthetic beams, Bmad coordinates ``(n, 6)``."""
    rot = _rotated(name)
    if rot is not None:  # x-y coupling: turn (x, y) and (px, py) together
        b = synthetic_beam(rot[1], n, seed).clone()
        c, s = math.cos(math.radians(rot[0])), math.sin(math.radians(rot[0]))
        turn = torch.tensor([[c, -s], [s, c]], dtype=b.dtype)
        b[:, [0, 2]] = b[:, [0, 2]] @ turn.T
        b[:, [1, 3]] = b[:, [1, 3]] @ turn.T
        return b
    g = torch.Generator().manual_seed(seed)
    if name.startswith("draw"):
        b = family_beam(drawn_params(name)[0], n, g)
        return b - b.mean(0)
    if name.startswith("tilted"):
        b = tilted_beam(drawn_params(name)[0], n, g)
        return b - b.mean(0)
    if name in FAMILY:
        b = family_beam(FAMILY[name], n, g)
        return b - b.mean(0)
    if name == "double_horn":
        b = double_horn_beam(OTHER_KINDS[name], n, g)
        return b - b.mean(0)
    if name == "wide":
        b = family_beam(OTHER_KINDS[name], n, g)
        return b - b.mean(0)
    preset = {"correlated": "correlated", "nonlinear_ypy": "nonlinear"}.get(
        name, "gaussian"
    )
    b = sample_preset_beam(preset, n, g) * torch.tensor(
        AWA6D_BEAM_SCALE, dtype=torch.float64
    )
    if name == "nonlinear_ypy":
        b[:, 3] += 0.5 * b[:, 2]
        b[:, 5] *= 0.5
    elif name == "gaussian_coupled":
        b[:, 3] += 0.5 * b[:, 2]
        b[:, 5] += 2.0 * b[:, 4]
        b[:, 4] += 0.5 * b[:, 0]
    elif name != "correlated":
        raise ValueError(f"unknown beam {name!r}")
    return b - b.mean(0)


def beam_scans(name: str, held_out: bool = True) -> tuple:
    """``(truth, train, test)`` of a beam: the shared training file (its stored
    truth, no held-out scans: ``test`` None) or a synthetic beam imaged at
    :data:`TRAIN_K1` and, with ``held_out``, at :data:`TEST_K1`."""
    if name == "shared":
        train = read_scans(TRAIN)
        return train.ground_truth, train, None
    seed = beam_seed(name)
    truth = synthetic_beam(name, 200_000, seed)
    train = make_synthetic_awa6d(particles=truth, k1_values=TRAIN_K1, seed=seed)
    test = (
        make_synthetic_awa6d(particles=truth, k1_values=TEST_K1, seed=seed)
        if held_out
        else None
    )
    return truth, train, test


def reported_rel_std(result, train) -> dict[str, float]:
    """The relative 1-sigma std a run reports (``Reconstruction.moments`` with
    the moment posterior of ``reconstruct``'s default, attached after
    training so that the training time above is training alone) of the rms
    sizes and the emittances."""
    measured = {n: scan.mean_images() for n, scan in train}
    settings = {n: scan.settings for n, scan in train}
    attach_uncertainty(result, measured, settings)
    m = result.moments()
    rms_mean, rms_std = m["rms"]["mean"], m["rms"]["std"]
    out = {
        f"rms_{c}": rms_std[i] / rms_mean[i]
        for i, c in enumerate(("x", "px", "y", "py", "z", "pz"))
    }
    for k in ("emit_x", "emit_y", "emit_z", "emit_6d"):
        out[k] = m[k]["std"] / m[k]["mean"]
    return out


def run_beam(name: str, seeds: list[int], overrides: dict | None = None) -> dict:
    truth, train, test = beam_scans(name)
    runs = []
    for s in seeds:
        config = ReconstructionConfig(dims=6, seed=s, **(overrides or {}))
        t0 = time.perf_counter()
        result = reconstruct(train, config, uncertainty=False)
        wall = time.perf_counter() - t0
        sample = result.sample(200_000)
        e = moment_errors(sample, truth)
        run = {"seed": s, "train_wall_s": wall, **{k: e[k] for k in KEYS}}
        run["reported_rel_std"] = reported_rel_std(result, train)
        run["misses"] = {
            k: {"error": e[k], "in_reported_std": e[k] / run["reported_rel_std"][k]}
            for k in run["reported_rel_std"]
            if abs(e[k]) > LIMITS[k]
        }
        # what the prior sets, as a run's summary.json reports it (here from
        # the pooled sample's covariance)
        run["prior_dependence"] = prior_dependence(
            result.training_maps(), torch.cov(sample.T.double())
        )
        run["rms_max_abs"] = max(abs(e[f"rms_{c}"]) for c in "x px y py z pz".split())
        if test is not None:
            run["held_out_relative_l1"] = {
                n: image_errors(
                    result.predict_images(scan.settings, scan=n), scan.mean_images()
                )["relative_l1"]
                for n, scan in test
            }
        runs.append(run)
    stats = {}
    for k in KEYS:
        v = torch.tensor([r[k] for r in runs], dtype=torch.float64)
        stats[k] = {
            "mean": float(v.mean()),
            "std": float(v.std()) if len(v) > 1 else math.nan,
            "worst_abs": float(v.abs().max()),
            "limit": LIMITS[k],
            "within_limit_all_seeds": bool((v.abs() <= LIMITS[k]).all()),
        }
    fails = [k for k, s in stats.items() if not s["within_limit_all_seeds"]]
    if test is not None:
        worst = {n: max(r["held_out_relative_l1"][n] for r in runs) for n, _ in test}
        stats["held_out_relative_l1_worst"] = worst
        fails += [f"held_out_l1_{n}" for n, v in worst.items() if v > HELD_OUT_L1]
    return {"config": config.to_dict(), "runs": runs, "stats": stats, "fails": fails}


def _override(text: str) -> tuple[str, object]:
    """``FIELD=VALUE`` as a config field and its value (int, float, bool or str)."""
    field, sep, value = text.partition("=")
    if not sep or not field:
        raise SystemExit(f"--set {text!r}: expected FIELD=VALUE")
    if value.lower() in ("true", "false"):
        return field, value.lower() == "true"
    for kind in (int, float):
        try:
            return field, kind(value)
        except ValueError:
            pass
    return field, value


def _kinds(result: dict) -> tuple[list[str], list[str]]:
    """Names of the shared-file-like beams and of the beams of other shapes run."""
    beams = result["beams"]
    family = [n for n in beams if n in FAMILY or n.startswith(("draw", "tilted"))]
    other = [n for n in beams if n in OTHER_KINDS or _rotated(n)]
    return family, other


def headline(result: dict) -> dict[str, str]:
    """The docs page's figures: beams within every limit, worst held-out L1."""
    beams = result["beams"]
    seeds = ("seed " if len(result["seeds"]) == 1 else "seeds ") + ", ".join(
        str(s) for s in result["seeds"]
    )
    family, other = _kinds(result)
    rest = [n for n in beams if n not in family and n not in other]
    figures = {}
    for names, label in (
        (family, "shared-file-like random beams"),
        (other, "synthetic beams of other shapes"),
        (rest, "presets and the shared file's beam"),
    ):
        if names:
            # the first figure names the training seeds
            label += " within every limit" + ("" if figures else f" ({seeds})")
            figures[label] = (
                f"{sum(not beams[n]['fails'] for n in names)} of {len(names)}"
            )
    worst = [
        v
        for b in beams.values()
        for v in b["stats"].get("held_out_relative_l1_worst", {}).values()
    ]
    if worst:
        figures["held-out relative L1, worst"] = f"{max(worst):.3f}"
    misses = [
        m["in_reported_std"]
        for b in beams.values()
        for r in b.get("runs", [])
        for m in r.get("misses", {}).values()
    ]
    if misses:
        within = sum(abs(z) <= 2 for z in misses)
        figures["errors outside a limit that are within 2 reported std"] = (
            f"{within} of {len(misses)} (largest {max(map(abs, misses)):.2f} std)"
        )
    return figures


def note(result: dict) -> str | None:
    """The beams outside a limit and the quantities that miss, if any."""
    fails = result["fails"]
    if not fails:
        return None
    return "outside a limit: " + "; ".join(
        f"{n} ({', '.join(f)})" for n, f in fails.items()
    )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument(
        "--beams",
        default=",".join(["shared", *BEAM_SEEDS]),
    )
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="override a ReconstructionConfig field (experiments; a number, "
        "true/false or text), e.g. --set penalty_end=1e5",
    )
    add_store_flag(ap)
    args = ap.parse_args()
    overrides = dict(_override(text) for text in args.set)
    torch.set_num_threads(args.threads)
    seeds = [int(s) for s in args.seeds.split(",")]
    out: dict = {
        "name": "reconstruction_6d_beams",
        "threads": args.threads,
        "torch": torch.__version__,
        "device": "cpu",
        "git_commit": git_commit(),
        "load_avg_1min_at_start": os.getloadavg()[0],
        "seeds": seeds,
        "overrides": overrides,
        "beams": {},
    }
    for name in args.beams.split(","):
        out["beams"][name] = run_beam(name, seeds, overrides)
    out["fails"] = {n: b["fails"] for n, b in out["beams"].items() if b["fails"]}
    # the shared file's family (README's description) apart from the presets
    family = [
        n for n in out["fails"] if n in FAMILY or n.startswith(("draw", "tilted"))
    ]
    out["fails_family"] = {n: out["fails"][n] for n in family}
    other = [n for n in out["fails"] if n in OTHER_KINDS or _rotated(n)]
    out["fails_other_kinds"] = {n: out["fails"][n] for n in other}
    out["fails_presets"] = {
        n: f for n, f in out["fails"].items() if n not in family and n not in other
    }
    out["load_avg_1min_at_end"] = os.getloadavg()[0]
    emit(out, args.out, note=note, headline=headline, store_result=args.store)


if __name__ == "__main__":
    main()
