"""The GPU checks in one run, for a machine with a CUDA GPU (H100, H200 or the like).

Needs a Python whose torch sees the GPU, with diffaccel, cheetah and gpsr
installed (``make install TORCH=torch``, then ``pip install -e ".[bench]"``).
Runs, each as its own process writing JSON into ``--out``:

- the CUDA tests (``pytest -k cuda tests``);
- ``reconstruction_step.py`` at 6 144 and 100 000 particles, the CUDA-graph
  default and ``--eager`` as the same run's baseline (limits 3 and 5 ms per
  step);
- ``tracking.py`` against cheetah on the same GPU (target >= 5x for both image
  methods) with a 10^7-particle x 20-setting fit check;
- ``reconstruction_process.py``: the whole ``reconstruct`` against gpsr's
  recipe on the same GPU (target >= 5x);
- ``reconstruction_6d.py --skip-gpsr`` with diffaccel on the GPU.

Prints one JSON object on the last line (``_meta.emit``); ``--store`` writes
``results/gpu_checks.json``. On a machine without CUDA it stops at once with
a message (exit status 1).
Not part of ``make bench``.

Usage: ``python benchmarks/gpu_checks.py [--out gpu_results] [--store]``
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from _meta import add_store_flag, emit, span

HERE = Path(__file__).resolve().parent
#: Step-time limits [s] by particle count.
STEP_LIMITS = {6144: 3e-3, 100_000: 5e-3}
#: Whole-process speed-up over gpsr on the same GPU.
PROCESS_TARGET = 5.0


def _last_json(path: Path) -> dict | None:
    """The JSON object on the last line of ``path`` (None if absent or broken)."""
    try:
        return json.loads(path.read_text().strip().splitlines()[-1])
    except (OSError, IndexError, json.JSONDecodeError):
        return None


def summarise(out: Path) -> dict:
    """The result from the JSON files a run left in ``out``.

    ``steps``: per particle count, the CUDA-graph and eager step times [s]
    (a list: several runs' results may be pooled),
    ATen ops and host syncs per step; ``tracking``: the speed-ups over
    cheetah; ``process``: the whole-process ratios over gpsr; ``sixd``: the 6D
    benchmark's wall time [s] and failed limits. A check whose file is missing
    is listed in ``missing``.
    """
    result: dict = {"name": "gpu_checks", "steps": {}, "missing": []}
    device = out / "device.txt"
    if device.exists():
        result["device"] = device.read_text().strip()
    for n in STEP_LIMITS:
        graph = _last_json(out / f"step_{n}.json")
        eager = _last_json(out / f"step_{n}_eager.json")
        if graph is None or eager is None:
            result["missing"].append(f"step_{n}")
            continue
        result["steps"][str(n)] = {
            "step_time_s": [graph["step_time_s"]],
            "eager_step_time_s": [eager["step_time_s"]],
            "cuda_graph": graph.get("cuda_graph"),
            "aten_ops_per_step": graph.get("aten_ops_per_step"),
            "host_syncs_per_step": graph.get("host_syncs_per_step"),
            "limit_s": STEP_LIMITS[n],
        }
    tracking = _last_json(out / "tracking.json")
    if tracking is None:
        result["missing"].append("tracking")
    else:
        keys = ("ratio_vs_cheetah_kde", "ratio_vs_cheetah_cic", "fit")
        result["tracking"] = {k: tracking[k] for k in keys if k in tracking}
    process = _last_json(out / "process.json")
    if process is None or "ratio" not in process:
        result["missing"].append("process")
    else:
        ratios = process.get("ratios", [process["ratio"]])
        result["process"] = {"ratios": ratios, "target": PROCESS_TARGET}
    sixd = _last_json(out / "sixd.json")
    if sixd is None:
        result["missing"].append("sixd")
    else:
        d = sixd["diffaccel"]
        result["sixd"] = {"wall_s": d["wall_s"], "fails": d.get("fails", [])}
    tests = out / "tests.txt"
    if tests.exists():
        lines = tests.read_text().strip().splitlines()
        result["cuda_tests"] = lines[-1] if lines else ""
    return result


def headline(result: dict) -> dict[str, str]:
    """The docs page's figures: step times, the ratio over gpsr, the 6D run."""
    figures = {}
    steps = result.get("steps", {})
    if steps:
        limits = " / ".join(f"{1e3 * s['limit_s']:g}" for s in steps.values())
        counts = " / ".join(f"{int(n):,}".replace(",", " ") for n in steps)
        figures[
            f"default 4D step, CUDA graph, {counts} particles (limits {limits} ms)"
        ] = " / ".join(
            f"{span([1e3 * t for t in s['step_time_s']], '.2f')} ms"
            for s in steps.values()
        )
    if "process" in result:
        p = result["process"]
        figures[
            f"whole `reconstruct` vs gpsr on the same GPU (limit {p['target']:g}x)"
        ] = f"{span(p['ratios'], '.3g')}x"
    if "sixd" in result:
        s = result["sixd"]
        met = "every limit met" if not s["fails"] else "fails: " + ", ".join(s["fails"])
        figures["shared 6D benchmark on the GPU"] = f"{s['wall_s']:.0f} s, {met}"
    return figures


def _run(cmd: list[str], log: Path) -> int:
    with log.open("w") as f:
        return subprocess.run(
            cmd, cwd=HERE, stdout=f, stderr=subprocess.STDOUT
        ).returncode


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("gpu_results"))
    add_store_flag(ap)
    args = ap.parse_args()
    import torch

    if not torch.cuda.is_available():
        sys.exit("no CUDA device: the GPU checks need one")
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    (out / "device.txt").write_text(
        f"{torch.__version__} {torch.cuda.get_device_name()}\n"
    )
    py = sys.executable
    tests = [py, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-k", "cuda"]
    _run([*tests, str(HERE.parent / "tests")], out / "tests.txt")
    for n in STEP_LIMITS:
        step = [py, "reconstruction_step.py", "--device", "cuda", "--particles", str(n)]
        _run([*step, "--json", str(out / f"step_{n}.json")], out / f"step_{n}.log")
        _run(
            [*step, "--eager", "--json", str(out / f"step_{n}_eager.json")],
            out / f"step_{n}_eager.log",
        )
    _run(
        [py, "tracking.py", "--device", "cuda", "--fit-n", "10000000"],
        out / "tracking.json",
    )
    _run(
        [py, "reconstruction_process.py", "--device", "cuda", "--repeats", "2",
         "--json", str(out / "process.json")],
        out / "process.log",
    )  # fmt: skip
    _run(
        [py, "reconstruction_6d.py", "--skip-gpsr", "--device", "cuda",
         "--threads", "8", "--out", str(out / "sixd.json")],
        out / "sixd.log",
    )  # fmt: skip
    emit(summarise(out), headline=headline, store_result=args.store)


if __name__ == "__main__":
    main()
