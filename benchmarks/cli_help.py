"""Start-up of the command-line tool: ``diffaccel --help`` vs ``import torch``.

Both run as fresh processes, alternately, ``--repeats`` times each (median and
spread reported). The target: ``--help`` at most 1.3x ``import torch``;
since commands load lazily, ``--help`` imports neither torch nor any command.
Also times ``diffaccel reconstruct --help`` (imports what reconstruct uses).

Usage: ``python benchmarks/cli_help.py [--repeats 7]``
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch
from _meta import add_store_flag, emit, git_commit


def _time(cmd: list[str]) -> float:
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def headline(result: dict) -> dict[str, str]:
    """The docs page's figures: the two start-up ratios against ``import torch``."""
    limit = result["acceptance_max_ratio"]
    return {
        f"`diffaccel --help` / `python -c 'import torch'` (limit {limit:g}x)": (
            f"{result['ratio_help_vs_import_torch']:.2g}x"
        ),
        f"`diffaccel reconstruct --help` / import torch (limit {limit:g}x)": (
            f"{result['ratio_reconstruct_help_vs_import_torch']:.3g}x"
        ),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--json", type=Path, default=None)
    add_store_flag(parser)
    args = parser.parse_args()
    exe = shutil.which("diffaccel", path=str(Path(sys.executable).parent))
    runs = {
        "import_torch": [sys.executable, "-c", "import torch"],
        "help": [exe or "diffaccel", "--help"],
        "reconstruct_help": [exe or "diffaccel", "reconstruct", "--help"],
    }
    times: dict[str, list[float]] = {k: [] for k in runs}
    for cmd in runs.values():  # warm the file cache once
        _time(cmd)
    for _ in range(args.repeats):
        for k, cmd in runs.items():
            times[k].append(_time(cmd))
    med = {k: statistics.median(v) for k, v in times.items()}
    emit(
        {
            "name": "cli_help",
            "repeats": args.repeats,
            "median_s": med,
            "min_s": {k: min(v) for k, v in times.items()},
            "max_s": {k: max(v) for k, v in times.items()},
            "ratio_help_vs_import_torch": med["help"] / med["import_torch"],
            "ratio_reconstruct_help_vs_import_torch": med["reconstruct_help"]
            / med["import_torch"],
            "acceptance_max_ratio": 1.3,
            "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
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
