"""Plain GP versus joint hysteresis GP on a synthetic, cycled hysteretic magnet.

Truth: a quadrupole whose normalised magnetisation follows a known Preisach
model (fine mesh, density concentrated off the diagonal: wide loops); the beam
transmission is a smooth function of that magnetisation, measured with known
Gaussian noise. Training data: 3 full current cycles (0 -> I_max -> 0). Held out
(predicted by the H-GP as one multi-step sequence from the state left by the
training history, by the plain GP from current): a 4th full cycle
(``heldout_*``), then a cycle with minor loops never seen in training
(``minor_loop_*``: the density inside the major loop is not identified by
major-loop data, so this is the hard, honest case).

Prints one JSON object on the last line; writes ``hgp_vs_gp.png`` and
``hgp_vs_gp.json`` into ``--out``.
"""

from __future__ import annotations

import argparse
import math
import platform
import time
import warnings
from pathlib import Path

import torch
from _meta import add_store_flag, emit, git_commit
from botorch.fit import fit_gpytorch_mll
from botorch.models import SingleTaskGP
from botorch.models.transforms.input import Normalize
from gpytorch.mlls import ExactMarginalLogLikelihood

from diffaccel.data import atomic_write
from diffaccel.hysteresis import (
    HysteresisGP,
    PreisachMesh,
    PreisachModel,
    fit_hysteresis_gp,
)
from diffaccel.plotting.hgp import plot_gp_vs_hgp

I_MAX = 10.0  # [A]


def truth_magnet() -> PreisachModel:
    """Known hysteretic magnet: fine mesh, density bump off the diagonal."""
    model = PreisachModel(PreisachMesh.triangular(n=60), input_range=(0.0, I_MAX))
    a, b = model.alpha, model.beta
    centre, width = (a + b - 1.0), (a - b - 0.35)
    model.density = torch.exp(-(centre**2) / 0.08 - width**2 / 0.04) + 0.02
    return model


def transmission(m: torch.Tensor) -> torch.Tensor:
    """Beam transmission [1] versus normalised magnetisation (smooth, peaked)."""
    return 0.15 + 0.8 * torch.exp(-((m - 0.25) ** 2) / (2 * 0.35**2))


def histories(n_per_cycle: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Three full cycles (training), a 4th full cycle and a minor-loop cycle."""
    half = n_per_cycle // 2
    up = torch.linspace(0.0, I_MAX, half + 1, dtype=torch.float64)[:-1]
    down = torch.linspace(I_MAX, 0.0, half + 1, dtype=torch.float64)[:-1]
    train = torch.cat([up, down] * 3)
    fourth = torch.cat([up, down])
    q = n_per_cycle // 4
    held = torch.cat(
        [
            torch.linspace(0.0, 0.7 * I_MAX, q + 1, dtype=torch.float64)[1:],
            torch.linspace(0.7 * I_MAX, 0.3 * I_MAX, q + 1, dtype=torch.float64)[1:],
            torch.linspace(0.3 * I_MAX, I_MAX, q + 1, dtype=torch.float64)[1:],
            torch.linspace(I_MAX, 0.0, q + 1, dtype=torch.float64)[1:],
        ]
    )
    return train, fourth, held


def nlpd(y: torch.Tensor, mean: torch.Tensor, var: torch.Tensor) -> float:
    """Mean negative log predictive density of observations [nats]."""
    return float(
        (0.5 * torch.log(2 * math.pi * var) + 0.5 * (y - mean) ** 2 / var).mean()
    )


def _heldout(
    mean: torch.Tensor,
    var: torch.Tensor,
    f: torch.Tensor,
    y: torch.Tensor,
    n4: int,
) -> dict[str, float]:
    """Held-out metrics: 4th full cycle (first n4 points) and minor-loop cycle."""
    out = {}
    for key, sl in (("heldout", slice(0, n4)), ("minor_loop", slice(n4, None))):
        out[f"{key}_rmse"] = float((mean[sl] - f[sl]).pow(2).mean().sqrt())
        out[f"{key}_nlpd"] = nlpd(y[sl], mean[sl], var[sl])
    return out


def headline(result: dict) -> dict[str, str]:
    """The docs page's figures: fitted noise, held-out rmse and sigma ratios."""
    r, gp, hgp = result["ratios"], result["gp"], result["hgp"]
    return {
        "fitted noise / true noise, H-GP vs plain GP": (
            f"{r['hgp_noise_over_true']:.2g}x vs {r['gp_noise_over_true']:.2g}x"
        ),
        "held-out rmse, H-GP / plain GP": (
            f"{hgp['heldout_rmse'] / gp['heldout_rmse']:.2g}x"
        ),
        "mean predictive sigma, H-GP / plain GP": f"{r['sigma_hgp_over_gp']:.2g}x",
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, default=Path("out") / "benchmarks")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--noise", type=float, default=0.02)
    parser.add_argument("--n-per-cycle", type=int, default=40)
    parser.add_argument("--mesh-n", type=int, default=44, help="H-GP mesh (990)")
    parser.add_argument("--restarts", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=3, help="timing repeats")
    parser.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch threads (1 is fastest for ~100-point GPs on a busy 2-core CPU)",
    )
    add_store_flag(parser)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    warnings.filterwarnings("ignore", module="botorch|gpytorch|linear_operator")
    gen = torch.Generator().manual_seed(args.seed)

    truth = truth_magnet()
    u_train, u_fourth, u_minor = histories(args.n_per_cycle)
    u_held = torch.cat([u_fourth, u_minor])
    n4 = u_fourth.numel()
    with torch.no_grad():
        m_all = truth.magnetization(torch.cat([u_train, u_held]))
    f_all = transmission(m_all)
    y_all = f_all + args.noise * torch.randn(
        f_all.shape, generator=gen, dtype=f_all.dtype
    )
    n = u_train.numel()
    X, Y = u_train.unsqueeze(-1), y_all[:n].unsqueeze(-1)
    f_train, f_held, y_held = f_all[:n], f_all[n:], y_all[n:]
    bounds = torch.tensor([[0.0], [I_MAX]], dtype=torch.float64)

    # plain GP on current
    gp_times = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        gp = SingleTaskGP(X, Y, input_transform=Normalize(d=1, bounds=bounds))
        fit_gpytorch_mll(ExactMarginalLogLikelihood(gp.likelihood, gp))
        gp_times.append(time.perf_counter() - t0)
    with torch.no_grad():
        p_tr = gp.posterior(X)
        p_he = gp.posterior(u_held.unsqueeze(-1), observation_noise=True)
    gp_noise = float(
        (gp.likelihood.noise.sqrt() * gp.outcome_transform.stdvs).squeeze().detach()
    )
    gp_res = {
        "noise_sigma": gp_noise,
        "mean_predictive_sigma": float(p_tr.variance.sqrt().mean()),
        "rmse": float((p_tr.mean.squeeze(-1) - f_train).pow(2).mean().sqrt()),
        **_heldout(p_he.mean.view(-1), p_he.variance.view(-1), f_held, y_held, n4),
        "fit_s": sorted(gp_times)[len(gp_times) // 2],
        "fit_s_all": gp_times,
    }

    # joint H-GP on the Preisach state
    hgp_times, fit = [], None
    for _ in range(args.repeats):
        prior = PreisachModel(
            PreisachMesh.triangular(n=args.mesh_n), input_range=(0.0, I_MAX)
        )
        t0 = time.perf_counter()
        hgp = HysteresisGP(X, Y, hysteresis={0: prior}, bounds=bounds)
        fit = fit_hysteresis_gp(hgp, restarts=args.restarts, seed=args.seed)
        hgp_times.append(time.perf_counter() - t0)
    assert fit is not None
    with torch.no_grad():
        h_tr = hgp.posterior_on_history()
        h_he = hgp.posterior_sequence(u_held.view(-1, 1), observation_noise=True)
    hgp_res = {
        "noise_sigma": float(hgp.noise_sigma.detach()),
        "mean_predictive_sigma": float(h_tr.variance.sqrt().mean()),
        "rmse": float((h_tr.mean.squeeze(-1) - f_train).pow(2).mean().sqrt()),
        **_heldout(h_he.mean.view(-1), h_he.variance.view(-1), f_held, y_held, n4),
        "fit_s": sorted(hgp_times)[len(hgp_times) // 2],
        "fit_s_all": hgp_times,
        "n_hysterons": len(prior.alpha),
        "restarts": args.restarts,
        "restart_mlls": list(fit.restart_mlls),
    }

    args.out.mkdir(parents=True, exist_ok=True)
    cycle = torch.arange(n) // args.n_per_cycle
    fig = plot_gp_vs_hgp(
        u_train,
        Y.squeeze(-1),
        p_tr.mean.squeeze(-1),
        p_tr.variance.sqrt().squeeze(-1),
        h_tr.mean.squeeze(-1),
        h_tr.variance.sqrt().squeeze(-1),
        cycle,
        ylabel="transmission",
    )
    png = args.out / "hgp_vs_gp.png"
    atomic_write(png, lambda p: fig.savefig(p, format="png", dpi=120))

    result = {
        "name": "hgp_vs_gp",
        "true_noise_sigma": args.noise,
        "gp": gp_res,
        "hgp": hgp_res,
        "ratios": {
            "hgp_noise_over_true": hgp_res["noise_sigma"] / args.noise,
            "gp_noise_over_true": gp_res["noise_sigma"] / args.noise,
            "rmse_hgp_over_gp": hgp_res["rmse"] / gp_res["rmse"],
            "sigma_hgp_over_gp": hgp_res["mean_predictive_sigma"]
            / gp_res["mean_predictive_sigma"],
        },
        "n_train": n,
        "n_heldout": n4,
        "n_minor_loop": u_minor.numel(),
        "dtype": "float64",
        "device": "cpu",
        "threads": torch.get_num_threads(),
        "cpu": platform.processor() or platform.machine(),
        "torch": torch.__version__,
        "git_commit": git_commit(),
        "figure": str(png),
    }
    emit(
        result, args.out / "hgp_vs_gp.json", headline=headline, store_result=args.store
    )


if __name__ == "__main__":
    main()
