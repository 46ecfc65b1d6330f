"""fit_preisach on synthetic and measured magnet histories."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from diffaccel.data import read_magnet_csv
from diffaccel.hysteresis import (
    FitResult,
    PreisachMesh,
    PreisachModel,
    fit_magnet,
    fit_preisach,
)
from diffaccel.hysteresis.fit import density_roughness
from diffaccel.hysteresis.synthetic import synthetic_measurement

F64 = torch.float64
SLAC = (
    Path(__file__).resolve().parents[2]
    / "data"
    / "hysteresis"
    / "slac_lcls2_quad_4194"
    / "measurements.csv"
)


def _rms_percent(pred: torch.Tensor, y: torch.Tensor, span: float) -> float:
    return 100.0 * float((pred - y).pow(2).mean().sqrt()) / span


@pytest.mark.parametrize("optimizer", ["lbfgs", "adam"], ids=["lbfgs", "adam"])
def test_fit_synthetic_generalises(optimizer: str) -> None:
    current, field, _ = synthetic_measurement(noise=1e-4, seed=0)
    span = float(field.max() - field.min())
    model = PreisachModel(PreisachMesh.triangular(20), input_range=(0.0, 10.0))
    steps = 50
    lr = 0.05 if optimizer == "adam" else None
    res = fit_preisach(
        model, current[:21], field[:21], optimizer=optimizer, steps=steps, lr=lr
    )
    assert isinstance(res, FitResult) and res.steps >= 1
    with torch.no_grad():
        pred = model(current)
    # a straight line misses the loop by 0.28 % of range on this magnet; the
    # Preisach fit on the major loop alone must predict minor loops and the
    # memory trial well below that (the spec's bar is 3 %). Adam converges
    # more slowly in the 50 steps a test may take.
    bar = 0.15 if optimizer == "lbfgs" else 0.2
    assert _rms_percent(pred[21:], field[21:], span) < bar
    assert res.rmse_percent < bar


def test_fit_beats_straight_line_on_minor_loops() -> None:
    current, field, _ = synthetic_measurement(noise=0.0)
    span = float(field.max() - field.min())
    basis = torch.stack([torch.ones_like(current), current], dim=1)
    coef = torch.linalg.lstsq(basis[:21], field[:21, None]).solution
    line = (basis @ coef).squeeze(1)
    model = PreisachModel(PreisachMesh.triangular(20), input_range=(0.0, 10.0))
    fit_preisach(model, current[:21], field[:21], steps=50)
    with torch.no_grad():
        pred = model(current)
    # half the error of the line after 50 steps (0.14 vs 0.28 %)
    assert _rms_percent(pred[21:], field[21:], span) < 0.5 * _rms_percent(
        line[21:], field[21:], span
    )


def test_smoothness_penalty_lowers_roughness() -> None:
    current, field, _ = synthetic_measurement(noise=1e-3)
    rough = []
    for weight in (0.0, 1.0):
        model = PreisachModel(PreisachMesh.triangular(12), input_range=(0.0, 10.0))
        fit_preisach(model, current, field, steps=40, smoothness=weight)
        rough.append(float(density_roughness(model).detach()))
    assert rough[1] < rough[0]


def test_learned_initial_state_is_fitted() -> None:
    current, field, _ = synthetic_measurement(noise=0.0)
    model = PreisachModel(
        PreisachMesh.triangular(10), input_range=(0.0, 10.0), initial_state="learned"
    )
    before = model.raw_initial_state.detach().clone()
    # start at 1 A, not 0: at 0 A every hysteron is switched down at once and
    # the initial state is invisible
    fit_preisach(model, current[1:30], field[1:30], steps=20)
    assert not torch.equal(before, model.raw_initial_state.detach())


@pytest.mark.parametrize(
    ("current", "field", "match"),
    [
        (torch.zeros(10), torch.zeros(9), "lengths differ"),
        (torch.zeros(3), torch.arange(3.0), "at least"),
        (torch.tensor([0.0, 1.0, float("nan"), 2.0, 3.0]), torch.arange(5.0), "NaN"),
        (torch.arange(5.0), torch.tensor([0.0, 1.0, 2.0, float("inf"), 3.0]), "NaN"),
        (torch.arange(5.0) * 10, torch.arange(5.0), "input_range"),
        (torch.zeros(2, 5), torch.zeros(2, 5), "1-D"),
        (torch.arange(5.0), torch.ones(5), "constant"),
        (
            torch.arange(5.0, dtype=F64),
            torch.tensor([0, 1, 1e300, 3, 4.0], dtype=F64),
            "1e\\+100",
        ),
    ],
    ids=[
        "length",
        "too-few",
        "nan-current",
        "inf-field",
        "outside",
        "2d",
        "constant",
        "1e300",
    ],
)
def test_bad_data_raises(current, field, match) -> None:
    model = PreisachModel(PreisachMesh.triangular(5), input_range=(0.0, 10.0))
    with pytest.raises(ValueError, match=match):
        fit_preisach(model, current, field, steps=2)


def test_bad_options_raise() -> None:
    model = PreisachModel(PreisachMesh.triangular(5), input_range=(0.0, 10.0))
    u, y = torch.arange(6.0), torch.arange(6.0) ** 2
    with pytest.raises(ValueError, match="optimizer"):
        fit_preisach(model, u, y, optimizer="sgd")
    with pytest.raises(ValueError, match="steps"):
        fit_preisach(model, u, y, steps=0)


def test_callback_sees_every_step() -> None:
    current, field, _ = synthetic_measurement()
    model = PreisachModel(PreisachMesh.triangular(8), input_range=(0.0, 10.0))
    seen: list[int] = []
    res = fit_preisach(
        model,
        current,
        field,
        optimizer="adam",
        steps=7,
        callback=lambda i, _: seen.append(i),
    )
    assert seen == list(range(7)) and res.steps == 7


def _line_rms(current: torch.Tensor, field: torch.Tensor, n: int) -> float:
    """Held-out rms of a straight line fitted to the first ``n`` rows."""
    basis = torch.stack([torch.ones_like(current), current], dim=1)
    coef = torch.linalg.lstsq(basis[:n], field[:n, None]).solution
    return float(((basis @ coef).squeeze(1)[n:] - field[n:]).pow(2).mean().sqrt())


def test_slac_quadrupole_acceptance() -> None:
    # acceptance: fit the first 62 points, predict the other 125 with less than
    # half the straight line's rms (line 0.197 % of range; the CLI default
    # reaches about 0.3 of it)
    hist = read_magnet_csv(SLAC)
    current, field = hist.input, hist.output
    fit = fit_magnet(current[:62], field[:62], steps=100)
    assert fit.symmetric is False  # unipolar range
    with torch.no_grad():
        pred = fit.model(current)
        std = fit.band.std(fit.model, current)
    err = pred[62:] - field[62:]
    assert float(err.pow(2).mean().sqrt()) < 0.5 * _line_rms(current, field, 62)
    # the band: 74 % of these rows inside 2 std (the 80 % target is over
    # cases: SLAC, bipolar and B-H, see test_predictive and the benchmark);
    # a band that ignored the minor loops would cover far fewer
    assert float((err.abs() < 2 * std[62:]).double().mean()) >= 0.7


@pytest.mark.slow
def test_slac_quadrupole_band_with_the_cli_defaults() -> None:
    # defaults of `hysteresis fit`: at least 80 % of the 125 held-out rows inside
    # 2 std, held-out rms at most 0.065 % of the training output range
    hist = read_magnet_csv(SLAC)
    current, field = hist.input, hist.output
    fit = fit_magnet(current[:62], field[:62])
    assert fit.mesh_adapt == 0.0 and fit.band_fallback is None
    with torch.no_grad():
        pred = fit.model(current)
        std = fit.band.std(fit.model, current)
    err = pred[62:] - field[62:]
    span = float(field[:62].max() - field[:62].min())
    assert 100 * float(err.pow(2).mean().sqrt()) / span <= 0.065
    assert float((err.abs() <= 2 * std[62:]).double().mean()) >= 0.8


@pytest.mark.parametrize("symmetric", [False, True])
def test_fit_objective_from_fixed_states_equals_the_model(symmetric: bool) -> None:
    # the fit evaluates a fixed relay-state table (known initial state): it must
    # be the model's own output for any density
    from diffaccel.hysteresis.fit import _FromStates

    gen = torch.Generator().manual_seed(3)
    model = PreisachModel(
        PreisachMesh.triangular(7), input_range=(-2.0, 3.0), symmetric=symmetric
    )
    with torch.no_grad():
        model.raw_density.copy_(torch.randn(model.raw_density.shape, generator=gen))
        model.offset.fill_(0.1)
        model.slope.fill_(-0.3)
        model.scale.fill_(1.7)
    u = -2.0 + 5.0 * torch.rand(40, generator=gen, dtype=torch.float64)
    with torch.no_grad():
        got = _FromStates(model, model.normalize_input(u), model.states(u))()
        torch.testing.assert_close(got, model(u), rtol=0, atol=1e-12)
