from __future__ import annotations

import pytest
import torch
from matplotlib.figure import Figure

from diffaccel.data import MultiScanDataset, make_synthetic_quad_scan
from diffaccel.plotting import (
    plot_corner,
    plot_image_comparison,
    plot_rms_evolution,
    plot_training_curves,
)
from diffaccel.plotting.reconstruction import (
    image_figures,
    result_figures,
    write_image_figures,
    write_result_figures,
)
from diffaccel.reconstruction import ReconstructionConfig, as_scans, reconstruct


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
    assert sum(len(a.images) for a in fig.axes) == 3 * 4  # one image per panel
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
    assert sum(len(a.images) for a in fig.axes) == 4 * 4  # a fourth row
    fig.savefig(tmp_path / "x.png")
    with pytest.raises(ValueError, match="predicted_std"):
        plot_image_comparison(
            ds.mean_images(), pred, ds.settings, predicted_std=std[:2]
        )


def test_image_comparison_panels_keep_their_scales_and_blocks(tmp_path) -> None:
    g = torch.Generator().manual_seed(0)
    meas = torch.rand(4, 6, 8, generator=g) * torch.arange(1.0, 5.0)[:, None, None]
    pred = meas.flip(-1)
    fig = plot_image_comparison(
        meas, pred, torch.arange(4.0)[:, None], held_out=[0, 1, 0, 0], max_columns=3
    )
    ims = [im for a in fig.axes for im in a.images]
    assert len(ims) == 3 * 4  # two blocks of 3 columns, 4 settings
    # measured and predicted panels of a setting share its own colour scale
    vmax = [max(float(meas[i].max()), float(pred[i].max())) for i in range(4)]
    tops = sorted({im.get_clim() for im in ims if im.get_cmap().name == "viridis"})
    assert tops == sorted((0.0, v) for v in vmax)
    titles = {t.get_text(): t.get_color() for a in fig.axes for t in a.texts}
    assert titles["1 (test)"] == "C3" and titles["2"] == "k"
    fig.savefig(tmp_path / "x.png")


def test_result_figures_are_the_three_summary_figures(scan_and_result) -> None:
    ds, r = scan_and_result
    names = [name for name, fig in result_figures(r, ds)]
    assert names == ["phase_space.png", "training.png", "rms_evolution.png"]


def test_image_figures_name_and_mark_each_scan(scan_and_result, tmp_path) -> None:
    ds, r = scan_and_result
    scans = as_scans(ds)
    (name,) = scans.names
    pred = {name: r.predict_images(ds.settings, n_particles=500)}
    calls = []

    def spy(*args, **kw):
        calls.append(kw)
        return plot_image_comparison(*args, **kw)

    written = write_image_figures(scans, {name: [0, 2]}, tmp_path, pred, plot=spy)
    assert written == ["images.png"]  # one scan: no scan name in the file
    assert calls[0]["held_out"] == [False, True, False, True]
    assert calls[0]["title"] == "" and calls[0]["predicted_std"] is None
    assert (tmp_path / "images.png").stat().st_size > 0
    two = MultiScanDataset({"a": scans[name], "b": scans[name]})
    both = {"a": pred[name], "b": pred[name]}
    figs = dict(image_figures(two, {"a": [0]}, both, both))
    assert list(figs) == ["images_a.png", "images_b.png"]
    # b is not trained on: every setting held out; the spread adds a fourth row
    assert sum(len(a.images) for a in figs["images_b.png"].axes) == 4 * 4


def test_write_result_figures_writes_the_files(scan_and_result, tmp_path) -> None:
    ds, r = scan_and_result
    names = write_result_figures(r, as_scans(ds), tmp_path)
    assert sorted(names) == sorted(p.name for p in tmp_path.iterdir())
    assert len(names) == 3
