"""Scores of a Preisach fit on its held-out rows."""

from __future__ import annotations

import math

import pytest
import torch

from diffaccel.hysteresis import fit_magnet
from diffaccel.hysteresis.fit_report import fit_line, score_fit
from diffaccel.hysteresis.synthetic import bipolar_quadrupole_case

NAMES = dict(
    data="m.csv",
    input_column="current_A",
    output_column="field_Tm",
    mesh_size=10,
    smoothness=0.0,
    initial_state="negative",
)


@pytest.fixture(scope="module")
def case():
    current, field, n, _ = bipolar_quadrupole_case(0)
    fit = fit_magnet(current[:n], field[:n], mesh_size=10, steps=60)
    return current, field, n, fit


def test_score_fit_numbers_are_those_of_the_prediction(case) -> None:
    current, field, n, fit = case
    score = score_fit(fit, current, field, n, **NAMES)
    s = score.summary
    assert score.prediction.shape == score.std.shape == current.shape
    resid = score.prediction - field
    assert s["train_rmse"] == pytest.approx(float(resid[:n].pow(2).mean().sqrt()))
    assert s["test_rmse"] == pytest.approx(float(resid[n:].pow(2).mean().sqrt()))
    span = float(field[:n].max() - field[:n].min())
    assert s["output_range"] == pytest.approx(span)
    assert s["test_rmse_percent"] == pytest.approx(100 * s["test_rmse"] / span)
    inside = (resid[n:].abs() <= 2 * score.std[n:]).double().mean()
    assert s["test_inside_2std"] == pytest.approx(float(inside))
    # a hysteretic magnet: the fit beats a straight line on the held-out rows
    assert s["test_rmse"] < 0.5 * s["straight_line_test_rmse"]
    assert (s["rows"], s["train_rows"], s["test_rows"]) == (len(current), n, 8)
    assert s["n_hysterons"] == 55 and s["warnings"] == score.alarms
    line = fit_line(s)
    assert line.startswith(f"fit {n} rows in ")
    assert f"held-out rmse {s['test_rmse']:.4g} (" in line
    assert line.endswith(f"percentages of the training output range {span:.4g}")


def test_score_fit_without_held_out_rows(case) -> None:
    current, field, n, fit = case
    score = score_fit(fit, current[:n], field[:n], n, **NAMES)
    s = score.summary
    assert s["test_rows"] == 0 and s["test_rmse"] is None
    assert s["straight_line_test_rmse"] is None and s["test_inside_2std"] is None
    assert "held-out rmse n/a;" in fit_line(s)
    assert math.isfinite(s["train_rmse"])


def test_score_fit_notes_rows_beyond_the_input_range(case) -> None:
    current, field, n, fit = case
    hi = fit.model.input_range[1]
    far = torch.cat([current, torch.tensor([2.0 * hi], dtype=current.dtype)])
    score = score_fit(fit, far, torch.cat([field, field[-1:]]), n, **NAMES)
    assert score.notes and score.summary["notes"] == score.notes
