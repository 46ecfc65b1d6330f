"""6D reconstruction of camera frames imported from a DAQ folder vs the noise-free file.

A known beam (``make_synthetic_awa6d``: the ``nonlinear`` preset, 100 000
particles, quadrupole k1 -12 ... 12 1/m^2 in 9 steps x deflecting cavity off /
4 MV, scans ``dipole_off`` and ``dipole_on``, 96 x 96 pixel screens, histogram
images: the defaults of ``diffaccel synthetic --layout awa6d``) gives the
noise-free version. The same scans are written as a DAQ folder
(``write_daq_folder``: 16-bit PNG frames with a fixed-pattern pedestal of ~400
counts, read noise 8 counts rms, shot noise with 4000 electrons at the brightest
pixel of each scan, 3 shots per setting, 4 background frames and a CSV table per
scan, ``experiment.yaml``) and imported as ``diffaccel data import`` does
(``import_experiment`` with the default preprocessing, ``write_scans``, read
back).

Both versions are reconstructed with ``reconstruct`` and the default 6D
``ReconstructionConfig(dims=6)`` on the same training settings (the even
quadrupole settings at both cavity states, 20 images); the held-out settings
(odd quadrupole settings, 16 images) are predicted (``predict_dataset``) and
scored against the noise-free images (relative L1 of unit-sum images,
``image_errors``). Measured:

* moments (six rms sizes, emittances x, y, z, 6D emittance) of the DAQ version
  minus those of the noise-free version, in units of the reported 1-sigma
  (``Reconstruction.moments()['...']['std']``), both stds combined in
  quadrature and the DAQ version's std alone; criterion: |difference| <= 2 std;
* held-out relative L1 of each version per scan; criterion: DAQ version within
  0.02 of the noise-free version;
* each version's moment errors against the ground truth, the screen rms sizes
  of the imported images against the noise-free ones (whole frame and within
  6 rms of each noise-free image; before training), and
  wall times.

Prints one JSON object on the last line (benchmarks/_meta.py ``emit``).

Usage: ``python benchmarks/daq_6d.py [--threads N] [--seed S] [--out FILE]``
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import torch
from _meta import add_store_flag, emit

from diffaccel.data import make_synthetic_awa6d, read_scans, write_scans
from diffaccel.data.experiment import import_experiment
from diffaccel.data.synthetic_daq import write_daq_folder
from diffaccel.reconstruction import (
    ReconstructionConfig,
    image_errors,
    moment_errors,
    predict_dataset,
    reconstruct,
)
from diffaccel.reconstruction.uncertainty import image_moments, moment_window

RMS = ("x", "px", "y", "py", "z", "pz")
SCALARS = ("emit_x", "emit_y", "emit_z", "emit_6d")
#: |DAQ - noise-free| of every moment within this many reported std.
N_STD = 2.0
#: Held-out relative L1 of the DAQ version within this of the noise-free one.
L1_TOLERANCE = 0.02


def _log(*args) -> None:
    print(*args, file=sys.stderr, flush=True)


def _split(k: int, n_voltages: int) -> tuple[list[int], list[int]]:
    """Settings of even / odd quadrupole index (all cavity states of each)."""
    train = [i for i in range(k) if (i // n_voltages) % 2 == 0]
    return train, [i for i in range(k) if i not in train]


def _moments(result) -> dict[str, tuple[float, float]]:
    m = result.moments()
    out = {
        f"rms_{c}": (m["rms"]["mean"][i], m["rms"]["std"][i]) for i, c in enumerate(RMS)
    }
    out.update({k: (m[k]["mean"], m[k]["std"]) for k in SCALARS})
    return out


def _screen_rms(ms, windows: dict | None = None) -> dict[str, torch.Tensor]:
    """Per scan: ``(K, 2)`` rms x, y of the shot-averaged images [m] (signed
    pixel weights: noise can make a whole-frame variance negative, NaN here),
    within ``windows[name]`` when given."""
    out = {}
    for name, scan in ms:
        xs, ys = scan.pixel_centers()
        w = None if windows is None else windows[name]
        m = image_moments(scan.mean_images().double(), xs, ys, w)
        out[name] = torch.stack([m[:, 2], m[:, 4]], -1).sqrt()
    return out


def _rms_difference(clean, daq) -> dict[str, dict[str, float]]:
    """Largest and mean |relative difference| of the screen rms over settings
    with a real rms, and the count without one (``nan``), over the whole frame
    and within 6 rms of each noise-free image."""
    windows = {}
    for name, scan in clean:
        xs, ys = scan.pixel_centers()
        windows[name] = moment_window(scan.mean_images().double(), xs, ys, 6.0)
    out = {}
    for label, win in (("frame", None), ("6sigma", windows)):
        sc, sd = _screen_rms(clean, win), _screen_rms(daq, win)
        for name in sc:
            rel = (sd[name] / sc[name] - 1.0).abs()
            entry = out.setdefault(name, {})
            for a, axis in enumerate("xy"):
                r = rel[:, a]
                entry[f"{label}_max_{axis}"] = round(float(r.nan_to_num(0.0).max()), 4)
                entry[f"{label}_mean_{axis}"] = round(float(r.nanmean()), 4)
                entry[f"{label}_nan_{axis}"] = int(r.isnan().sum())
    return out


def _run(ms, train: dict, test, truth: torch.Tensor, label: str) -> dict:
    t0 = time.perf_counter()
    result = reconstruct(ms, ReconstructionConfig(dims=6), train_indices=train)
    wall = time.perf_counter() - t0
    pred = predict_dataset(result, test)
    held = {
        name: image_errors(pred[name], scan.mean_images())["relative_l1"]
        for name, scan in test
    }
    gt = moment_errors(result.sample(200_000), truth)
    out = {
        "wall_s": round(wall, 1),
        "moments": _moments(result),
        "held_out_relative_l1": held,
        "errors_vs_truth": {
            k: round(float(gt[k]), 4) for k in [f"rms_{c}" for c in RMS] + [*SCALARS]
        },
        "timings_s": dict(result.info.get("timings_s", {})),
    }
    _log(label, {k: v for k, v in out.items() if k != "moments"})
    return out


def headline(result: dict) -> dict[str, str]:
    """The stored result's figures, from this benchmark's printed result."""
    worst_c, n_c = result["worst"]["combined"]
    worst_d, n_d = result["worst"]["daq_std"]
    rel = result["comparison"][worst_c]["relative_difference"]
    l1_c = result["noise_free"]["held_out_relative_l1"]
    l1_d = result["daq"]["held_out_relative_l1"]
    met = all(result["met"].values())
    return {
        "moments, DAQ vs noise-free: worst |difference| / combined reported std "
        "(limit 2)": f"{n_c:.2f} ({worst_c}, {100 * rel:+.1f} %)",
        "same, / the DAQ version's reported std alone (limit 2)": (
            f"{n_d:.2f} ({worst_d})"
        ),
        **{
            f"held-out relative L1 against the noise-free images, noise-free / DAQ "
            f"version, {name} (limit: DAQ within 0.02)": (
                f"{l1_c[name]:.3f} / {l1_d[name]:.3f}"
            )
            for name in l1_c
        },
        "criterion (moments within 2 std, held-out L1 within 0.02)": (
            "met" if met else "not met"
        ),
        "wall: import / noise-free / DAQ reconstruction": (
            f"{result['daq_import_s']:.1f} / {result['noise_free']['wall_s']:.0f} / "
            f"{result['daq']['wall_s']:.0f} s"
        ),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    add_store_flag(ap)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    t_start = time.perf_counter()
    voltages = (0.0, 4e6)
    clean = make_synthetic_awa6d("nonlinear", seed=args.seed, voltages=voltages)
    truth = clean.ground_truth
    k = clean[clean.names[0]].n_settings
    train_idx, test_idx = _split(k, len(voltages))
    train = {name: train_idx for name in clean.names}
    test = clean.subset({name: test_idx for name in clean.names})
    out: dict = {
        "name": "daq_6d",
        "threads": args.threads,
        "seed": args.seed,
        "load_avg_1min_at_start": os.getloadavg()[0],
        "data": {
            name: {"settings": s.n_settings, "screen": list(s.screen_shape)}
            for name, s in clean
        },
        "train_indices": train_idx,
        "held_out_indices": test_idx,
        "criteria": {"n_std": N_STD, "held_out_l1_tolerance": L1_TOLERANCE},
    }
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        yml = write_daq_folder(clean, Path(tmp) / "daq", seed=args.seed)
        t1 = time.perf_counter()
        h5 = write_scans(import_experiment(yml), Path(tmp) / "daq.h5")
        daq = read_scans(h5)
        t2 = time.perf_counter()
    out["daq_write_s"] = round(t1 - t0, 1)
    out["daq_import_s"] = round(t2 - t1, 1)
    out["daq_shape"] = {name: list(s.shape) for name, s in daq}
    # screen rms of the imported images vs the noise-free ones (no training)
    out["screen_rms_relative_difference"] = _rms_difference(clean, daq)
    _log("screen rms", out["screen_rms_relative_difference"])
    out["noise_free"] = _run(clean, train, test, truth, "noise_free")
    out["daq"] = _run(daq, train, test, truth, "daq")
    cmp = {}
    for key, (m_d, s_d) in out["daq"]["moments"].items():
        m_c, s_c = out["noise_free"]["moments"][key]
        diff = m_d - m_c
        both = math.hypot(s_d, s_c)
        cmp[key] = {
            "relative_difference": round(diff / m_c, 4),
            "std_daq_relative": round(s_d / m_d, 4),
            "std_noise_free_relative": round(s_c / m_c, 4),
            "n_std_combined": round(abs(diff) / both, 2) if both > 0 else None,
            "n_std_daq": round(abs(diff) / s_d, 2) if s_d > 0 else None,
        }
    out["comparison"] = cmp
    l1 = {
        name: round(
            out["daq"]["held_out_relative_l1"][name]
            - out["noise_free"]["held_out_relative_l1"][name],
            4,
        )
        for name in clean.names
    }
    out["held_out_l1_difference"] = l1
    worst_c = max(cmp, key=lambda q: cmp[q]["n_std_combined"] or 0.0)
    worst_d = max(cmp, key=lambda q: cmp[q]["n_std_daq"] or 0.0)
    out["met"] = {
        "moments_within_2_std_combined": all(
            (v["n_std_combined"] or 0.0) <= N_STD for v in cmp.values()
        ),
        "moments_within_2_std_daq": all(
            (v["n_std_daq"] or 0.0) <= N_STD for v in cmp.values()
        ),
        "held_out_l1_within_0.02": all(v <= L1_TOLERANCE for v in l1.values()),
    }
    out["worst"] = {
        "combined": [worst_c, cmp[worst_c]["n_std_combined"]],
        "daq_std": [worst_d, cmp[worst_d]["n_std_daq"]],
    }
    out["wall_s"] = round(time.perf_counter() - t_start, 1)
    out["load_avg_1min_at_end"] = os.getloadavg()[0]
    emit(out, args.out, headline=headline, store_result=args.store)


if __name__ == "__main__":
    main()
