"""``diffaccel hysteresis set`` through click's CliRunner, on the SLAC quadrupole."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from diffaccel.cli.main import main
from diffaccel.data import write_csv_atomic
from diffaccel.hysteresis import load_stream_fit, save_fit
from diffaccel.hysteresis.setpoint import field_for_k1, plan_setpoint
from diffaccel.hysteresis.synthetic import synthetic_magnet

SLAC = (
    Path(__file__).resolve().parents[1]
    / "hysteresis"
    / "data"
    / "slac_lcls2_quad_4194"
    / "measurements.csv"
)


@pytest.fixture(scope="module")
def slac_fit(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("slac") / "fit"
    args = ["hysteresis", "fit", str(SLAC), "--train-rows", "62"]
    args += ["--input", "current_A", "--output", "field_Tm", "--out", str(out)]
    args += ["--steps", "60", "--no-figures"]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    return out


def _set(fit: Path, *extra: str):
    args = ["hysteresis", "set", str(fit), "--history", str(SLAC), *extra]
    return CliRunner().invoke(main, args)


def _predict_after(fit: Path, inputs: list[float], tmp_path: Path) -> float:
    """``hysteresis predict``'s last prediction after the history and ``inputs``."""
    with open(SLAC, newline="") as f:
        history = [float(r["current_A"]) for r in csv.DictReader(f)]
    path = tmp_path / "then.csv"
    write_csv_atomic(path, ["current_A"], [[v] for v in history + inputs])
    out = tmp_path / "pred.csv"
    args = ["hysteresis", "predict", str(fit), "--input", str(path)]
    result = CliRunner().invoke(main, [*args, "--out", str(out)])
    assert result.exit_code == 0, result.output
    with open(out, newline="") as f:
        return float(list(csv.DictReader(f))[-1]["prediction"])


@pytest.mark.parametrize("target", [3.0, 0.7, 4.9])
def test_set_then_predict_gives_the_target(
    slac_fit: Path, tmp_path: Path, target: float
) -> None:
    result = _set(slac_fit, "--target", str(target), "--json")
    assert result.exit_code == 0, result.output
    plan = json.loads(result.output)
    span = json.loads((slac_fit / "summary.json").read_text())["output_range"]
    assert plan["approach"] in ("from below", "from above")
    assert plan["sequence"][-1] == plan["input"]
    assert plan["predicted_std"] > 0
    assert abs(plan["predicted_output"] - target) <= 1e-6 * span
    # predict, given the history and the inputs to apply, lands on the target
    predicted = _predict_after(slac_fit, plan["sequence"], tmp_path)
    assert abs(predicted - target) <= 1e-6 * span


def test_set_prints_input_and_approach(slac_fit: Path, tmp_path: Path) -> None:
    result = _set(slac_fit, "--target", "3.0")
    assert result.exit_code == 0, result.output
    first = result.output.splitlines()[0]
    assert first.startswith("set current_A to ") and " from above " in first
    assert "(1 std) predicted there" in first
    # the printed input (12 digits) gives the target as well
    value = float(first.split()[3])
    span = json.loads((slac_fit / "summary.json").read_text())["output_range"]
    assert abs(_predict_after(slac_fit, [value], tmp_path) - 3.0) <= 1e-6 * span


@pytest.mark.parametrize("target", ["9.0", "-1.0"])
def test_unreachable_target_is_one_line_naming_the_interval(
    slac_fit: Path, target: str
) -> None:
    result = _set(slac_fit, "--target", target)
    assert result.exit_code == 1
    lines = result.output.strip().splitlines()
    assert len(lines) == 1, result.output
    assert f"field_Tm {float(target):g} cannot be reached" in lines[0]
    assert "the fit reaches field_Tm " in lines[0] and " within current_A " in lines[0]
    assert "Traceback" not in result.output


def test_k1_target_goes_through_the_calibration(slac_fit: Path) -> None:
    k1, length, p0c = 1.0, 0.2, 4.0e9
    args = ["--target", str(k1), "--k1", "--length", str(length), "--p0c", str(p0c)]
    result = _set(slac_fit, *args, "--json")
    assert result.exit_code == 0, result.output
    plan = json.loads(result.output)
    field = k1 * length * p0c / 299_792_458.0
    assert plan["target_output"] == pytest.approx(field, rel=1e-15)
    assert field_for_k1(k1, length, p0c) == pytest.approx(field, rel=1e-15)
    assert plan["predicted_output"] == pytest.approx(field, abs=1e-8)
    result = _set(
        slac_fit, "--target", "100", "--k1", "--length", "0.2", "--p0c", "4e9"
    )
    assert result.exit_code == 1 and "1/m^2" in result.output


@pytest.mark.parametrize(
    "extra, match",
    [
        (["--k1"], "--k1 needs --length and --p0c"),
        (["--length", "0.2"], "--length only go with --k1"),
        (["--limits", "5", "1"], "LO < HI"),
        (["--limits", "200", "300"], "leave no current_A inside the fit's input"),
    ],
)
def test_bad_options_are_named(slac_fit: Path, extra: list[str], match: str) -> None:
    result = _set(slac_fit, "--target", "3.0", *extra)
    assert result.exit_code == 2
    assert match in result.output


def test_narrow_limits_shape_the_cycle(slac_fit: Path) -> None:
    result = _set(slac_fit, "--target", "3.0", "--limits", "0", "165", "--json")
    assert result.exit_code == 0, result.output
    plan = json.loads(result.output)
    assert plan["limits"] == [0.0, 165.0]
    assert all(0.0 <= v <= 165.0 for v in plan["sequence"])


def test_a_target_in_a_jump_gets_a_degaussing_cycle(
    slac_fit: Path, tmp_path: Path
) -> None:
    # some targets lie in a jump of the one-step response after this history
    # (a row of hysterons switching); a cycle to the limits reaches them
    spec, _ = load_stream_fit(slac_fit)
    with open(SLAC, newline="") as f:
        history = np.array([float(r["current_A"]) for r in csv.DictReader(f)])
    targets = np.linspace(0.1, 5.1, 400)
    target = next(
        t for t in targets if plan_setpoint(spec, history, float(t)).kind == "cycle"
    )
    result = _set(slac_fit, "--target", repr(float(target)), "--json")
    assert result.exit_code == 0, result.output
    plan = json.loads(result.output)
    assert plan["kind"] == "cycle" and len(plan["sequence"]) == 3
    assert plan["cycle"] in (plan["limits"], plan["limits"][::-1])
    span = json.loads((slac_fit / "summary.json").read_text())["output_range"]
    predicted = _predict_after(slac_fit, plan["sequence"], tmp_path)
    assert abs(predicted - target) <= 1e-6 * span
    text = _set(slac_fit, "--target", repr(float(target))).output
    assert text.startswith("first a degaussing cycle: current_A ")


def test_a_target_no_approach_reaches_is_one_line(tmp_path: Path) -> None:
    # hysteresis 3x the linear term on a 4-cell mesh: some outputs lie in a
    # jump of every approach tried
    magnet = synthetic_magnet(i_max=10.0, n=4, hysteresis_fraction=3.0)
    fit = tmp_path / "fit"
    save_fit(fit, magnet, extra={"input_column": "I", "output_column": "B"})
    history = [0.0, 8.0, 2.0, 6.0]
    path = tmp_path / "history.csv"
    write_csv_atomic(path, ["I"], [[v] for v in history])
    spec = magnet.stream_spec()
    lo, hi = (float(v) for v in magnet(torch.tensor([0.0, 10.0], dtype=torch.float64)))
    missed = next(
        t
        for t in np.linspace(lo, hi, 200)[1:-1]
        if abs(plan_setpoint(spec, np.array(history), float(t)).error) > 1e-6 * hi
    )
    args = ["hysteresis", "set", str(fit), "--history", str(path)]
    result = CliRunner().invoke(main, [*args, "--target", repr(float(missed))])
    assert result.exit_code == 1
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and "lies in a jump of the fitted model" in lines[0]
    assert "nearest: I " in lines[0]
