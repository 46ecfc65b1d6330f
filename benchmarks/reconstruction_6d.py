"""6D phase-space reconstruction on the shared 6D benchmark: diffaccel vs gpsr 0.2.0.

Data: ``data/phase_space/sixd_synthetic_train.h5`` (training: even
quadrupole settings, TDC off/on, dipole off/on: 20 images) and
``sixd_synthetic_test.h5`` (held out: the odd quadrupole settings, 16 images),
both with the 50 000-particle ground truth.

diffaccel runs as a user would: the whole ``diffaccel reconstruct TRAIN --dims 6``
command (default options) in a subprocess, timed from outside (wall and CPU
time of the child); then ``diffaccel.reconstruction.load(RUN).sample(200_000)``
is compared with the truth, and the images of the held-out file are predicted
(``predict_dataset``) and scored per scan (relative L1 of unit-sum images).

gpsr runs its 6D recipe in this process on the same data: ``GPSR6DLattice``
(quadrupole, TDC tilted to streak vertically, spectrometer dipole, two cheetah
screens), ``NNParticleBeamGenerator``, ``train_gpsr`` (Adam, MAE on sum-normalised
images). Note: its dipole asks cheetah for ``tracking_method="bmadx"``, which
cheetah 0.8.4 no longer has; cheetah only warns (PhysicsWarning) and keeps its
linear dipole map, and
its quadrupole and TDC are tracked with cheetah's default (linear) maps, so gpsr
models this beamline without the chromatic and RF-curvature terms that made the
data. Its particles are scored with the same metrics, its held-out images with
its own lattice (fresh objects: trained gpsr models can return stale images)
and with diffaccel's forward model.

Prints one JSON object (benchmarks/_meta.py). Timings under load are inflated:
``load_avg_1min_*`` records the machine's load.

Usage: ``python benchmarks/reconstruction_6d.py [--skip-gpsr] [--gpsr-epochs N]
[--gpsr-particles N] [--threads N] [--device cuda]``
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from _meta import add_store_flag, emit, git_commit
from _sixd import HELD_OUT_L1, KEYS, LIMITS, TEST, TRAIN, WALL_LIMIT_S

from diffaccel.data import read_scans
from diffaccel.dynamics.coordinates import cheetah_to_bmad
from diffaccel.reconstruction import (
    ReconstructionConfig,
    ScreenForwardModel,
    beam_moments,
    image_errors,
    load,
    moment_errors,
    predict_dataset,
)


def _errors(particles: torch.Tensor, truth: torch.Tensor) -> dict[str, float]:
    e = moment_errors(particles, truth)
    return {k: e[k] for k in KEYS}


def _verdict(errors: dict[str, float], held_out: dict[str, float]) -> dict:
    fails = [k for k, lim in LIMITS.items() if not abs(errors[k]) <= lim]
    fails += [f"held_out_l1_{n}" for n, v in held_out.items() if not v <= HELD_OUT_L1]
    return {"meets_moments_and_images": not fails, "fails": fails}


def run_diffaccel(threads: int, test, device: str = "cpu") -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run"
        cmd = [
            sys.executable,
            "-m",
            "diffaccel",
            "reconstruct",
            str(TRAIN),
            "--dims",
            "6",
            "--out",
            str(out),
            "--device",
            device,
        ]
        env = dict(os.environ, OMP_NUM_THREADS=str(threads))
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
        wall = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        if proc.returncode != 0:
            raise RuntimeError(f"diffaccel reconstruct failed: {proc.stderr[-2000:]}")
        result = load(out)
        truth = read_scans(TRAIN).ground_truth
        x = result.sample(200_000)
        pred = predict_dataset(result, test)
    held = {
        name: image_errors(pred[name], scan.mean_images())["relative_l1"]
        for name, scan in test
    }
    errors = _errors(x, truth)
    return {
        "command": " ".join(["diffaccel", *cmd[3:]]),
        "wall_s": wall,
        "cpu_s": (after.ru_utime + after.ru_stime)
        - (before.ru_utime + before.ru_stime),
        "wall_within_120_s": wall <= WALL_LIMIT_S,
        "config": result.config.to_dict(),
        "errors": errors,
        "held_out_relative_l1": held,
        **_verdict(errors, held),
    }


def _gpsr_lattice(ms, method: str):
    from cheetah.accelerator import Screen
    from gpsr.modeling import GPSR6DLattice

    spec = {e["name"]: e for e in ms["dipole_on"].beamline_spec}
    off = {e["name"]: e for e in ms["dipole_off"].beamline_spec}
    l_quad = spec["SCAN_QUAD"]["length"]
    l_tdc = spec["SCAN_TDC"]["length"]
    l_bend = off["SCAN_DIPOLE_OFF"]["length"]  # straight length of the magnet
    theta = spec["SCAN_DIPOLE"]["angle"]
    # centre-to-centre distances of GPSR6DLattice, from our element lengths
    l1 = spec["D1"]["length"] + l_quad / 2 + l_tdc / 2
    l2 = spec["D2"]["length"] + l_tdc / 2 + l_bend / 2
    l3 = off["D3"]["length"] + l_bend / 2
    screens = []
    for name in ("dipole_off", "dipole_on"):
        scan = ms[name]
        h, w = scan.screen_shape
        screens.append(
            Screen(
                resolution=(w, h),
                pixel_size=torch.tensor(scan.pixel_size, dtype=torch.float32),
                method=method,
                is_active=True,
            )
        )
    lattice = GPSR6DLattice(
        l_quad,
        l_tdc,
        spec["SCAN_TDC"]["frequency"],
        spec["SCAN_TDC"]["phase"],
        l_bend,
        theta,
        l1,
        l2,
        l3,
        screens[0],
        screens[1],
    )
    return lattice, screens, l_bend, theta


def _gpsr_parameters(ms, l_bend: float, theta: float) -> torch.Tensor:
    """(K, N=2, 2, 3): k1, TDC voltage, dipole field G per setting and screen."""
    s = ms["dipole_off"].settings.float()  # the same settings in both scans
    k, v = s[:, 0].reshape(-1, 2), s[:, 1].reshape(-1, 2)
    # G = sin(angle) / l_bend; "off" as a tiny field (G = 0 makes 0/0 lengths)
    g_on = math.sin(theta) / l_bend
    g = torch.tensor([1e-9, g_on], dtype=torch.float32)
    return torch.stack(
        [
            k[..., None].expand(-1, -1, 2),
            v[..., None].expand(-1, -1, 2),
            g.expand(k.shape[0], 2, 2),
        ],
        dim=-1,
    )


def run_gpsr(train, test, epochs: int, n_particles: int, method: str) -> dict:
    import lightning as L  # noqa: F401  (gpsr's trainer)
    from gpsr.beams import NNParticleBeamGenerator
    from gpsr.datasets import SixDReconstructionDataset
    from gpsr.modeling import GPSR
    from gpsr.train import train_gpsr
    from lightning.pytorch.loggers import CSVLogger
    from torch.utils.data import DataLoader

    lattice, screens, l_bend, theta = _gpsr_lattice(train, method)
    params = _gpsr_parameters(train, l_bend, theta)
    obs = tuple(
        train[name].mean_images().reshape(params.shape[0], 2, *train[name].screen_shape)
        for name in ("dipole_off", "dipole_on")
    )
    data = SixDReconstructionDataset(params, obs, tuple(screens))
    loader = DataLoader(data, batch_size=len(data))
    mass = 0.51099895e6
    energy = (train.p0c**2 + mass**2) ** 0.5
    torch.manual_seed(0)
    model = GPSR(NNParticleBeamGenerator(n_particles, energy), lattice)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        c0 = time.process_time()
        lit = train_gpsr(
            model,
            loader,
            n_epochs=epochs,
            logger=CSVLogger(tmp),
            checkpoint_period_epochs=epochs,
            enable_progress_bar=False,
            enable_model_summary=False,
        )
        wall = time.perf_counter() - t0
        cpu = time.process_time() - c0
    with torch.no_grad():
        beam = lit.gpsr_model.beam_generator()
        x = cheetah_to_bmad(beam.particles[:, :6].double(), train.p0c)
        # held out: a fresh lattice with the test settings (no stale caches)
        fresh, _, _, _ = _gpsr_lattice(test, method)
        fresh.set_lattice_parameters(_gpsr_parameters(test, l_bend, theta))
        pred = fresh.track_and_observe(beam)
    held, held_ours = {}, {}
    for i, name in enumerate(("dipole_off", "dipole_on")):
        scan = test[name]
        p = pred[i].reshape(scan.n_settings, *scan.screen_shape)
        p = p / p.sum((-2, -1), keepdim=True).clamp_min(1e-30)
        held[name] = image_errors(p, scan.mean_images())["relative_l1"]
        fwd = ScreenForwardModel.from_dataset(
            scan, blur_pixels=ReconstructionConfig(dims=6).blur_for(scan)
        )
        ours = fwd.images(x.float(), scan.settings)
        ours = ours / ours.sum((-2, -1), keepdim=True).clamp_min(1e-30)
        held_ours[name] = image_errors(ours, scan.mean_images())["relative_l1"]
    errors = _errors(x, train.ground_truth)
    return {
        "wall_s": wall,
        "cpu_s": cpu,
        "epochs": epochs,
        "particles": n_particles,
        "screen_method": method,
        "errors": errors,
        "held_out_relative_l1": held,
        "held_out_relative_l1_diffaccel_forward": held_ours,
        **_verdict(errors, held),
    }


def headline(result: dict) -> dict[str, str]:
    """The docs page's figures: diffaccel's moment errors, held-out L1, time."""
    d, lim = result["diffaccel"], result["limits"]
    e, held = d["errors"], d["held_out_relative_l1"]
    rms = max(abs(v) for k, v in e.items() if k.startswith("rms_"))
    emits = ("emit_x", "emit_y", "emit_z")
    limits = " / ".join(f"{100 * lim[k]:g}" for k in emits)
    return {
        f"rms sizes vs truth (limit {100 * lim['rms_x']:g} %)": (
            f"within {100 * rms:.2f} %"
        ),
        f"emittances x / y / z vs truth (limits {limits} %)": " / ".join(
            f"{100 * e[k]:+.2f} %" for k in emits
        ),
        f"6D emittance vs truth (limit {100 * lim['emit_6d']:g} %)": (
            f"{100 * e['emit_6d']:+.2f} %"
        ),
        "held-out relative L1, dipole off / on": (
            f"{held['dipole_off']:.3f} / {held['dipole_on']:.3f}"
        ),
        f"whole `diffaccel reconstruct --dims 6` (limit {lim['wall_s']:g} s)": (
            f"{d['wall_s']:.1f} s wall, {d['cpu_s']:.0f} s CPU"
        ),
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--skip-gpsr", action="store_true")
    ap.add_argument("--gpsr-epochs", type=int, default=1000)
    ap.add_argument("--gpsr-particles", type=int, default=10_000)
    ap.add_argument(
        "--gpsr-screen", default="cloud-in-cell", choices=["cloud-in-cell", "kde"]
    )
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument(
        "--device", default="cpu", choices=["cpu", "cuda"], help="diffaccel's device"
    )
    ap.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    add_store_flag(ap)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    train, test = read_scans(TRAIN), read_scans(TEST)
    truth = beam_moments(train.ground_truth)
    out: dict = {
        "name": "reconstruction_6d",
        "train": str(TRAIN.resolve()),
        "test": str(TEST.resolve()),
        "threads": args.threads,
        "torch": torch.__version__,
        "python": platform.python_version(),
        "device": args.device,
        "git_commit": git_commit(),
        "load_avg_1min_at_start": os.getloadavg()[0],
        "truth_rms": truth["rms"].tolist(),
        "limits": LIMITS
        | {"held_out_relative_l1": HELD_OUT_L1, "wall_s": WALL_LIMIT_S},
    }
    out["diffaccel"] = run_diffaccel(args.threads, test, args.device)
    if not args.skip_gpsr:
        out["gpsr"] = run_gpsr(
            train, test, args.gpsr_epochs, args.gpsr_particles, args.gpsr_screen
        )
        out["gpsr_note"] = (
            "GPSR6DLattice asks cheetah 0.8.4 for the dipole tracking method "
            "'bmadx', which no longer exists; cheetah warns (PhysicsWarning) and "
            "keeps the linear dipole map, so training runs on a linear dipole. "
            "Quadrupole and TDC use cheetah's linear maps."
        )
    out["load_avg_1min_at_end"] = os.getloadavg()[0]
    emit(out, args.out, headline=headline, store_result=args.store)


if __name__ == "__main__":
    main()
