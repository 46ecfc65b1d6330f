"""``hysteresis predict`` on a long history: time and peak memory, streamed.

A fit folder with a 990-hysteron model (mesh 44) and its predictive band is
written, then a CSV of ``--rows`` random set-points (default 10^6) is
predicted by the CLI in a fresh process, as a user runs it:
``cli_wall_s`` and ``cli_peak_rss_mb`` (the child's peak resident memory,
everything included: Python start-up, imports, CSV parsing and writing), the
median of ``--cli-repeats`` runs, with the child's CPU time and the machine's
load average (on a shared machine the wall time is inflated by the others'
work). The command imports no torch (numpy and scipy only, see
``diffaccel.hysteresis.stream``); its reader and writer threads overlap the
model where numpy and scipy release the GIL. ``--threads`` sets
``OMP_NUM_THREADS`` for it. The library part alone (``predict_stream`` with the
band, and the mean only; one thread) is timed in this process, as the median
of ``--repeats`` runs.

Anchor (recorded, not re-run: the old one-pass code needs 8.5 GB): the
same 10^6 rows x 1000 hysterons took 58 s and 8.5 GB before streaming.
Targets: at least 10x faster (5.8 s) and under 500 MB.

Prints one JSON object on the last line.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from _meta import add_store_flag, emit, git_commit

from diffaccel.data import write_csv_atomic
from diffaccel.hysteresis import fit_magnet, predict_stream, save_fit
from diffaccel.hysteresis.synthetic import synthetic_measurement

ANCHOR = {"source": "issue 11", "wall_s": 58.0, "peak_rss_mb": 8500.0}
TARGETS = {"wall_s": 5.8, "peak_rss_mb": 500.0}
MESH = 44


_PROBE = (
    "import resource, subprocess, sys\n"
    "subprocess.run(sys.argv[1:], check=True, capture_output=True)\n"
    "r = resource.getrusage(resource.RUSAGE_CHILDREN)\n"
    "print(r.ru_utime + r.ru_stime, r.ru_maxrss / 1024.0)\n"
)


def headline(result: dict) -> dict[str, str]:
    """The docs page's figures: the CLI's wall time, peak RSS and speed-up."""
    rows, targets, anchor = result["rows"], result["targets"], result["anchor"]
    power = math.log10(rows) if rows > 0 else 0.5
    rows_text = f"10^{power:.0f}" if power == int(power) else f"{rows:,}"
    case = f"{rows_text} rows, {result['n_hysterons']} hysterons"
    reference = f"{anchor['wall_s']:g} s, {anchor['peak_rss_mb'] / 1000:g} GB"
    return {
        f"`hysteresis predict`, {case}, with band: wall (target "
        f"{targets['wall_s']:g} s)": f"{result['cli_wall_s']:.2f} s",
        f"peak RSS (target {targets['peak_rss_mb']:g} MB)": (
            f"{result['cli_peak_rss_mb']:.0f} MB"
        ),
        f"speed-up vs the one-pass reference ({reference})": (
            f"{result['speedup_vs_anchor']:.3g}x"
        ),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--threads", type=int, default=None, help="default: torch's default"
    )
    parser.add_argument("--cli-repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON")
    add_store_flag(parser)
    args = parser.parse_args()
    # the library part on one thread, as the CLI's model thread runs
    torch.set_num_threads(1 if args.threads is None else args.threads)
    current, field, _ = synthetic_measurement(noise=1e-4, seed=0)
    fit = fit_magnet(current, field, mesh_size=MESH, steps=100)
    model, band = fit.model, fit.band
    gen = torch.Generator().manual_seed(0)
    u = 10.0 * torch.rand(args.rows, generator=gen, dtype=torch.float64)
    times_band, times_mean = [], []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        for _pred, _std in predict_stream(model, u.split(20_000), band):
            pass
        times_band.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        for _pred, _ in predict_stream(model, u.split(20_000)):
            pass
        times_mean.append(time.perf_counter() - t0)
    with tempfile.TemporaryDirectory() as tmp:
        fit_dir = Path(tmp) / "fit"
        save_fit(fit_dir, model, band, extra={"input_column": "current_A"})
        data = Path(tmp) / "long.csv"
        write_csv_atomic(data, ["current_A"], [[v] for v in u.tolist()])
        out = Path(tmp) / "pred.csv"
        exe = Path(sys.executable).with_name("diffaccel")  # the console script
        cmd = [str(exe), "hysteresis", "predict"]
        cmd += [str(fit_dir), "--input", str(data), "--out", str(out)]
        env = dict(os.environ)
        env.pop("OMP_NUM_THREADS", None)
        if args.threads is not None:
            env["OMP_NUM_THREADS"] = str(args.threads)
        walls, cpus, loads, peaks = [], [], [], []
        for _ in range(args.cli_repeats):
            out.unlink(missing_ok=True)
            loads.append(os.getloadavg()[0])
            # a small fresh Python starts the CLI and reports the CLI's own
            # peak RSS and CPU time (a child forked from this big process would
            # count this process's pages in its peak before exec)
            t0 = time.perf_counter()
            probe = subprocess.run(
                [sys.executable, "-c", _PROBE, *cmd],
                check=True,
                capture_output=True,
                text=True,
                env=env,
            )
            walls.append(time.perf_counter() - t0)
            cpu_s, peak_mb = (float(v) for v in probe.stdout.split()[-2:])
            cpus.append(cpu_s)
            peaks.append(peak_mb)
        wall = statistics.median(walls)
        peak = max(peaks)
        with out.open() as f:
            n_out = sum(1 for _ in f) - 1
    result = {
        "name": "preisach_stream",
        "device": "cpu",
        "threads_library": torch.get_num_threads(),
        "threads_cli": "the model, a reader and a writer thread (numpy, no torch)",
        "cpu_count": os.cpu_count(),
        "dtype": "float64",
        "torch": torch.__version__,
        "python": platform.python_version(),
        "git_commit": git_commit(),
        "rows": args.rows,
        "n_hysterons": int(model.alpha.numel()),
        "band_directions": int(band.directions.shape[0]),
        "cli_wall_s": wall,
        "cli_wall_runs_s": walls,
        "cli_cpu_s": statistics.median(cpus),
        "load_average_1min": loads,
        "cli_peak_rss_mb": peak,
        "cli_rows_written": n_out,
        "library_with_band_s": statistics.median(times_band),
        "library_with_band_spread_s": [min(times_band), max(times_band)],
        "library_mean_only_s": statistics.median(times_mean),
        "library_ns_per_row_with_band": 1e9 * statistics.median(times_band) / args.rows,
        "anchor": ANCHOR,
        "targets": TARGETS,
        "speedup_vs_anchor": ANCHOR["wall_s"] / wall,
        "meets_wall": wall <= TARGETS["wall_s"],
        "meets_memory": peak <= TARGETS["peak_rss_mb"],
        "meets_targets": wall <= TARGETS["wall_s"] and peak <= TARGETS["peak_rss_mb"],
    }
    emit(result, args.out, headline=headline, store_result=args.store)


if __name__ == "__main__":
    main()
