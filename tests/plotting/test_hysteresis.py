"""Figures of Preisach models."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from matplotlib.figure import Figure

from diffaccel.hysteresis import PreisachMesh, PreisachModel
from diffaccel.hysteresis.synthetic import synthetic_magnet, synthetic_measurement
from diffaccel.plotting.hysteresis import (
    FIT_FIGURES,
    plot_preisach_density,
    plot_preisach_fit,
    write_fit_figures,
)


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


def test_symmetric_density_figure_draws_mirror_line() -> None:
    model = PreisachModel(
        PreisachMesh.triangular(8), input_range=(-6.0, 6.0), symmetric=True
    )
    ax = plot_preisach_density(model).axes[0]
    assert "symmetric" in ax.get_title()
    # the diagonal and the mirror line alpha + beta = lo + hi
    ends = {tuple(np.round(line.get_xydata()[[0, -1]].ravel(), 9)) for line in ax.lines}
    assert (-6.0, 6.0, 6.0, -6.0) in ends


def test_fit_figure_draws_band() -> None:
    current, field, _ = synthetic_measurement(noise=0.0)
    magnet = synthetic_magnet()
    std = torch.full_like(current, 0.01)
    fig = plot_preisach_fit(magnet, current, field, n_train=21, std=std)
    loop, res = fig.axes[:2]
    assert "model +- 2 std" in [t.get_text() for t in loop.get_legend().get_texts()]
    assert len(res.collections) == 1  # the residual band
    with pytest.raises(ValueError, match="std must have shape"):
        plot_preisach_fit(magnet, current, field, std=std[:-1])


def test_write_fit_figures_writes_both_pngs(tmp_path) -> None:
    current, field, _ = synthetic_measurement(noise=0.0)
    magnet = synthetic_magnet()
    std = torch.full_like(field, 1e-3)
    names = write_fit_figures(
        tmp_path, magnet, current, field, 21, std, "current_A", "field_Tm"
    )
    assert names == list(FIT_FIGURES) == ["fit.png", "density.png"]
    for name in names:
        assert (tmp_path / name).read_bytes()[:4] == b"\x89PNG"
