"""Fit-quality alarms of hysteresis fits (diffaccel.hysteresis.alarms)."""

from __future__ import annotations

import warnings

import pytest
import torch

from diffaccel.hysteresis import (
    HysteresisGP,
    PreisachMesh,
    PreisachModel,
    fit_hysteresis_gp,
)
from diffaccel.hysteresis.alarms import (
    GP_HELDOUT_RATIO,
    GP_NOISE_RATIO,
    LINE_RATIO,
    hgp_alarms,
    preisach_alarms,
)
from diffaccel.hysteresis.hgp import joint_gp_from_preisach
from diffaccel.hysteresis.synthetic import synthetic_measurement

F64 = torch.float64


def test_preisach_alarm_quiet_below_threshold_and_names_the_signal() -> None:
    assert preisach_alarms(0.3, 1.0, "held-out") == []
    assert preisach_alarms(None, 1.0, "held-out") == []
    (line,) = preisach_alarms(0.9, 1.0, "held-out", train_rmse=0.1, line_train_rmse=1)
    assert "held-out rms error 0.9 is 0.90 of a straight line's" in line
    assert f"alarm at {LINE_RATIO}" in line
    # training rows fitted well, held-out rows not: branches first, not the mesh
    assert line.index("branches or minor loops") < line.index("time order")
    assert "mesh cell" not in line


def test_preisach_alarm_puts_a_wide_input_range_first() -> None:
    (line,) = preisach_alarms(
        1.0,
        1.0,
        "held-out",
        train_rmse=0.9,
        line_train_rmse=1.0,
        input_range=(-1e6, 1e6),
        train_span=165.0,
        cell_width=1e5,
        output_range=5.0,
    )
    causes = line.split("Likely causes: ")[1]
    assert causes.startswith("the input range [-1e+06, 1e+06] is 1.21e+04x")
    assert "within one mesh cell (1e+05 input units" in causes


def test_hgp_alarms_thresholds() -> None:
    assert hgp_alarms(0.01, 0.01, 0.02, 0.02) == []
    assert hgp_alarms(GP_NOISE_RATIO * 0.999, 1.0) == []
    (noise,) = hgp_alarms(0.11, 0.0133)
    assert "noise 0.11 is 8.27x the plain GP's (0.0133" in noise
    assert "poor optimum" in noise
    (held,) = hgp_alarms(0.01, 0.02, GP_HELDOUT_RATIO * 1.01, 1.0)
    assert "held-out rms error" in held and "never did" in held


def _quad(seed: int):
    u, y, _ = synthetic_measurement(noise=1e-4, seed=seed)
    X, Y = u[:, None], y[:, None]
    n_tr = X.shape[0] - round(0.25 * X.shape[0])
    return X, Y, n_tr


def _pm(n: int = 12) -> PreisachModel:
    return PreisachModel(PreisachMesh.triangular(n=n), input_range=(-0.1, 10.1))


@pytest.fixture(autouse=True)
def _quiet_one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*not p.d.*")
        yield
    torch.set_num_threads(threads)


def _heldout(model: HysteresisGP, X, Y, n_tr: int) -> float:
    with torch.no_grad():
        if model.hysteretic_dims:
            mean = model.posterior_sequence(X[n_tr:]).mean
        else:
            mean = model.posterior(X[n_tr:].unsqueeze(0)).mean
    return float((mean.reshape(-1) - Y[n_tr:, 0]).pow(2).mean().sqrt())


def test_hgp_worse_than_plain_gp_alarms_on_a_synthetic_quadrupole() -> None:
    # a quadrupole's field (linear + 2 % hysteresis): an H-GP of the
    # magnetisation alone, from a uniform density, explains the staircase of
    # exact relays as noise; the plain GP does not
    X, Y, n_tr = _quad(0)
    plain = HysteresisGP(X[:n_tr], Y[:n_tr], {})
    p = fit_hysteresis_gp(plain, restarts=1, max_iter=100)
    naive = HysteresisGP(X[:n_tr], Y[:n_tr], {0: _pm()})
    r = fit_hysteresis_gp(naive, restarts=1, max_iter=100)
    alarms = hgp_alarms(
        r.noise_sigma,
        p.noise_sigma,
        _heldout(naive, X, Y, n_tr),
        _heldout(plain, X, Y, n_tr),
    )
    assert r.noise_sigma > 2.0 * p.noise_sigma
    assert alarms and "noise" in alarms[0]
    # started from a Preisach fit, with the input as a feature: quiet, better
    model, start = joint_gp_from_preisach(X[:n_tr], Y[:n_tr], _pm())
    g = fit_hysteresis_gp(
        model, restarts=2, max_iter=100, density_starts=start.density_starts
    )
    held, p_held = _heldout(model, X, Y, n_tr), _heldout(plain, X, Y, n_tr)
    assert g.noise_sigma <= p.noise_sigma
    assert held < p_held
    assert hgp_alarms(g.noise_sigma, p.noise_sigma, held, p_held) == []
