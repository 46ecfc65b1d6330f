"""Xopt's own loop with the hysteresis-aware generator on a tiny hysteretic problem."""

from __future__ import annotations

import subprocess
import sys
import warnings
from pathlib import Path

import pytest
import torch

pytest.importorskip("xopt")
yaml = pytest.importorskip("yaml")

from xopt import Evaluator, Xopt  # noqa: E402
from xopt.generators import get_generator  # noqa: E402

from diffaccel.hysteresis import HysteresisGP, PreisachMesh, PreisachModel  # noqa: E402
from diffaccel.hysteresis.xopt_generator import (  # noqa: E402
    HysteresisBayesianGenerator,
    HysteresisModelConstructor,
)

DOCS = Path(__file__).resolve().parents[2] / "docs"

YAML = """
generator:
  name: hysteresis_bayesian
  hysteretic_inputs: [I]
  beta: 2.0
  gp_constructor: {name: hysteresis, mesh_n: 5, fit_max_iter: 30}
  numerical_optimizer: {name: LBFGS, n_restarts: 2}
  vocs:
    variables: {I: [-1.0, 1.0], x: [0.0, 1.0]}
    objectives: {f: MINIMIZE}
"""


def _evaluator() -> tuple[Evaluator, list[float]]:
    """f = (m - 0.2)^2 + (x - 0.3)^2, m the magnetisation after the applied history."""
    truth = PreisachModel(PreisachMesh.triangular(n=8), input_range=(-1.0, 1.0))
    history: list[float] = []

    def f(inputs: dict) -> dict:
        history.append(float(inputs["I"]))
        with torch.no_grad():
            m = truth.magnetization(torch.tensor(history, dtype=torch.float64))[-1]
        return {"f": float((m - 0.2) ** 2) + (float(inputs["x"]) - 0.3) ** 2}

    return Evaluator(function=f), history


def test_registered_by_name() -> None:
    assert get_generator("hysteresis_bayesian") is HysteresisBayesianGenerator


def test_yaml_runs_under_xopt_and_proposes_within_bounds() -> None:
    evaluator, history = _evaluator()
    X = Xopt.model_validate({**yaml.safe_load(YAML), "evaluator": evaluator})
    assert isinstance(X.generator, HysteresisBayesianGenerator)
    assert X.generator.gp_constructor.hysteretic_inputs == ["I"]
    torch.manual_seed(0)
    X.random_evaluate(4)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for _ in range(3):
            X.step()
    data = X.data
    assert len(data) == 7 and len(history) == 7
    assert data["I"].between(-1.0, 1.0).all() and data["x"].between(0.0, 1.0).all()
    assert data["f"].notna().all()
    model = X.generator.model
    assert isinstance(model, HysteresisGP)
    # the model's history is Xopt's data, in order (6 rows when step 3 fitted it)
    expected = torch.tensor(data[["I", "x"]].to_numpy()[:6], dtype=torch.float64)
    torch.testing.assert_close(model.train_X, expected)
    assert len(model.hysteresis_models) == 1


def test_bad_options_are_one_line_errors() -> None:
    vocs = {"variables": {"I": [-1.0, 1.0]}, "objectives": {"f": "MINIMIZE"}}
    with pytest.raises(ValueError, match="not VOCS variables"):
        HysteresisBayesianGenerator(vocs=vocs, hysteretic_inputs=["J"])
    with pytest.raises(ValueError, match="'hysteresis' constructor"):
        HysteresisBayesianGenerator(vocs=vocs, gp_constructor="standard")
    with pytest.raises(ValueError, match="initial_state"):
        HysteresisModelConstructor(initial_state="sideways")


def test_docs_yaml_runs_under_xopt() -> None:
    text = (DOCS / "xopt.md").read_text()
    config = yaml.safe_load(text.split("```yaml\n", 1)[1].split("```", 1)[0])
    assert config["generator"]["name"] == "hysteresis_bayesian"
    assert config["evaluator"]["function"] == "my_machine.measure"
    assert config["stopping_condition"]["max_evaluations"] == 50
    config["generator"]["gp_constructor"].update(mesh_n=4, fit_max_iter=20)
    config["stopping_condition"]["max_evaluations"] = 6
    truth = PreisachModel(PreisachMesh.triangular(n=6), input_range=(-10.0, 10.0))
    history: list[list[float]] = []

    def measure(inputs: dict) -> dict:
        history.append([float(inputs[n]) for n in ("Q1", "Q2", "Q3")])
        with torch.no_grad():
            m = truth.magnetization(torch.tensor(history, dtype=torch.float64).T)
        return {"distance": float((m[:, -1] - 0.1).norm())}

    X = Xopt.model_validate({**config, "evaluator": Evaluator(function=measure)})
    torch.manual_seed(1)
    X.random_evaluate(4)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        X.run()
    assert len(X.data) == 6
    assert X.data[["Q1", "Q2", "Q3"]].abs().le(10.0).all().all()
    assert isinstance(X.generator.model, HysteresisGP)
    assert X.generator.gp_constructor.hysteretic_inputs == ["Q1", "Q2", "Q3"]


def test_hysteresis_room_does_not_import_xopt() -> None:
    code = (
        "import sys, diffaccel.hysteresis as h; h.HysteresisBO; h.HysteresisGP; "
        "print(sorted(m for m in sys.modules if m.split('.')[0] == 'xopt'))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == "[]", out.stdout


def test_importing_the_generator_keeps_torchs_default_dtype() -> None:
    """Xopt sets float64 as torch's default when imported; the module restores
    the caller's default (a fresh interpreter: this one may have it cached)."""
    import subprocess
    import sys

    code = (
        "import torch; torch.set_default_dtype(torch.float32); "
        "import diffaccel.hysteresis.xopt_generator; "
        "print(torch.get_default_dtype())"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == "torch.float32"
