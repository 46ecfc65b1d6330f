"""Xopt's own loop on 3 hysteretic quadrupoles: Xopt's UCB vs ``hysteresis_bayesian``.

The simulated machine of ``bo_hysteresis.py`` (three quadrupoles whose
integrated gradients follow their own Preisach models of the current history;
target: round beam of ``--target`` rms size; measured objective: the distance
to target [mm] plus noise, minimised). Both optimisers run through ``Xopt``:
``xopt_ucb`` is Xopt's ``UpperConfidenceBoundGenerator`` (beta = 2, its
standard GP on the currents), ``hysteresis`` is
:class:`diffaccel.hysteresis.xopt_generator.HysteresisBayesianGenerator`
(beta = 2, an H-GP with a uniform Preisach prior on each current, refitted at
every step). Same budget: ``--n-init`` random settings (the same per seed for
both, evaluated with ``Xopt.evaluate_data``) then ``X.step()`` up to
``--steps`` evaluations; every run starts from negative saturation.

Prints one JSON object on the last line (``final_best``: the true distance to
target [mm] of the best setting tried, lower is better) and writes
``xopt_hysteresis.json`` into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path

import pandas as pd
import torch
from _meta import add_store_flag, emit, git_commit
from bo_hysteresis import I_MAX, Machine
from xopt import Evaluator, Xopt
from xopt.generators.bayesian import UpperConfidenceBoundGenerator
from xopt.numerical_optimizer import LBFGSOptimizer

from diffaccel.data import atomic_write_text
from diffaccel.hysteresis.xopt_generator import (
    HysteresisBayesianGenerator,
    HysteresisModelConstructor,
)

NAMES = ["Q1", "Q2", "Q3"]


def run(method: str, seed: int, args: argparse.Namespace) -> list[float]:
    """One Xopt run; returns the true distance [mm] after every evaluation."""
    machine = Machine(seed, args.particles, args.target)
    noise_gen = torch.Generator().manual_seed(5000 + seed)
    dist: list[float] = []

    def measure(inputs: dict) -> dict:
        d = machine.apply(torch.tensor([float(inputs[n]) for n in NAMES]))
        dist.append(d)
        return {"d": d + args.noise * float(torch.randn((), generator=noise_gen))}

    vocs = {
        "variables": {n: [-I_MAX, I_MAX] for n in NAMES},
        "objectives": {"d": "MINIMIZE"},
    }
    opt = LBFGSOptimizer(n_restarts=args.acq_restarts)
    if method == "xopt_ucb":
        gen = UpperConfidenceBoundGenerator(
            vocs=vocs, beta=2.0, numerical_optimizer=opt
        )
    else:
        gen = HysteresisBayesianGenerator(
            vocs=vocs,
            beta=2.0,
            hysteretic_inputs=NAMES,
            gp_constructor=HysteresisModelConstructor(
                mesh_n=args.mesh_n, fit_max_iter=args.fit_iter, seed=seed
            ),
            numerical_optimizer=opt,
        )
    X = Xopt(generator=gen, evaluator=Evaluator(function=measure))
    g = torch.Generator().manual_seed(seed)
    init = (
        torch.rand(args.n_init, 3, generator=g, dtype=torch.float64) * 2 - 1
    ) * I_MAX
    X.evaluate_data(pd.DataFrame(init.numpy(), columns=NAMES))
    torch.manual_seed(seed)
    while len(dist) < args.steps:
        X.step()
    return dist[: args.steps]


def headline(result: dict) -> dict[str, str]:
    """The docs page's figures: median final distances, their ratio, time per run."""
    h, u, seeds = result["hysteresis"], result["xopt_ucb"], result["seeds"]
    runs = f"{seeds} seeds x {result['steps']} steps"
    return {
        "median final distance to target through Xopt's loop, hysteresis_bayesian "
        f"vs Xopt's UCB ({runs})": (
            f"{h['median_final_best']:.3f} mm vs {u['median_final_best']:.3f} mm"
        ),
        "Xopt UCB / hysteresis_bayesian (median final distance)": (
            f"{result['ratio_xopt_ucb_over_hysteresis']:.3g}x"
        ),
        "time per run, hysteresis_bayesian vs Xopt's UCB": (
            f"{h['time_s'] / seeds:.0f} s vs {u['time_s'] / seeds:.0f} s"
        ),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, default=Path("out") / "benchmarks")
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--n-init", type=int, default=5)
    parser.add_argument("--target", type=float, default=1.2, help="rms size [mm]")
    parser.add_argument("--noise", type=float, default=0.01, help="[mm]")
    parser.add_argument("--particles", type=int, default=1000)
    parser.add_argument("--mesh-n", type=int, default=12, help="H-GP mesh (78)")
    parser.add_argument("--fit-iter", type=int, default=100)
    parser.add_argument("--acq-restarts", type=int, default=2)
    parser.add_argument("--threads", type=int, default=1)
    add_store_flag(parser)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    warnings.filterwarnings("ignore")

    t_start = time.perf_counter()
    methods = ("xopt_ucb", "hysteresis")
    curves: dict[str, list[list[float]]] = {m: [] for m in methods}
    times = {m: 0.0 for m in methods}
    args.out.mkdir(parents=True, exist_ok=True)
    for seed in range(args.seeds):
        for method in methods:
            t0 = time.perf_counter()
            dist = run(method, seed, args)
            times[method] += time.perf_counter() - t0
            curves[method].append(torch.tensor(dist).cummin(0).values.tolist())
        result = _result(curves, times, seed + 1, time.perf_counter() - t_start, args)
        if seed + 1 < args.seeds:  # the seeds done so far, kept if the run stops
            path = args.out / "xopt_hysteresis.partial.json"
            atomic_write_text(path, json.dumps(result) + "\n")
    emit(
        result,
        args.out / "xopt_hysteresis.json",
        headline=headline,
        store_result=args.store,
    )


def _result(
    curves: dict[str, list[list[float]]],
    times: dict[str, float],
    seeds: int,
    total: float,
    args: argparse.Namespace,
) -> dict[str, object]:
    """Summary of the seeds run so far."""

    def summary(method: str) -> dict[str, object]:
        c = torch.tensor(curves[method])
        final = c[:, -1]
        return {
            "median_final_best": float(final.quantile(0.5)),
            "quartiles_final_best": [
                float(final.quantile(0.25)),
                float(final.quantile(0.75)),
            ],
            "final_best_per_seed": final.tolist(),
            "median_curve": c.quantile(0.5, dim=0).tolist(),
            "time_s": times[method],
        }

    res = {m: summary(m) for m in curves}
    return {
        "name": "xopt_hysteresis",
        "objective": "distance of (sigma_x, sigma_y) to (target, target) [mm]",
        "xopt_ucb": res["xopt_ucb"],
        "hysteresis": res["hysteresis"],
        "ratio_xopt_ucb_over_hysteresis": res["xopt_ucb"]["median_final_best"]
        / max(res["hysteresis"]["median_final_best"], 1e-12),
        "seeds": seeds,
        "steps": args.steps,
        "n_init": args.n_init,
        "target_mm": args.target,
        "noise_mm": args.noise,
        "hgp_hysterons_per_magnet": args.mesh_n * (args.mesh_n + 1) // 2,
        "total_time_s": total,
        "torch": torch.__version__,
        "git_commit": git_commit(),
        "higher_is_better": False,
    }


if __name__ == "__main__":
    main()
