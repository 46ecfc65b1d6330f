"""One training step of the default 4D reconstruction: time, ATen ops, host syncs.

Trains the default configuration on the even settings of the GPSR 4D benchmark
(``data/phase_space/gpsr_4d_synthetic.h5``) for ``--steps`` and for
twice as many steps, under ``torch.profiler``; per-step figures are the
differences divided by ``--steps`` (set-up, initial fit and the per-snapshot
bookkeeping cancel; progress reads every ``report_every`` steps are included).
Counts, per step on average:

* ``aten_ops_per_step``: every ``aten::*`` event, nested ones included (views,
  implicit copies and casts inside an operator count too);
* ``aten_ops_top_level_per_step``: top-level ATen operators (``aten::*`` events
  with no ATen parent; each is at least one kernel launch on a GPU);
* ``host_syncs``: ``aten::item`` / ``aten::_local_scalar_dense`` events (the
  ops that read a device value on the host, i.e. synchronise on CUDA).

The budget: at most 1 sync and 300 ops per step without the moment term
(``moment_weight = 0``, ``aten_ops_per_step_without_moment_term``) and 80 more
for the moment term; ``met`` applies them to the stricter count,
``aten_ops_per_step``. Counts are deterministic; the
per-step time (the same difference of the median training times of
``--repeats`` unprofiled runs) depends on the machine's load.

On a CUDA device the default 4D step is captured as a CUDA graph after three
eager steps (``reconstruct(..., cuda_graph=...)``): the ATen ops counted are
then the host's per step (one row copy, the replay, the copies of the losses);
the ~290 operators of the step run inside the graph. ``--eager`` turns the
graph off, the baseline to quote beside it (same run, same GPU).

Usage: ``python benchmarks/reconstruction_step.py [--steps 60] [--repeats 3]
[--particles 6144] [--device cpu] [--threads 1] [--top 0] [--eager]``
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from collections import Counter
from pathlib import Path

import torch
from _meta import add_store_flag, emit, git_commit

from diffaccel.data import read_quad_scan
from diffaccel.reconstruction import ReconstructionConfig, reconstruct
from diffaccel.reconstruction.training import REPORT_EVERY

DATA = Path(__file__).resolve().parents[1] / "data" / "phase_space"
DATASET = DATA / "gpsr_4d_synthetic.h5"
SYNC_OPS = ("aten::item", "aten::_local_scalar_dense")


def _config(steps: int, particles: int, **fields) -> ReconstructionConfig:
    return ReconstructionConfig(n_particles=particles, steps=steps, **fields)


def _profile(ds, train, cfg, device, graph: bool) -> tuple[list, float]:
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as p:
        t0 = time.perf_counter()
        reconstruct(ds, cfg, train_indices=train, device=device, cuda_graph=graph)
        wall = time.perf_counter() - t0
    return list(p.events()), wall


def _top_level(events) -> list:
    """ATen events whose parents are not ATen events."""
    out = []
    for e in events:
        if not e.name.startswith("aten::"):
            continue
        p = e.cpu_parent
        nested = False
        while p is not None:
            if p.name.startswith("aten::"):
                nested = True
                break
            p = p.cpu_parent
        if not nested:
            out.append(e)
    return out


def headline(result: dict) -> dict[str, str | float]:
    """The docs page's figures: ATen ops and host syncs per step, step time."""
    acc = result["acceptance"]
    threads = result["threads"]
    where = "CPU" if result["device"] == "cpu" else result["device"]
    syncs = result["host_syncs_per_step"]
    without = result.get("aten_ops_per_step_without_moment_term")
    moment = acc.get("max_moment_term_aten_ops")
    budget = f"{acc['max_aten_ops']}" + (f" + {moment} moment term" if moment else "")
    figures = {
        f"ATen ops per default 4D training step (budget <= {budget})": (
            round(result["aten_ops_per_step"], 1)
        ),
        f"host syncs per step (budget <= {acc['max_host_syncs']})": (
            int(syncs) if syncs == int(syncs) else round(syncs, 2)
        ),
        f"step time, {where}, {threads} thread{'s' if threads != 1 else ''}": (
            f"{1000 * result['step_time_s']:.1f} ms"
        ),
    }
    if without is not None:
        figures["ATen ops per step without the moment term"] = round(without, 1)
    return figures


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--steps", type=int, default=60, help="short run; long = 2x")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per length")
    ap.add_argument("--particles", type=int, default=ReconstructionConfig.n_particles)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--top", type=int, default=0, help="list the N commonest ops")
    ap.add_argument(
        "--eager",
        action="store_true",
        help="no CUDA graph on a GPU (cuda_graph=False): the step launched op by op",
    )
    ap.add_argument("--json", type=Path, default=None)
    add_store_flag(ap)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.optim.Adam([torch.zeros(1, requires_grad=True)])  # one-off import
    ds = read_quad_scan(DATASET)
    train = list(range(0, ds.n_settings, 2))
    short, long = args.steps, 2 * args.steps
    # per-step figures: (long run - short run) / (long - short steps), so that
    # set-up, initial fit and the ensemble's bookkeeping cancel; both runs have
    # the same number of snapshots, hence the same extra reads
    timings = {}
    for steps in (short, long):
        t = []
        for _ in range(args.repeats):
            r = reconstruct(
                ds,
                _config(steps, args.particles),
                train_indices=train,
                device=args.device,
                cuda_graph=not args.eager,
            )
            t.append(r.info["timings_s"]["training"])
        timings[steps] = statistics.median(t)
    step_time = (timings[long] - timings[short]) / (long - short)
    counts, core = {}, {}
    for steps in (short, long):
        events, _ = _profile(
            ds, train, _config(steps, args.particles), args.device, not args.eager
        )
        aten = [e for e in events if e.name.startswith("aten::")]
        counts[steps] = {
            "all": aten,
            "top": _top_level(events),
            "syncs": sum(e.name in SYNC_OPS for e in aten),
        }
        # the same step without the moment term
        events, _ = _profile(
            ds,
            train,
            _config(steps, args.particles, moment_weight=0.0),
            args.device,
            not args.eager,
        )
        core[steps] = sum(e.name.startswith("aten::") for e in events)
    d = long - short
    cfg = _config(short, args.particles)
    result = {
        "name": "reconstruction_step",
        "dataset": str(DATASET.resolve()),
        "device": args.device,
        "cuda_graph": not args.eager,
        "threads": torch.get_num_threads(),
        "n_particles": cfg.n_particles,
        "train_images": len(train),
        "steps_compared": [short, long],
        "report_every": REPORT_EVERY,
        "aten_ops_per_step": (len(counts[long]["all"]) - len(counts[short]["all"])) / d,
        "aten_ops_per_step_without_moment_term": (core[long] - core[short]) / d,
        "aten_ops_top_level_per_step": (
            len(counts[long]["top"]) - len(counts[short]["top"])
        )
        / d,
        "host_syncs_per_step": (counts[long]["syncs"] - counts[short]["syncs"]) / d,
        "step_time_s": step_time,
        "training_s": timings,
        "acceptance": {
            "max_aten_ops": 300,
            "max_moment_term_aten_ops": 80,
            "max_host_syncs": 1,
        },
        "load_avg_1min": os.getloadavg()[0],
        "torch": torch.__version__,
        "python": platform.python_version(),
        "git_commit": git_commit(),
    }
    # met on the stricter count (every ATen event, nested ones included): 300
    # for the step without the moment term, 80 more for that term
    without = result["aten_ops_per_step_without_moment_term"]
    result["met"] = (
        without <= 300
        and result["aten_ops_per_step"] - without <= 80
        and result["host_syncs_per_step"] <= 1
    )
    if args.top:
        ca = Counter(e.name for e in counts[long]["all"])
        ca.subtract(Counter(e.name for e in counts[short]["all"]))
        result["top_ops_per_step"] = [(k, v / d) for k, v in ca.most_common(args.top)]
    emit(result, args.json, headline=headline, store_result=args.store)


if __name__ == "__main__":
    main()
