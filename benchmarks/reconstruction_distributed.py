"""torchrun scaling of ``diffaccel reconstruct``: 1 -> 2 processes (gloo, CPU).

Runs ``diffaccel reconstruct`` on the even settings of the GPSR 4D benchmark
once as a plain process and once under ``torchrun --standalone --nproc-per-node
2 ... --distributed`` (one thread per process), both with the same total number
of particles, and reports the training time of each (from ``summary.json``), its
ratio, and the rms sizes of both results with their relative difference. A
third run, ``--distributed --split members``, trains one whole-beam ensemble per
process (``members``: twice the single run's) and reports its time and rms.

Usage: ``python benchmarks/reconstruction_distributed.py [--particles 6144]
[--steps 300]``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from _meta import add_store_flag, emit, git_commit

DATA = Path(__file__).resolve().parents[1] / "data" / "phase_space"
DATASET = DATA / "gpsr_4d_synthetic.h5"


def _run(cmd: list[str], out: Path) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS="1")
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, env=env, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    s = json.loads((out / "summary.json").read_text())
    return {
        "wall_s": wall,
        "training_s": s["timings_s"].get("training"),
        "rms": s["moments"]["rms"]["mean"][:4],
        "held_out_relative_l1": s["metrics"]["images_held_out"]["relative_l1"],
        "members": s["snapshots"],
    }


def headline(result: dict) -> dict[str, str]:
    """The docs page's figures: 2 ranks against 1 process."""
    one, two = result["single"], result["torchrun_2_gloo"]
    worst = max(abs(v) for v in result["rms_relative_difference"])
    limit = 100 * result["acceptance_max_abs_rms_difference"]
    return {
        f"rms sizes, 2 ranks vs 1 process (limit {limit:g} %)": (
            f"within {100 * worst:.2f} %"
        ),
        "held-out relative L1, 2 ranks vs 1 process": (
            f"{two['held_out_relative_l1']:.3f} vs {one['held_out_relative_l1']:.3f}"
        ),
        f"training time, 1 process vs 2 ranks ({result['particles']} particles)": (
            f"{one['training_s']:.1f} s vs {two['training_s']:.1f} s"
        ),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--particles", type=int, default=6144)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--json", type=Path, default=None)
    add_store_flag(ap)
    args = ap.parse_args()
    bindir = Path(sys.executable).parent
    common = [
        str(DATASET),
        "--particles",
        str(args.particles),
        "--steps",
        str(args.steps),
        "--train-indices",
        "even",
        "--no-figures",
    ]
    torchrun = [str(bindir / "torchrun"), "--standalone", "--nproc-per-node", "2"]
    with tempfile.TemporaryDirectory() as tmp:
        one, two, mem = Path(tmp) / "one", Path(tmp) / "two", Path(tmp) / "mem"
        single = _run(
            [str(bindir / "diffaccel"), "reconstruct", *common, "--out", str(one)], one
        )
        dist = _run(
            [
                *torchrun,
                "-m",
                "diffaccel",
                "reconstruct",
                *common,
                "--out",
                str(two),
                "--distributed",
            ],
            two,
        )
        # members on different processes: each trains the whole beam
        members = _run(
            [
                *torchrun,
                *("-m", "diffaccel", "reconstruct", *common, "--out", str(mem)),
                *("--distributed", "--split", "members"),
            ],
            mem,
        )
    rel = [b / a - 1 for a, b in zip(single["rms"], dist["rms"], strict=True)]
    emit(
        {
            "name": "reconstruction_distributed",
            "dataset": str(DATASET.resolve()),
            "particles": args.particles,
            "steps": args.steps,
            "single": single,
            "torchrun_2_gloo": dist,
            "torchrun_2_gloo_split_members": members,
            "speedup_training": single["training_s"] / dist["training_s"],
            "rms_relative_difference": rel,
            "acceptance_max_abs_rms_difference": 0.02,
            "load_avg_1min": os.getloadavg()[0],
            "cpus": os.cpu_count(),
            "torch": torch.__version__,
            "python": platform.python_version(),
            "git_commit": git_commit(),
        },
        args.json,
        headline=headline,
        store_result=args.store,
    )


if __name__ == "__main__":
    main()
