"""Speed and memory of the exact-mode Preisach model: forward and forward+backward.

For each history length T in {100, 1000} and mesh size N in {990, 5050, 20100}
(triangular meshes with 44, 100, 200 cells per axis), times

* ``forward_s``: ``model(u)`` for a fresh random input sequence ``u`` of length T,
  including the hysteron state computation (no autograd graph);
* ``forward_backward_s``: the same with autograd on, then ``loss.backward()``
  down to the density and the output parameters (offset, slope, scale).

Each figure is the median of ``--repeats`` runs after two warm-up runs; the
spread is the interquartile range. ``peak_memory_mb`` is the growth of the
process's peak resident memory during the timed runs (after the model and inputs
exist), measured in a fresh subprocess per case so that cases do not hide each
other's peaks.

Anchor (not re-run here: the reference code is not installable as published,
see ``../shared/ANCHORS.md``): the paper authors' implementation takes 3.05 s
(and up to 1.6 GB) for forward+backward at T = 1000, N = 20 000, and 0.042 s at
T = 100, N = 1000, on a 2-core CPU like this one.

Every case runs with 1 intra-op thread and with torch's default: on a loaded
machine, multi-threaded kernels on these small tensors can be 10-50x slower
(threads wait for descheduled peers), so both are recorded.

Prints one JSON object on the last line; its ``records`` list holds one
``{"T", "N", "dtype", "threads", "forward_s", "forward_backward_s",
"peak_memory_mb", ...}`` per case.
"""

from __future__ import annotations

import argparse
import itertools
import json
import platform
import resource
import statistics
import subprocess
import sys
import time

import torch
from _meta import add_store_flag, emit, git_commit, span

from diffaccel.hysteresis import PreisachMesh, PreisachModel

CASES = [(100, 44), (100, 100), (100, 200), (1000, 44), (1000, 100), (1000, 200)]
ANCHOR = {
    "source": "shared/ANCHORS.md (reference implementation, 2-core CPU)",
    "T1000_N20000_forward_backward_s": 3.05,
    "T1000_N20000_peak_memory_mb": 1600.0,
    "T100_N1000_forward_backward_s": 0.042,
}
TARGETS = {"T1000_N20000": 0.1, "T100_N1000": 0.01}


def _maxrss_mb() -> float:
    # Linux reports kB
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _quartiles(xs: list[float]) -> tuple[float, float, float]:
    q = statistics.quantiles(xs, n=4, method="inclusive")
    return q[0], statistics.median(xs), q[2]


def run_case(t: int, n: int, dtype: torch.dtype, repeats: int, seed: int) -> dict:
    """Time one (T, mesh) case in this process."""
    gen = torch.Generator().manual_seed(seed)
    model = PreisachModel(
        PreisachMesh.triangular(n), input_range=(0.0, 1.0), dtype=dtype
    )
    inputs = [torch.rand(t, generator=gen, dtype=dtype) for _ in range(repeats + 2)]
    fwd, fwd_bwd = [], []
    base = _maxrss_mb()
    with torch.no_grad():
        for i, u in enumerate(inputs):
            t0 = time.perf_counter()
            model(u)
            if i >= 2:
                fwd.append(time.perf_counter() - t0)
    for i, u in enumerate(inputs):
        model.zero_grad(set_to_none=True)
        t0 = time.perf_counter()
        model(u).square().mean().backward()
        if i >= 2:
            fwd_bwd.append(time.perf_counter() - t0)
    assert model.raw_density.grad is not None and model.scale.grad is not None
    f_q = _quartiles(fwd)
    fb_q = _quartiles(fwd_bwd)
    return {
        "T": t,
        "N": int(model.alpha.numel()),
        "mesh_cells": n,
        "dtype": str(dtype).removeprefix("torch."),
        "forward_s": f_q[1],
        "forward_iqr_s": [f_q[0], f_q[2]],
        "forward_backward_s": fb_q[1],
        "forward_backward_iqr_s": [fb_q[0], fb_q[2]],
        "peak_memory_mb": max(_maxrss_mb() - base, 0.0),
        "repeats": repeats,
    }


def headline(result: dict) -> dict[str, str]:
    """The docs page's figures: forward+backward times and memory vs the anchor.

    Times span the thread counts and dtypes run.
    """
    checks, anchor = result["checks"].values(), result["anchor"]
    big = [c["T1000_N20100_forward_backward_s"] for c in checks]
    small = [c["T100_N990_forward_backward_s"] for c in checks]
    memory = max(
        r["peak_memory_mb"]
        for r in result["records"]
        if r["T"] == 1000 and r["N"] == 20100
    )
    ref_big = anchor["T1000_N20000_forward_backward_s"]
    ref_mem = anchor["T1000_N20000_peak_memory_mb"] / 1000
    ref_small = anchor["T100_N1000_forward_backward_s"]
    return {
        "forward+backward, T = 1000 steps, 20 100 hysterons": (
            f"{span(big, '.3f')} s (reference code {ref_big:.3g} s)"
        ),
        "peak memory, same case": f"{memory:.0f} MB (reference code {ref_mem:.2g} GB)",
        "forward+backward, T = 100, 990 hysterons": (
            f"{span(small, '.2g')} s (reference code {ref_small:.2g} s)"
        ),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument(
        "--threads",
        type=int,
        nargs="+",
        default=None,
        help="torch intra-op thread counts to run (default: 1 and torch's default)",
    )
    parser.add_argument(
        "--dtypes",
        nargs="+",
        default=["float64", "float32"],
        choices=["float64", "float32"],
    )
    parser.add_argument(
        "--case", nargs=3, metavar=("T", "CELLS", "DTYPE"), help=argparse.SUPPRESS
    )
    add_store_flag(parser)
    args = parser.parse_args()
    if args.case is not None:  # child process: one case, one JSON line
        if args.threads is not None:
            torch.set_num_threads(args.threads[0])
        t, n, dt = int(args.case[0]), int(args.case[1]), getattr(torch, args.case[2])
        record = run_case(t, n, dt, args.repeats, seed=t + n)
        record["threads"] = torch.get_num_threads()
        print(json.dumps(record))
        return
    threads = args.threads or sorted({1, torch.get_num_threads()})
    records = []
    for nt in threads:
        for dt in args.dtypes:
            for t, n in CASES:
                cmd = [sys.executable, __file__, "--case", str(t), str(n), dt]
                cmd += ["--repeats", str(args.repeats), "--threads", str(nt)]
                out = subprocess.run(cmd, capture_output=True, text=True, check=True)
                records.append(json.loads(out.stdout.strip().splitlines()[-1]))
    by_key = {(r["T"], r["N"], r["dtype"], r["threads"]): r for r in records}
    checks = {}
    for nt, dt in itertools.product(threads, args.dtypes):
        big = by_key[(1000, 20100, dt, nt)]["forward_backward_s"]
        small = by_key[(100, 990, dt, nt)]["forward_backward_s"]
        checks[f"{dt}_threads{nt}"] = {
            "T1000_N20100_forward_backward_s": big,
            "T1000_N20100_meets_0.1s": big <= TARGETS["T1000_N20000"],
            "T1000_N20100_speedup_vs_anchor": ANCHOR["T1000_N20000_forward_backward_s"]
            / big,
            "T100_N990_forward_backward_s": small,
            "T100_N990_meets_0.01s": small <= TARGETS["T100_N1000"],
            "T100_N990_speedup_vs_anchor": ANCHOR["T100_N1000_forward_backward_s"]
            / small,
        }
    result = {
        "name": "preisach",
        "device": "cpu",
        "threads": threads,
        "torch": torch.__version__,
        "python": platform.python_version(),
        "git_commit": git_commit(),
        "anchor": ANCHOR,
        "targets_s": TARGETS,
        "checks": checks,
        "records": records,
    }
    emit(result, headline=headline, store_result=args.store)


if __name__ == "__main__":
    main()
