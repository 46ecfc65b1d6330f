from __future__ import annotations

import pytest
import torch
from matplotlib.figure import Figure

from diffaccel.data import make_synthetic_quad_scan
from diffaccel.plotting import (
    plot_corner,
    plot_image_comparison,
    plot_rms_evolution,
    plot_training_curves,
)
from diffaccel.reconstruction import ReconstructionConfig, reconstruct


@pytest.fixture(scope="module")
def scan_and_result():
    ds = make_synthetic_quad_scan(
        "correlated", n_particles=1000, n_settings=4, screen_shape=(24, 24), seed=0
    )
    cfg = ReconstructionConfig(n_particles=512, steps=4, snapshots=2, dims=6)
    return ds, reconstruct(ds, cfg)


def test_corner_has_all_15_projections_in_6d(scan_and_result) -> None:
    ds, r = scan_and_result
    fig = plot_corner(r, ds.ground_truth, n=2000)
    assert isinstance(fig, Figure)
    visible = [a for a in fig.axes if a.axison]
    assert len(visible) == 15 + 6  # 15 pairs + 6 diagonal panels


def test_image_comparison_and_curves(scan_and_result, tmp_path) -> None:
    ds, r = scan_and_result
    pred = r.predict_images(ds.settings, n_particles=1000)
    fig = plot_image_comparison(
        ds.mean_images(), pred, ds.settings, held_out=[False, True, False, True]
    )
    assert len([a for a in fig.axes if a.images]) == 3 * 4
    for f in (fig, plot_training_curves(r), plot_rms_evolution(r, ds.ground_truth)):
        f.savefig(tmp_path / "x.png")
    with pytest.raises(ValueError, match="differ"):
        plot_image_comparison(ds.mean_images(), pred[:2], ds.settings)
    assert torch.isfinite(pred).all()


def test_image_comparison_shows_the_predicted_spread(scan_and_result, tmp_path) -> None:
    ds, r = scan_and_result
    pred, std = r.predict_images(
        ds.settings, n_particles=1000, return_std=True, n_draws=2
    )
    fig = plot_image_comparison(ds.mean_images(), pred, ds.settings, predicted_std=std)
    assert len([a for a in fig.axes if a.images]) == 4 * 4  # a fourth row
    fig.savefig(tmp_path / "x.png")
    with pytest.raises(ValueError, match="predicted_std"):
        plot_image_comparison(
            ds.mean_images(), pred, ds.settings, predicted_std=std[:2]
        )
