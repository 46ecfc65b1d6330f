"""Bayesian optimisation of a hysteretic magnet with the hysteresis-aware GP.

The beam response (a transmission peaked at one field value) depends on the
*field* of a hysteretic quadrupole, not on its current: the same current gives
another field on the way up than on the way down. `HysteresisBO` models the
response through a Preisach model of the applied current history (the H-GP)
and is compared with a plain GP on currents (`hysteresis={}`), 8 steps each
after 4 starting points. On a problem this small both usually find the peak;
`benchmarks/bo_hysteresis.py` compares them over 10 seeds and 50 steps on three
hysteretic quadrupoles (see the benchmarks page).
"""

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import torch

from diffaccel.hysteresis import HysteresisBO, PreisachMesh, PreisachModel
from diffaccel.hysteresis.synthetic import synthetic_magnet

magnet = synthetic_magnet(i_max=10.0, n=20, hysteresis_fraction=0.2)  # the truth
target = 0.55  # normalised field of best transmission


def measure(currents: torch.Tensor, history: list[float]) -> torch.Tensor:
    """Apply the currents in order; return the transmission after each."""
    history.extend(currents[:, 0].tolist())
    with torch.no_grad():
        field = magnet(torch.tensor(history, dtype=torch.float64))
    b = (field - magnet.output_loc) / magnet.output_scale
    b = b[-len(currents) :]
    return torch.exp(-0.5 * ((b - target) / 0.1) ** 2)[:, None]


bounds = torch.tensor([[0.0], [10.0]], dtype=torch.float64)
start = torch.tensor([[1.0], [8.0], [3.0], [6.0]], dtype=torch.float64)
best = {}
guess = PreisachModel(PreisachMesh.triangular(n=12), input_range=(0.0, 10.0))
for label, hysteresis in (("H-GP", {0: guess}), ("plain GP", {})):
    history: list[float] = []
    bo = HysteresisBO(bounds, hysteresis, seed=0, fit_max_iter=30)
    bo.tell(start, measure(start, history))
    for _ in range(8):
        x = bo.ask()
        bo.tell(x, measure(x, history))
    ys = bo.Y[:, 0]
    x_best, y_best = bo.best
    best[label] = torch.cummax(ys, 0).values
    print(f"{label}: best transmission {float(y_best):.3f} at {float(x_best[0]):.2f} A")

fig, ax = plt.subplots(figsize=(5, 3))
for label, curve in best.items():
    ax.plot(curve.numpy(), label=label)
ax.set_xlabel("measurement")
ax.set_ylabel("best transmission so far")
ax.legend()
fig.tight_layout()
fig.savefig("best_so_far.png", dpi=80)
