"""Bayesian optimisation of a beam size with 3 hysteretic quadrupoles: GP vs H-GP.

Simulated machine: three quadrupoles (0.1 m) separated by drifts, tracked with
``diffaccel.dynamics`` (1 000 particles, fixed sample). Each quadrupole's
integrated gradient follows its own known Preisach model of its current history
(wide loops plus a reversible part), so the same currents give different
focusing depending on the order in which they were set. Target: round beam of
``--target`` rms size at the end; the measured objective is
``-|(sigma_x, sigma_y) - target|`` [mm] plus noise. Both optimisers use UCB
(beta = 2) through :class:`diffaccel.hysteresis.HysteresisBO`: the plain GP as
``hysteresis={}`` (identical to BoTorch's SingleTaskGP), the H-GP with a
generic Preisach prior (uniform density, coarse mesh) on each current, refitted
jointly with the GP at every step (``hgp``), and the H-GP given each magnet's
measured density (here the true one, kept fixed: ``hgp_measured``, the
situation after magnetic measurements with ``fit_preisach``). Every run starts
from negative saturation with the same random initial settings per seed.

Prints one JSON object on the last line (``final_best`` is the distance to
target [mm] of the best setting tried, lower is better); writes
``bo_hysteresis.png`` and ``bo_hysteresis.json`` into ``--out``.
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import torch
from _meta import add_store_flag, emit, git_commit

from diffaccel.data import atomic_write
from diffaccel.dynamics import Beamline, Drift, Quadrupole, rms_sizes
from diffaccel.hysteresis import (
    HysteresisBO,
    HystereticMagnet,
    PreisachMesh,
    PreisachModel,
)
from diffaccel.plotting.hgp import plot_best_so_far

I_MAX = 10.0  # [A], currents in [-I_MAX, I_MAX]
P0C = 50e6  # [eV]
LENGTH = 0.1  # [m]
G_MAX = 0.15  # [T], integrated gradient at saturation: |k1| <= 9 1/m^2


def truth_magnets(seed: int) -> list[HystereticMagnet]:
    """Three magnets with different known densities (wide loops, some reversible)."""
    gen = torch.Generator().manual_seed(1000 + seed)
    magnets = []
    for j in range(3):
        pm = PreisachModel(PreisachMesh.triangular(n=40), input_range=(-I_MAX, I_MAX))
        a, b = pm.alpha, pm.beta
        shift = 0.05 * torch.randn((), generator=gen, dtype=a.dtype)
        loop = 0.3 + 0.1 * torch.rand((), generator=gen, dtype=a.dtype)
        dens = torch.exp(
            -((a + b - 1.0 - shift) ** 2) / 0.15 - (a - b - loop) ** 2 / 0.02
        )
        pm.density = dens + 0.05
        with torch.no_grad():  # field = G_MAX * m (no separate linear term)
            pm.slope.zero_()
            pm.output_scale.fill_(G_MAX)
        magnets.append(HystereticMagnet(f"Q{j + 1}", pm, length=LENGTH))
    return magnets


class Machine:
    """Simulated beamline whose magnets remember their history."""

    def __init__(self, seed: int, n_particles: int, target: float) -> None:
        self.magnets = truth_magnets(seed)
        self.line = Beamline(
            [
                Quadrupole("Q1", length=LENGTH),
                Drift("D1", length=0.5),
                Quadrupole("Q2", length=LENGTH),
                Drift("D2", length=0.5),
                Quadrupole("Q3", length=LENGTH),
                Drift("D3", length=1.5),
            ]
        )
        gen = torch.Generator().manual_seed(2000 + seed)
        sig = torch.tensor([0.5e-3, 0.4e-3, 0.5e-3, 0.4e-3, 1e-4, 1e-4])
        self.particles = torch.randn(n_particles, 6, generator=gen) * sig
        self.states = [m.preisach.initial_states("negative") for m in self.magnets]
        self.target = target

    def apply(self, currents: torch.Tensor) -> float:
        """Set the currents (3,), update the magnets, return distance to target [mm]."""
        k1 = []
        for j, m in enumerate(self.magnets):
            u = currents[j].reshape(1).double()
            k1.append(m.k1(u, P0C, initial_state=self.states[j])[0])
            self.states[j] = m.final_state(u, initial_state=self.states[j])
        k1_t = torch.stack(k1).to(torch.float32).unsqueeze(0)
        out = self.line.track(
            self.particles, p0c=P0C, settings=k1_t, names=["Q1.k1", "Q2.k1", "Q3.k1"]
        )
        s = rms_sizes(out)[0]
        sx, sy = float(s[0].detach()) * 1e3, float(s[2].detach()) * 1e3
        return ((sx - self.target) ** 2 + (sy - self.target) ** 2) ** 0.5


def run(
    method: str, seed: int, steps: int, n_init: int, args: argparse.Namespace
) -> list[float]:
    """One optimisation; returns the true distance [mm] after every step."""
    machine = Machine(seed, args.particles, args.target)
    bounds = torch.tensor([[-I_MAX] * 3, [I_MAX] * 3], dtype=torch.float64)
    hyst = {}
    if method == "hgp_measured":
        hyst = {j: truth_magnets(seed)[j].preisach for j in range(3)}
    elif method == "hgp":
        hyst = {
            j: PreisachModel(
                PreisachMesh.triangular(n=args.mesh_n), input_range=(-I_MAX, I_MAX)
            )
            for j in range(3)
        }
    bo = HysteresisBO(
        bounds,
        hyst,
        acquisition="ucb",
        beta=2.0,
        maximize=True,
        fit_restarts=1,
        fit_max_iter=args.fit_iter,
        fit_density=method == "hgp" and not args.fixed_density,
        density_prior_scale=args.density_prior if args.density_prior > 0 else None,
        num_restarts=args.acq_restarts,
        raw_samples=args.raw_samples,
        seed=seed,
    )
    gen = torch.Generator().manual_seed(seed)
    noise_gen = torch.Generator().manual_seed(5000 + seed)
    init = (torch.rand(n_init, 3, generator=gen, dtype=torch.float64) * 2 - 1) * I_MAX
    dist = []
    for t in range(steps):
        x = init[t] if t < n_init else bo.ask()[0]
        d = machine.apply(x)
        dist.append(d)
        y = -d + args.noise * float(torch.randn((), generator=noise_gen))
        bo.tell(x.unsqueeze(0), torch.tensor([[y]], dtype=torch.float64))
    return dist


def headline(result: dict) -> dict[str, str]:
    """The docs page's figures: median final distances to the target [mm]."""
    gp, hgp = result["gp"]["median_final_best"], result["hgp"]["median_final_best"]
    runs = f"{result['seeds']} seeds x {result['steps']} steps"
    return {
        f"median final distance to target, H-GP vs plain GP ({runs})": (
            f"{hgp:.3f} mm vs {gp:.3f} mm"
        ),
        "with the true Preisach densities": (
            f"{result['hgp_measured']['median_final_best']:.3f} mm"
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
    parser.add_argument("--raw-samples", type=int, default=64)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument(
        "--fixed-density",
        action="store_true",
        help="keep the H-GP's prior (uniform) densities instead of refitting them",
    )
    parser.add_argument(
        "--density-prior",
        type=float,
        default=1.0,
        help="prior width of the refitted raw densities (0: no prior)",
    )
    add_store_flag(parser)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    warnings.filterwarnings("ignore", module="botorch|gpytorch|linear_operator")
    warnings.filterwarnings("ignore", message=".*not p.d.*")

    t_start = time.perf_counter()
    methods = ("gp", "hgp", "hgp_measured")
    curves: dict[str, list[list[float]]] = {m: [] for m in methods}
    times: dict[str, float] = {m: 0.0 for m in methods}
    for seed in range(args.seeds):
        for method in methods:
            t0 = time.perf_counter()
            dist = run(method, seed, args.steps, args.n_init, args)
            times[method] += time.perf_counter() - t0
            best = torch.tensor(dist).cummin(0).values.tolist()
            curves[method].append(best)
    total = time.perf_counter() - t_start

    def summary(method: str) -> dict[str, object]:
        c = torch.tensor(curves[method])
        final = c[:, -1]
        return {
            # interpolated median (mean of the middle two for an even count),
            # as in the figure
            "median_final_best": float(final.quantile(0.5)),
            "quartiles_final_best": [
                float(final.quantile(0.25)),
                float(final.quantile(0.75)),
            ],
            "final_best_per_seed": final.tolist(),
            "median_curve": c.quantile(0.5, dim=0).tolist(),
            "time_s": times[method],
        }

    res = {m: summary(m) for m in methods}
    args.out.mkdir(parents=True, exist_ok=True)
    fig = plot_best_so_far(
        {k: torch.tensor(v) for k, v in curves.items()},
        higher_is_better=False,
        ylabel="distance to target size [mm]",
        log_y=True,
    )
    png = args.out / "bo_hysteresis.png"
    atomic_write(png, lambda p: fig.savefig(p, format="png", dpi=120))
    result = {
        "name": "bo_hysteresis",
        "higher_is_better": False,
        "objective": "distance of (sigma_x, sigma_y) to (target, target) [mm]",
        "gp": res["gp"],
        "hgp": res["hgp"],
        "hgp_measured": res["hgp_measured"],
        "ratio_gp_over_hgp": res["gp"]["median_final_best"]
        / max(res["hgp"]["median_final_best"], 1e-12),
        "ratio_gp_over_hgp_measured": res["gp"]["median_final_best"]
        / max(res["hgp_measured"]["median_final_best"], 1e-12),
        "seeds": args.seeds,
        "steps": args.steps,
        "n_init": args.n_init,
        "target_mm": args.target,
        "noise_mm": args.noise,
        "particles": args.particles,
        "hgp_hysterons_per_magnet": args.mesh_n * (args.mesh_n + 1) // 2,
        "acquisition": "UCB beta=2",
        "hgp_density": (
            "uniform prior, fixed"
            if args.fixed_density
            else f"uniform prior, refitted each step (prior width {args.density_prior})"
        ),
        "hgp_measured_density": "each magnet's true density (as if measured on "
        "a test stand with fit_preisach), fixed",
        "total_time_s": total,
        "threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "git_commit": git_commit(),
        "figure": str(png),
    }
    emit(
        result,
        args.out / "bo_hysteresis.json",
        headline=headline,
        store_result=args.store,
    )


if __name__ == "__main__":
    main()
