"""Model and optimise a beam response through a hysteretic magnet with the H-GP.

The beam transmission depends on the *magnetisation* of a hysteretic quadrupole,
not on its current: the same current gives another field on the way up than on
the way down. A plain GP on currents can only call that difference noise. The
hysteresis GP (`HysteresisGP`) models the response through a Preisach model of the
applied current history. Part 1 fits both to three measured current cycles and
compares their fitted noise with the true one. Part 2 runs a short ask/tell
Bayesian optimisation (`HysteresisBO`) with the H-GP. `benchmarks/hgp_vs_gp.py` and
`benchmarks/bo_hysteresis.py` measure both at full size (see the benchmarks page).
"""

import warnings

import matplotlib

matplotlib.use("Agg")

import torch

from diffaccel.hysteresis import (
    HysteresisBO,
    HysteresisGP,
    PreisachMesh,
    PreisachModel,
    fit_hysteresis_gp,
)
from diffaccel.plotting.hgp import plot_gp_vs_hgp

warnings.filterwarnings("ignore", module="botorch|gpytorch|linear_operator")
I_MAX, NOISE = 10.0, 0.01  # current range [A], measurement noise [1]

# the truth: a Preisach magnet with wide loops, a transmission peaked in its field
magnet = PreisachModel(PreisachMesh.triangular(n=40), input_range=(0.0, I_MAX))
a, b = magnet.alpha, magnet.beta
magnet.density = (
    torch.exp(-((a + b - 1) ** 2) / 0.08 - (a - b - 0.35) ** 2 / 0.04) + 0.02
)


def measure(history: torch.Tensor) -> torch.Tensor:
    """Transmission after each current of the history, with noise, ``(n, 1)``."""
    with torch.no_grad():
        m = magnet.magnetization(history)
    f = 0.15 + 0.8 * torch.exp(-((m - 0.25) ** 2) / (2 * 0.35**2))
    return (f + NOISE * torch.randn(f.shape, dtype=f.dtype))[:, None]


# Part 1: three cycles 0 -> I_MAX -> 0, 12 points each
torch.manual_seed(0)
up = torch.linspace(0.0, I_MAX, 7, dtype=torch.float64)[:-1]
cycles = torch.cat([up, up.flip(0) + up[1]] * 3)
X, Y = cycles[:, None], measure(cycles)
bounds = torch.tensor([[0.0], [I_MAX]], dtype=torch.float64)
guess = PreisachModel(PreisachMesh.triangular(n=12), input_range=(0.0, I_MAX))
models = {}
for label, hysteresis in (("plain GP", {}), ("H-GP", {0: guess})):
    model = HysteresisGP(X, Y, hysteresis=hysteresis, bounds=bounds)
    fit_hysteresis_gp(model, restarts=1, seed=0)
    models[label] = model
    print(f"{label}: fitted noise {float(model.noise_sigma):.4f} (true {NOISE})")

with torch.no_grad():
    gp = models["plain GP"].posterior(X)
    hgp = models["H-GP"].posterior_on_history()
fig = plot_gp_vs_hgp(
    cycles,
    Y[:, 0],
    gp.mean[:, 0],
    gp.variance.sqrt()[:, 0],
    hgp.mean[:, 0],
    hgp.variance.sqrt()[:, 0],
    torch.arange(len(cycles)) // 12,
    ylabel="transmission",
)
fig.savefig("gp_vs_hgp.png", dpi=80)

# Part 2: maximise the transmission, 6 H-GP steps after the 4 first settings
history = [1.0, 8.0, 3.0, 6.0]
bo = HysteresisBO(bounds, {0: guess}, seed=0, fit_max_iter=30)
bo.tell(
    torch.tensor(history, dtype=torch.float64)[:, None],
    measure(torch.tensor(history, dtype=torch.float64)),
)
for _ in range(6):
    x = bo.ask()  # judged from the magnetic state the history leaves
    history.append(float(x))
    y = measure(torch.tensor(history, dtype=torch.float64))[-1:]
    bo.tell(x, y)
x_best, y_best = bo.best
print(
    f"BO: best transmission {float(y_best):.3f} at {float(x_best[0]):.2f} A (peak 0.95)"
)
