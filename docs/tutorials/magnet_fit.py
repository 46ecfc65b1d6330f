"""Fit a Preisach model to a magnet's field measurements and predict its field.

A synthetic magnet with a known Preisach density is measured along a protocol
like the SLAC LCLS-II quadrupole measurements: a major loop, minor loops and an
alternating "memory trial". The first 62 rows train `fit_magnet` (a Preisach fit
plus a calibrated predictive band); the model then predicts the remaining rows
from the state the training history left, with a 1-sigma band.
"""

import matplotlib

matplotlib.use("Agg")

import torch

from diffaccel.hysteresis import fit_magnet
from diffaccel.hysteresis.synthetic import synthetic_measurement
from diffaccel.plotting.hysteresis import plot_preisach_density, plot_preisach_fit

current, field, truth = synthetic_measurement(noise=1e-4, seed=0)  # [A], [T m]
n_train = 62
fit = fit_magnet(current[:n_train], field[:n_train])
print(f"fit in {fit.seconds:.1f} s, symmetric density: {fit.symmetric}")

with torch.no_grad():
    predicted = fit.model(current)
    std = fit.band.std(fit.model, current)
span = float(field.max() - field.min())
test = slice(n_train, None)
rms = float((predicted[test] - field[test]).pow(2).mean().sqrt())
inside = float(((predicted[test] - field[test]).abs() < 2 * std[test]).double().mean())
print(f"held-out rms error: {100 * rms / span:.3f} % of the field range")
print(f"held-out rows inside 2 std: {100 * inside:.0f} %")

plot_preisach_fit(fit.model, current, field, n_train=n_train, std=std).savefig(
    "fit.png", dpi=80
)
plot_preisach_density(fit.model).savefig("density.png", dpi=80)
