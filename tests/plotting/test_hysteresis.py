"""Figures of Preisach models."""

from __future__ import annotations

import pytest
import torch
from matplotlib.figure import Figure

from diffaccel.hysteresis import PreisachMesh, PreisachModel
from diffaccel.hysteresis.synthetic import synthetic_magnet, synthetic_measurement
from diffaccel.plotting.hysteresis import plot_preisach_density, plot_preisach_fit


@pytest.mark.parametrize(
    "mesh",
    [PreisachMesh.triangular(8), PreisachMesh.from_points([0.5, 0.9], [0.1, 0.2])],
    ids=["triangular", "two-user-points"],
)
def test_density_figure(mesh: PreisachMesh) -> None:
    model = PreisachModel(mesh, input_range=(0.0, 165.0))
    fig = plot_preisach_density(model)
    assert isinstance(fig, Figure)
    ax = fig.axes[0]
    # axes in physical input units
    assert ax.get_xlim() == (0.0, 165.0) and ax.get_ylim() == (0.0, 165.0)


def test_fit_figure_reports_split_rms() -> None:
    current, field, _ = synthetic_measurement(noise=0.0)
    magnet = synthetic_magnet()  # the true model: residuals are round-off only
    fig = plot_preisach_fit(magnet, current, field, n_train=21)
    loop, res = fig.axes[:2]
    assert "fit 0.000 %" in res.get_title() and "prediction 0.000 %" in res.get_title()
    assert len(loop.get_legend().get_texts()) == 4


def test_fit_figure_rejects_mismatched_series() -> None:
    magnet = synthetic_magnet()
    with pytest.raises(ValueError, match="shape"):
        plot_preisach_fit(magnet, torch.zeros(5), torch.zeros(4))
