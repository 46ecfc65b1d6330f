"""Whole process: ``diffaccel reconstruct`` vs gpsr 0.2.0's 4D recipe (GPSR 4D data).

The default ``reconstruct`` on the GPSR 4D training split, whole process,
at least 8x faster than the gpsr 0.2.0 recipe as a whole process, measured in
the same run.

The training split (the even settings of ``data/phase_space/
gpsr_4d_synthetic.h5``) is written to a temporary ``TRAIN.h5``; then, each as a
subprocess timed from outside (wall clock and the child's CPU time):

* ``diffaccel reconstruct TRAIN.h5 --out RUN`` with default options, as a user
  runs it: imports, training, evaluation, ensemble, particles file, summary and
  figures (``--repeats`` times; the median counts);
* ``python benchmarks/_gpsr4d.py TRAIN.h5 OUT``: imports gpsr and cheetah, reads
  the same file, trains gpsr's documented default 4D recipe (10 000 particles,
  2000 epochs, Adam 1e-3, MAE, cloud-in-cell screen) and saves the model.

Both children get the same ``OMP_NUM_THREADS`` (``--threads``) and run from
byte-compiled modules, as installed packages do (pip compiles them at install;
gpsr, cheetah and torch come with their ``.pyc`` files): before timing,
diffaccel's modules are compiled once (``compileall``, into the ignored
``__pycache__`` folders), since an editable install under
``PYTHONDONTWRITEBYTECODE`` would otherwise compile them from source in every
run (~0.2 s). Timings under
load are inflated (``load_avg_1min_*``); the ratio of the two, taken in one run,
is the criterion. Prints one JSON object; ``met`` is ``ratio >= 8`` on the CPU.

``--device cuda`` runs both on the GPU (``diffaccel reconstruct --device cuda``;
gpsr's Lightning trainer with ``accelerator="gpu"``); ``met`` is then ``ratio >=
5`` (the GPU target). The default ``cpu`` keeps gpsr on the CPU too.

Usage: ``python benchmarks/reconstruction_process.py [--threads 2] [--repeats 2]
[--gpsr-epochs 2000] [--skip-gpsr] [--device cpu]``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _meta import add_store_flag, emit, git_commit

HERE = Path(__file__).resolve().parent
DATA = HERE.parents[0] / "data" / "phase_space"
DATASET = DATA / "gpsr_4d_synthetic.h5"
TARGET = {"cpu": 8.0, "cuda": 5.0}


def _timed(cmd: list[str], env: dict) -> dict:
    """Run ``cmd``; wall and CPU seconds of the child, its last output line."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        sys.stderr.write(proc.stdout[-2000:] + proc.stderr[-4000:])
        raise SystemExit(f"{cmd[:3]} failed with exit status {proc.returncode}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    lines = [ln for ln in proc.stdout.splitlines() if ln.strip()]
    return {"wall_s": wall, "cpu_s": cpu, "last_line": lines[-1] if lines else ""}


def headline(result: dict) -> dict[str, str]:
    """The docs page's figures: whole-process ratio against gpsr, wall times."""
    d = result["diffaccel"]
    figures = {}
    if "gpsr" in result:
        target = result["acceptance"]["min_ratio"]
        figures[
            f"whole process, gpsr 0.2.0 / diffaccel reconstruct (target >= {target:g}x)"
        ] = f"{result['ratio']:.3g}x"
        figures["CPU time ratio"] = f"{result['ratio_cpu']:.3g}x"
    figures["diffaccel reconstruct, wall"] = f"{d['wall_s']:.2f} s"
    if "gpsr" in result:
        g = result["gpsr"]
        figures[f"gpsr 4D recipe ({g['epochs']} epochs), wall"] = f"{g['wall_s']:.3g} s"
    return figures


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=2, help="diffaccel runs")
    ap.add_argument("--gpsr-epochs", type=int, default=2000)
    ap.add_argument("--skip-gpsr", action="store_true")
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--json", type=Path, default=None)
    add_store_flag(ap)
    args = ap.parse_args()
    from diffaccel.data import read_quad_scan, write_quad_scan

    env = dict(
        os.environ, OMP_NUM_THREADS=str(args.threads), MKL_NUM_THREADS=str(args.threads)
    )
    env.pop("MPLBACKEND", None)
    import compileall

    import diffaccel

    # byte-compile diffaccel as an installation would (see the docstring)
    out_bytecode = compileall.compile_dir(
        Path(diffaccel.__file__).parent, quiet=1, legacy=False
    )
    cli = [sys.executable, "-m", "diffaccel"]
    out: dict = {
        "name": "reconstruction_process",
        "dataset": str(DATASET.resolve()),
        "split": "even settings (training)",
        "threads": args.threads,
        "device": args.device,
        "python": platform.python_version(),
        "git_commit": git_commit(),
        "load_avg_1min_at_start": os.getloadavg()[0],
        "diffaccel_byte_compiled": bool(out_bytecode),
    }
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        ds = read_quad_scan(DATASET)
        train = tmp / "TRAIN.h5"
        write_quad_scan(ds.subset(range(0, ds.n_settings, 2)), train)
        runs = []
        for i in range(args.repeats):
            cmd = [*cli, "reconstruct", str(train), "--out", str(tmp / f"run{i}")]
            run = _timed([*cmd, "--device", args.device], env)
            summary = json.loads((tmp / f"run{i}" / "summary.json").read_text())
            run["timings_s"] = summary.get("timings_s", {})
            run["train_images_relative_l1"] = summary["metrics"]["images_train"][
                "relative_l1"
            ]
            run["figures"] = summary.get("figures", [])
            runs.append(run)
        out["diffaccel"] = {
            "command": "diffaccel reconstruct TRAIN.h5 --out RUN --device "
            + args.device,
            "wall_s": statistics.median(r["wall_s"] for r in runs),
            "cpu_s": statistics.median(r["cpu_s"] for r in runs),
            "runs": runs,
        }
        if not args.skip_gpsr:
            g = _timed(
                [
                    sys.executable,
                    str(HERE / "_gpsr4d.py"),
                    str(train),
                    str(tmp / "gpsr"),
                    "--epochs",
                    str(args.gpsr_epochs),
                    "--device",
                    args.device,
                ],
                env,
            )
            g["command"] = (
                f"python benchmarks/_gpsr4d.py TRAIN.h5 OUT --epochs {args.gpsr_epochs}"
                f" --device {args.device}"
            )
            g["in_process_s"] = json.loads(g.pop("last_line"))["in_process_s"]
            g["epochs"] = args.gpsr_epochs
            out["gpsr"] = g
            d = out["diffaccel"]
            out["ratio"] = g["wall_s"] / d["wall_s"]
            out["ratio_cpu"] = g["cpu_s"] / d["cpu_s"]
            target = TARGET[args.device]
            out["acceptance"] = {"min_ratio": target}
            out["met"] = out["ratio"] >= target and args.gpsr_epochs == 2000
    for r in out["diffaccel"]["runs"]:
        r.pop("last_line", None)
    out["load_avg_1min_at_end"] = os.getloadavg()[0]
    emit(out, args.json, headline=headline, store_result=args.store)


if __name__ == "__main__":
    main()
