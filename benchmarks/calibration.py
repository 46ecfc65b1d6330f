"""Calibration of the reported moment uncertainty on reconstructions with known truth.

Reconstructs datasets whose ground-truth beam is known with default settings
and scores how often the truth lies within 1 and 2 reported std
(``Reconstruction.moments()[name]["std"]``) of the reported mean, for the rms
sizes of the reconstructed coordinates and the emittances (x, y, 4D; with
``--dims 6`` also z and 6D), and the median relative std of the *constrained*
quantities (those not involving a coordinate listed by
``Reconstruction.unconstrained_coordinates``).

Datasets:
- ``gpsr4d``: ``data/phase_space/gpsr_4d_synthetic.h5``, even settings
  (check only: nothing was tuned on it);
- ``sixd``: ``sixd_synthetic_train.h5`` with ``--dims 6`` (``--sixd``; slow);
- ``awa6d-<preset>-s<seed>``: the AWA 6D layout of the shared file (two
  scans, TDC off/on, dipole, k1 = -12 ... 12 in 5 steps) of beams generated
  here with ``make_synthetic_awa6d`` (``--awa6d N`` cases, default 2; seeds
  400+ differ from the 310-313 the analysis was developed on);
- ``beams6d-<beam>``: the other beams of ``benchmarks/reconstruction_6d_beams.py``
  (every beam of its ``BEAM_SEEDS`` by default, or those named by
  ``--beams6d``: presets, the shared file's family, other kinds, and any
  other name it knows, e.g. the random draws ``draw<R>_<K>``);
- ``quad-<preset>-n<noise>-s<seed>``: quad-only scans simulated here (presets
  gaussian/correlated/nonlinear, Poisson noise at the peak pixel, seeds; KDE
  images of one-pixel bandwidth, recorded in the data as
  ``resolution_pixels``), reconstructed with ``--dims 4`` and, for the presets
  of ``--quad-6d`` (default gaussian, every noise level and seed), ``--dims
  6`` (z and pz unconstrained: each must be
  within 2 std or carry >= 20 %); with ``--mismatch`` also ``--dims 6`` with
  the resolution removed from the data (the 6D default blur then mismatches
  the images: model error, reported apart as ``blur_mismatch_cases``).

Prints one JSON object: per dataset the per-quantity z-scores, coverage and
median relative std; the pooled numbers; ``met``: the acceptance criteria
(pooled coverage of 2 std >= 85 %, over all and over the constrained
quantities; median relative std of the constrained quantities <= 5 %, pooled
and for each 6D dataset; on quad-only ``--dims 6`` z and pz each within 2 std or
with a relative std >= 20 %); and the share of the reconstruction time that
the uncertainty analysis takes; ``per_class``: the same coverage and median
for each class of data (GPSR 4D, quad-only by dims and noise level, own AWA-6D
beams, other 6D beams, the shared 6D file), ``met.each_class``: every class
at >= 85 % of its constrained quantities within 2 std and a median relative
std <= 5 %.

Usage: ``python benchmarks/calibration.py [--quick] [--sixd] [--seeds 0 1 2]
[--awa6d 3] [--beams6d correlated] [--quad-6d gaussian] [--out calibration.json]``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch
from _meta import add_store_flag, emit, git_commit
from reconstruction_6d_beams import BEAM_SEEDS, beam_scans

from diffaccel.data import make_synthetic_quad_scan, read_quad_scan
from diffaccel.reconstruction import ReconstructionConfig, beam_moments, reconstruct
from diffaccel.reconstruction.pipeline import as_scans

DATA = Path(__file__).resolve().parents[1] / "data" / "phase_space"
COORDS = ("x", "px", "y", "py", "z", "pz")


def score(result, truth: torch.Tensor) -> dict:
    """z-scores ``|mean - truth| / std`` of rms sizes and emittances."""
    dims = result.config.dims
    mom = result.moments()
    t = beam_moments(truth.to(torch.float64))
    free = set(result.unconstrained_coordinates())
    rows = {}
    for i in range(dims):
        rows[f"rms_{COORDS[i]}"] = (
            mom["rms"]["mean"][i],
            mom["rms"]["std"][i],
            float(t["rms"][i]),
            COORDS[i] in free,
        )
    emits = ["emit_x", "emit_y", "emit_4d"] + (
        ["emit_z", "emit_6d"] if dims == 6 else []
    )
    involve = {
        "emit_x": {"x", "px"},
        "emit_y": {"y", "py"},
        "emit_4d": {"x", "px", "y", "py"},
        "emit_z": {"z", "pz"},
        "emit_6d": set(COORDS),
    }
    for k in emits:
        rows[k] = (mom[k]["mean"], mom[k]["std"], float(t[k]), bool(involve[k] & free))
    out = {}
    for k, (m, s, tv, unconstrained) in rows.items():
        out[k] = {
            "mean": m,
            "std": s,
            "truth": tv,
            "rel_error": (m - tv) / tv if tv else None,
            "rel_std": s / abs(m) if m else None,
            "z": abs(m - tv) / s if s > 0 else float("inf"),
            "unconstrained": unconstrained,
        }
    return out


def summarise(rows: list[dict]) -> dict:
    z = [r["z"] for r in rows]
    rel = [r["rel_std"] for r in rows if not r["unconstrained"] and r["rel_std"]]
    con = [r["z"] for r in rows if not r["unconstrained"]]
    return {
        "n": len(z),
        "coverage_1sigma": sum(v <= 1 for v in z) / len(z),
        "coverage_2sigma": sum(v <= 2 for v in z) / len(z),
        "coverage_2sigma_constrained": (
            sum(v <= 2 for v in con) / len(con) if con else None
        ),
        "median_rel_std_constrained": statistics.median(rel) if rel else None,
    }


def dataset_class(key: str, entry: dict) -> str:
    """Class of a dataset for the per-class summary (noise levels apart)."""
    if key.startswith("quad-"):
        noise = re.search(r"-n([0-9.]+)-s", key).group(1)
        return f"quad-only dims {entry['dims']}, noise {noise}"
    if key.startswith("awa6d"):
        return "own AWA-6D beams"
    if key.startswith("beams6d"):
        return "other 6D beams (reconstruction_6d_beams)"
    return {"gpsr4d": "GPSR 4D", "sixd": "shared 6D file"}.get(key, key)


def run(name: str, ds, dims: int, train=None, uncertainty: bool = True) -> dict:
    cfg = ReconstructionConfig(dims=dims)
    t0 = time.perf_counter()
    result = reconstruct(ds, cfg, train_indices=train, uncertainty=uncertainty)
    wall = time.perf_counter() - t0
    truth = as_scans(ds).ground_truth
    quantities = score(result, truth)
    entry = {
        "dims": dims,
        "wall_s": wall,
        "timings_s": result.info.get("timings_s", {}),
        "unconstrained": result.unconstrained_coordinates(),
        "quantities": quantities,
        "diagnostics": (result.info.get("uncertainty") or {}).get("diagnostics"),
    }
    entry |= summarise(list(quantities.values()))
    print(json.dumps({name: entry}), file=sys.stderr)  # partial results survive
    print(
        f"{name}: {entry['coverage_2sigma']:.2f} 2-sigma, median rel std "
        f"{entry['median_rel_std_constrained']}, {wall:.1f} s",
        file=sys.stderr,
    )
    return entry


def headline(result: dict) -> dict[str, str]:
    """The docs page's figures: pooled 2-std coverage and median relative std."""
    pooled, datasets = result["pooled"], result["datasets"]
    dims = {d["dims"] for d in datasets.values()}
    kind = {frozenset({6}): "6D quantities", frozenset({4}): "4D quantities"}.get(
        frozenset(dims), "quantities"
    )
    rel = pooled["median_rel_std_constrained"]
    return {
        f"{kind} within 2 reported std ({len(datasets)} datasets, "
        f"{pooled['n']} quantities)": f"{100 * pooled['coverage_2sigma']:.0f} %",
        "median relative std of the constrained quantities": (
            "none constrained" if rel is None else f"{100 * rel:.1f} %"
        ),
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="one seed, two presets")
    ap.add_argument(
        "--presets",
        nargs="*",
        default=["gaussian", "correlated", "nonlinear"],
        help="quad-only presets (none: no quad-only cases)",
    )
    ap.add_argument("--sixd", action="store_true", help="also the shared 6D file")
    ap.add_argument("--no-gpsr4d", action="store_true")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--noise", type=float, nargs="+", default=[0.05, 0.2])
    ap.add_argument(
        "--awa6d",
        type=int,
        default=2,
        help="own AWA-6D cases (beams generated here; presets nonlinear, "
        "correlated, gaussian in turn, one seed each)",
    )
    ap.add_argument(
        "--quad-6d",
        nargs="*",
        default=["gaussian"],
        help="presets also reconstructed with --dims 6 (every noise and seed)",
    )
    ap.add_argument(
        "--beams6d",
        nargs="*",
        default=list(BEAM_SEEDS),
        help="other 6D beams of benchmarks/reconstruction_6d_beams.py (default all)",
    )
    ap.add_argument(
        "--mismatch",
        action="store_true",
        help="also the quad-only --dims 6 cases with the screen resolution "
        "removed from the data (6D default blur on 1-pixel KDE images: model "
        "error, reported apart)",
    )
    ap.add_argument(
        "--no-uncertainty",
        action="store_true",
        help="ensemble scatter only (today's std), for comparison",
    )
    ap.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    add_store_flag(ap)
    args = ap.parse_args()
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    unc = not args.no_uncertainty
    presets = ["gaussian", "nonlinear"] if args.quick else args.presets
    seeds = args.seeds[:1] if args.quick else args.seeds
    datasets: dict[str, dict] = {}
    load_start = os.getloadavg()[0]
    t_all = time.perf_counter()
    if not args.no_gpsr4d:
        ds = read_quad_scan(DATA / "gpsr_4d_synthetic.h5")
        datasets["gpsr4d"] = run("gpsr4d", ds, 4, list(range(0, ds.n_settings, 2)), unc)
    mismatch: dict[str, dict] = {}
    for preset in presets:
        for noise in args.noise:
            for seed in seeds:
                ds = make_synthetic_quad_scan(
                    preset, n_particles=10_000, noise=noise, seed=100 + seed
                )
                key = f"quad-{preset}-n{noise}-s{seed}"
                datasets[key] = run(key, ds, 4, None, unc)
                if preset in args.quad_6d:
                    datasets[key + "-6d"] = run(key + "-6d", ds, 6, None, unc)
                    if args.mismatch:
                        # the screen resolution unknown: the 6D default blur
                        # (histograms, sqrt(1/12) pixel) on 1-pixel KDE images
                        k6 = key + "-6d-unknown-resolution"
                        blind = replace(ds, resolution_pixels=None)
                        mismatch[k6] = run(k6, blind, 6, None, unc)
    awa_presets = ["nonlinear", "correlated", "gaussian"]
    for i in range(args.awa6d):
        from diffaccel.data import make_synthetic_awa6d

        preset = awa_presets[i % 3]
        seed = 400 + i  # not the beams the posterior was tuned on (310-313)
        # the shared file's layout: k1 = -12 ... 12 in 5 steps x TDC off/on
        ds = make_synthetic_awa6d(
            preset,
            n_particles=100_000,
            k1_values=[-12.0, -6.0, 0.0, 6.0, 12.0],
            noise=0.02,
            seed=seed,
        )
        key = f"awa6d-{preset}-s{seed}"
        datasets[key] = run(key, ds, 6, None, unc)
    for name in args.beams6d:
        # the other beams of benchmarks/reconstruction_6d_beams.py (
        # "the same holds on other beams"), its beam seeds and training k1;
        # any name it knows (random draws draw<R>_<K>, tilted<R>_<K>, ...)
        _, ds, _ = beam_scans(name, held_out=False)
        datasets[f"beams6d-{name}"] = run(f"beams6d-{name}", ds, 6, None, unc)
    if args.sixd:
        from diffaccel.data import read_scans

        ds = read_scans(DATA / "sixd_synthetic_train.h5")
        datasets["sixd"] = run("sixd", ds, 6, None, unc)
    pooled_rows = [q for d in datasets.values() for q in d["quantities"].values()]
    four = [
        q
        for k, d in datasets.items()
        if d["dims"] == 4
        for q in d["quantities"].values()
    ]
    zpz = {}
    for k, d in datasets.items():
        if d["dims"] == 6 and k.startswith("quad"):
            for c in ("rms_z", "rms_pz"):
                q = d["quantities"][c]
                zpz[f"{k}:{c}"] = {
                    "z": q["z"],
                    "rel_std": q["rel_std"],
                    "ok": q["z"] <= 2 or (q["rel_std"] or 0) >= 0.2,
                }
    pooled = summarise(pooled_rows)
    classes: dict[str, list[dict]] = {}
    for k, d in datasets.items():
        classes.setdefault(dataset_class(k, d), []).extend(d["quantities"].values())
    per_class = {c: summarise(rows) for c, rows in classes.items()}
    for c in per_class.values():
        # over the constrained quantities: the unconstrained z, pz of quad-only
        # --dims 6 are judged by the z/pz criterion (prior-limited, >= 20 %)
        c["met"] = (c["coverage_2sigma_constrained"] or 0) >= 0.85 and (
            c["median_rel_std_constrained"] or 1
        ) <= 0.05
    six = {
        k: d["median_rel_std_constrained"]
        for k, d in datasets.items()
        if d["dims"] == 6 and not k.startswith("quad")
    }
    met = {
        # acceptance: >= 85 % of rms sizes and emittances within 2 std, pooled
        "coverage_2sigma_pooled": pooled["coverage_2sigma"] >= 0.85,
        # the same over the constrained quantities (the unconstrained z, pz of
        # quad-only --dims 6 are judged by the z/pz criterion below)
        "coverage_2sigma_pooled_constrained": (
            pooled["coverage_2sigma_constrained"] or 0
        )
        >= 0.85,
        "median_rel_std_pooled": (pooled["median_rel_std_constrained"] or 1) <= 0.05,
        "median_rel_std_each_6d_dataset": (
            all(v is not None and v <= 0.05 for v in six.values()) if six else None
        ),
        "quad_only_6d_z_pz": all(v["ok"] for v in zpz.values()) if zpz else None,
        # the brief's aim beyond the pooled acceptance: each class of data
        "each_class": all(c["met"] for c in per_class.values()),
    }
    with_mismatch = summarise(
        pooled_rows + [q for d in mismatch.values() for q in d["quantities"].values()]
    )
    timings = [
        (d["timings_s"].get("uncertainty", 0.0), d["wall_s"]) for d in datasets.values()
    ]
    result = {
        "name": "calibration",
        "uncertainty": unc,
        "met": met,
        "pooled": pooled,
        "pooled_dims4": summarise(four) if four else None,
        # >= 85 % within 2 std and median relative std <= 5 % per class
        "per_class": per_class,
        # not in "pooled" (--mismatch): quad-only --dims 6 without the recorded
        # screen resolution, imaged with the 6D default blur: a wrong model
        "blur_mismatch_cases": mismatch,
        "pooled_with_blur_mismatch_cases": with_mismatch if mismatch else None,
        "median_rel_std_6d_datasets": six,
        "quad_only_6d_z_pz": zpz,
        "uncertainty_share_of_reconstruct_time": (
            sum(u for u, _ in timings) / sum(w for _, w in timings) if timings else None
        ),
        "datasets": datasets,
        "wall_s": time.perf_counter() - t_all,
        "load_avg_1min_at_start": load_start,
        "load_avg_1min_at_end": os.getloadavg()[0],
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "machine": platform.machine(),
        "commit": git_commit(),
        "note": "timings under contention on a shared 2-core machine",
    }
    emit(result, args.out, headline=headline, store_result=args.store)


if __name__ == "__main__":
    main()
