"""Soft-iron B-H loops: an adaptive mesh, odd symmetry and a band that never aborts.

The loops come from ``hysteresis.synthetic.soft_iron_loop``: tanh/atan/erf
branches with the coercive field a small fraction of the range, not made by a
Preisach model. H in A/m up to 1e5, B in tesla, no manual scaling.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from diffaccel.cli.main import main
from diffaccel.data import write_csv_atomic
from diffaccel.hysteresis import (
    BandFallbackWarning,
    InputRangeWarning,
    PreisachMesh,
    PreisachModel,
    adaptive_warp,
    changes_sign,
    fit_magnet,
    laplace_band,
    load_fit,
    save_fit,
)
from diffaccel.hysteresis import band as band_module
from diffaccel.hysteresis.mesh import unwarp_input, warp_input
from diffaccel.hysteresis.synthetic import MU0, soft_iron_loop


def _predict(fit, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputRangeWarning)
        with torch.no_grad():
            return fit.model(h), fit.band.std(fit.model, h)


def test_descending_branch_from_the_ascending_one() -> None:
    # coercive field 200 A/m: 1e-3 of the range -1e5 .. 1e5 A/m
    h, b, n = soft_iron_loop(coercive=1e-3, seed=1)
    assert float(h[1]) < 20.0 and float(h.max()) == pytest.approx(1e5)
    fit = fit_magnet(h[:n], b[:n], mesh_adapt=0.8)  # what "auto" picks here
    assert fit.symmetric and fit.model.odd  # H and B change sign
    assert fit.model.input_range == pytest.approx((-1.01e5, 1.01e5))
    pred, std = _predict(fit, h)
    span = float(b[:n].max() - b[:n].min())
    desc = slice(n, n + 2 * (n - 1))  # the descending branch h_max -> -h_max
    err = (pred[desc] - b[desc]) / span
    assert float(err.pow(2).mean().sqrt()) < 0.02
    # the regular mesh puts the switching region into one cell: far worse
    plain = fit_magnet(h[:n], b[:n], mesh_adapt=0.0, steps=100)
    plain_err = (_predict(plain, h)[0][desc] - b[desc]) / span
    assert float(plain_err.pow(2).mean().sqrt()) > 3 * float(err.pow(2).mean().sqrt())
    # saturation stays exact: beyond the range every hysteron is switched and
    # the output is the linear term alone, with a reversible slope near mu0
    far = torch.tensor([2e5, 3e5, 4e5], dtype=torch.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputRangeWarning)
        with torch.no_grad():
            y = fit.model.predict(far, history=h[:n])
    model = fit.model
    lo, hi = model.input_range
    slope = float((model.slope * model.output_scale).detach()) / (hi - lo)
    assert float(y[1] - y[0]) == pytest.approx(1e5 * slope, rel=1e-9)
    assert float(y[2] - y[1]) == pytest.approx(1e5 * slope, rel=1e-9)
    assert slope == pytest.approx(MU0, rel=0.5)
    assert (std > 0).all()


@pytest.mark.slow
def test_default_fit_chooses_the_adaptive_mesh_for_soft_iron() -> None:
    h, b, n = soft_iron_loop(coercive=1e-3, seed=1)
    fit = fit_magnet(h[:n], b[:n])
    assert fit.mesh_adapt > 0
    assert [r["mesh_adapt"] for r in fit.mesh_validation] == [0.0, 0.8, 0.95]
    span = float(b[:n].max() - b[:n].min())
    err = (_predict(fit, h)[0][n:] - b[n:]) / span
    assert float(err.pow(2).mean().sqrt()) < 0.02


def test_changes_sign_default() -> None:
    h, b, n = soft_iron_loop(points=20)
    assert changes_sign(h[:n], b[:n])  # H starts at 0 (remanence), B < 0 there
    current = torch.linspace(0.0, 165.0, 12, dtype=torch.float64)
    assert not changes_sign(current, 0.03 * current + 0.03)  # unipolar magnet
    assert changes_sign(current - 80.0, 0.03 * (current - 80.0))


def test_adaptive_warp_places_thresholds_where_the_output_switches() -> None:
    h, b, n = soft_iron_loop(coercive=1e-3, points=40)
    lo, hi = -1.01e5, 1.01e5
    un = (h[:n] - lo) / (hi - lo)
    warp = adaptive_warp(un, b[:n], 0.8, symmetric=True)
    mesh = PreisachMesh.triangular(20, warp=warp)
    assert float(mesh.area.sum()) == pytest.approx(0.5)
    mesh.mirror_index()  # mirror symmetric: a symmetric density works
    hc = (200.0 - lo) / (hi - lo)  # the coercive field, normalised
    levels = torch.unique(mesh.alpha)
    near = ((levels - hc).abs() < 1e-3).sum()  # within +-200 A/m of +Hc
    assert int(near) >= 6  # a regular 20-cell mesh has none there
    t = torch.linspace(0.0, 1.0, 11, dtype=torch.float64)
    assert torch.allclose(warp_input(unwarp_input(t, warp), warp), t, atol=1e-12)


def test_band_falls_back_instead_of_aborting(monkeypatch, tmp_path: Path) -> None:
    h, b, n = soft_iron_loop(points=24)
    # no density prior is positive definite: every length scale fails
    monkeypatch.setattr(
        band_module,
        "_prior_covariance",
        lambda model, length, dtype: torch.full(
            (model.alpha.numel(),) * 2, float("nan"), dtype=dtype
        ),
    )
    with pytest.warns(BandFallbackWarning, match="coarser band") as record:
        fit = fit_magnet(h[:n], b[:n], mesh_adapt=0.8, steps=60)
    assert len([w for w in record if w.category is BandFallbackWarning]) == 1
    assert "coarser band" in fit.band_fallback
    _, std = _predict(fit, h)
    assert torch.isfinite(std).all() and (std > 0).all()
    # the CLI: one warning line, the fallback in summary.json, files written
    rows = [[i, float(x), float(y)] for i, (x, y) in enumerate(zip(h, b, strict=True))]
    data = tmp_path / "bh.csv"
    write_csv_atomic(data, ["time_s", "H_A_per_m", "B_T"], rows)
    out = tmp_path / "fit"
    args = ["hysteresis", "fit", str(data), "--train-rows", str(n), "--input"]
    args += ["H_A_per_m", "--output", "B_T", "--out", str(out), "--no-figures"]
    args += ["--steps", "40", "--mesh-adapt", "0.8"]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    lines = [s for s in result.output.splitlines() if s.startswith("warning:")]
    assert len(lines) == 1 and "coarser band" in lines[0]
    summary = json.loads((out / "summary.json").read_text())
    assert "coarser band" in summary["band_fallback"]
    assert summary["test_inside_2std"] is not None
    assert (out / "model.pt").is_file() and (out / "stream.npz").is_file()


def test_jitter_ladder_is_reported() -> None:
    h, b, n = soft_iron_loop(points=16)
    fit = fit_magnet(h[:n], b[:n], mesh_adapt=0.0, steps=30)
    with warnings.catch_warnings():
        warnings.simplefilter("error", BandFallbackWarning)
        band = laplace_band(fit.model, h[:n], b[:n])  # plain band: no warning
    assert band.fallback is None


def test_saved_fit_with_a_warp_round_trips(tmp_path: Path) -> None:
    h, b, n = soft_iron_loop(points=24)
    fit = fit_magnet(h[:n], b[:n], mesh_adapt=0.8, steps=40)
    save_fit(tmp_path / "fit", fit.model, fit.band)
    model, band, config = load_fit(tmp_path / "fit")
    assert band is not None
    assert config["odd"] is True and config["mesh_warp"] is not None
    assert model.mesh_warp == fit.model.mesh_warp
    with torch.no_grad():
        assert torch.allclose(model(h), fit.model(h), rtol=0, atol=1e-12)


def test_config_without_warp_or_odd_loads() -> None:
    model = PreisachModel(PreisachMesh.triangular(6), input_range=(0.0, 10.0))
    config = model.config()
    del config["mesh_warp"], config["odd"]  # as written before these settings
    again = PreisachModel.from_config(config, model.state_dict())
    assert again.mesh_warp is None and again.odd is False


def test_odd_needs_a_symmetric_centred_model() -> None:
    with pytest.raises(ValueError, match="odd=True needs"):
        PreisachModel(PreisachMesh.triangular(6), input_range=(0.0, 1.0), odd=True)


def test_five_decades_of_field_in_si_units() -> None:
    # H from 0.18 A/m to 1e5 A/m (5.2 orders of magnitude), B in tesla
    h, b, n = soft_iron_loop(points=60, spacing=11.0, seed=2)
    pos = h[h > 0]
    assert float(torch.log10(pos.max() / pos.min())) > 5.0
    fit = fit_magnet(h[:n], b[:n], mesh_adapt=0.8, steps=100)
    pred, std = _predict(fit, h)
    assert torch.isfinite(pred).all() and torch.isfinite(std).all()
    span = float(b[:n].max() - b[:n].min())
    err = (pred[n:] - b[n:]) / span
    assert float(err.pow(2).mean().sqrt()) < 0.06
    # negative saturation, never seen in training: -B(+h_max) by symmetry
    i_neg = int(torch.argmin(h))
    assert float(pred[i_neg]) == pytest.approx(-float(b[n - 1]), abs=0.01 * span)


@pytest.mark.parametrize("value", ["1", "-0.1", "abc"])
def test_cli_refuses_a_bad_mesh_adapt(tmp_path: Path, value: str) -> None:
    h, b, n = soft_iron_loop(points=8)
    rows = [[i, float(x), float(y)] for i, (x, y) in enumerate(zip(h, b, strict=True))]
    data = tmp_path / "bh.csv"
    write_csv_atomic(data, ["time_s", "H", "B"], rows)
    args = ["hysteresis", "fit", str(data), "--train-rows", str(n), "--input", "H"]
    args += ["--output", "B", "--out", str(tmp_path / "f"), "--mesh-adapt", value]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 2 and "--mesh-adapt" in result.output
    assert not (tmp_path / "f").exists()


def test_odd_output_can_be_switched_off() -> None:
    h, b, n = soft_iron_loop(points=16)
    fit = fit_magnet(h[:n], b[:n] + 0.05, mesh_adapt=0.0, steps=40, odd=False)
    assert fit.symmetric and not fit.model.odd
    with pytest.raises(ValueError, match="odd=True needs"):
        fit_magnet(h[:n], b[:n], symmetric=False, odd=True)
