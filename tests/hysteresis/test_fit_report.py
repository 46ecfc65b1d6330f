"""Scores of a Preisach fit on its held-out rows."""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from diffaccel.data import FormatError, OptionError, write_csv_atomic
from diffaccel.hysteresis import fit_magnet
from diffaccel.hysteresis.fit_report import (
    fit_history,
    fit_line,
    fit_messages,
    read_fit_history,
    score_fit,
)
from diffaccel.hysteresis.predictive import min_training_rows
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


def _history_file(tmp_path: Path, current, field, name: str = "m.csv") -> Path:
    path = tmp_path / name
    rows = [[f"{a:.17g}", f"{b:.17g}"] for a, b in zip(current, field, strict=True)]
    write_csv_atomic(path, ["current_A", "field_Tm"], rows)
    return path


def test_read_fit_history_checks_rows_columns_and_magnitudes(
    case, tmp_path: Path
) -> None:
    current, field, n, _ = case
    path = _history_file(tmp_path, current.tolist(), field.tolist())
    hist = read_fit_history(path, "current_A", "field_Tm", None, n)
    assert len(hist) == len(current) and hist.header == ["current_A", "field_Tm"]
    with pytest.raises(OptionError, match="exceeds the") as err:
        read_fit_history(path, "current_A", "field_Tm", None, len(current) + 1)
    assert err.value.option == "--train-rows"
    with pytest.raises(OptionError, match="training rows"):
        read_fit_history(path, "current_A", "field_Tm", None, min_training_rows() - 1)
    with pytest.raises(OptionError, match="no column 't'") as err:
        read_fit_history(path, "current_A", "field_Tm", "t", n)
    assert err.value.option == "--time-column"
    values = [1.0, 2e100, *range(3, 10)]
    big = _history_file(tmp_path, values, list(range(9)), "big.csv")
    with pytest.raises(FormatError, match="column 'current_A', data row 2"):
        read_fit_history(big, "current_A", "field_Tm", None, min_training_rows())


def test_fit_history_fits_the_first_rows_and_scores_all(case, tmp_path) -> None:
    current, field, n, _ = case
    path = _history_file(tmp_path, current.tolist(), field.tolist())
    hist = read_fit_history(path, "current_A", "field_Tm", None, n)
    steps = []
    fit, score = fit_history(
        hist,
        n,
        data="m.csv",
        callback=lambda step, loss: steps.append(step),
        mesh_size=10,
        steps=60,
    )
    assert steps and fit.model.alpha.numel() == 55
    assert score.summary["train_rows"] == n and score.summary["data"] == "m.csv"
    assert score.summary["input_column"] == "current_A"
    assert (
        fit_messages(fit, score)
        == [
            *(f"note: {x}" for x in score.notes),
            *(f"warning: {x}" for x in score.alarms),
        ]
        or fit.band_fallback is not None
    )


def test_fit_messages_give_fallback_notes_then_alarms() -> None:
    fit = SimpleNamespace(band_fallback="band: jitter 1e-6")
    score = SimpleNamespace(notes=["3 rows outside"], alarms=["worse than a line"])
    assert fit_messages(fit, score) == [
        "warning: band: jitter 1e-6",
        "note: 3 rows outside",
        "warning: worse than a line",
    ]
