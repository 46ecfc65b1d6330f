"""Tests of the ask/tell Bayesian optimiser (diffaccel.hysteresis.bo)."""

from __future__ import annotations

import warnings

import pytest
import torch

from diffaccel.hysteresis import HysteresisBO, PreisachMesh, PreisachModel

DT = torch.float64


@pytest.fixture(autouse=True)
def _quiet_numerics_one_thread():
    # small GPs: single-threaded is fastest and avoids OpenMP spinning
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*not p.d.*")
        warnings.filterwarnings("ignore", message=".*Optimization failed.*")
        yield
    torch.set_num_threads(threads)


def test_plain_bo_finds_the_maximum_of_a_parabola() -> None:
    bounds = torch.tensor([[0.0], [1.0]], dtype=DT)
    bo = HysteresisBO(bounds, {}, acquisition="ucb", beta=1.0, raw_samples=32)
    X0 = torch.tensor([[0.05], [0.5], [0.95]], dtype=DT)
    bo.tell(X0, -((X0 - 0.3) ** 2))
    for _ in range(6):
        x = bo.ask()
        bo.tell(x, -((x - 0.3) ** 2))
    x_best, _ = bo.best
    # a 1-D smooth bump is located to a few % of the range within 6 steps
    assert abs(float(x_best[0]) - 0.3) < 0.05


@pytest.mark.parametrize(
    ("acquisition", "q"),
    [("ucb", 1), ("logei", 1), ("ucb", 2), ("logei", 2)],
    ids=["ucb-q1", "logei-q1", "qucb-q2", "qlogei-q2"],
)
def test_mixed_hysteretic_and_plain_inputs(acquisition: str, q: int) -> None:
    pm = PreisachModel(PreisachMesh.triangular(n=8), input_range=(0.0, 10.0))
    bounds = torch.tensor([[0.0, -1.0], [10.0, 1.0]], dtype=DT)
    bo = HysteresisBO(
        bounds, {0: pm}, acquisition=acquisition, raw_samples=16, num_restarts=2
    )
    gen = torch.Generator().manual_seed(0)
    X = torch.rand(6, 2, generator=gen, dtype=DT) * (bounds[1] - bounds[0]) + bounds[0]
    with torch.no_grad():
        m = pm.magnetization(X[:, 0])
    bo.tell(X, (m - X[:, 1] ** 2).unsqueeze(-1))
    assert bo.model is not None and bo.model.hysteretic_dims == (0,)
    cand = bo.ask(q)
    assert cand.shape == (q, 2)
    assert ((cand >= bounds[0]) & (cand <= bounds[1])).all()
    bo.tell(cand, torch.zeros(q, 1, dtype=DT))
    assert bo.X.shape == (6 + q, 2)
    # the history keeps growing in order: the refit model sees all of it
    assert bo.model.train_X.shape == (6 + q, 2)


def test_minimise_reports_lowest_measurement() -> None:
    bounds = torch.tensor([[0.0], [1.0]], dtype=DT)
    bo = HysteresisBO(bounds, {}, maximize=False)
    X = torch.tensor([[0.1], [0.4], [0.8]], dtype=DT)
    bo.tell(X, torch.tensor([[2.0], [-1.0], [0.5]], dtype=DT))
    x_best, y_best = bo.best
    assert float(x_best[0]) == pytest.approx(0.4)
    assert float(y_best) == -1.0


def test_ask_before_enough_data_raises() -> None:
    bo = HysteresisBO(torch.tensor([[0.0], [1.0]], dtype=DT), {})
    bo.tell(torch.tensor([[0.2]], dtype=DT), torch.tensor([[1.0]], dtype=DT))
    with pytest.raises(RuntimeError, match="at least 3"):
        bo.ask()


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"bounds": torch.zeros(3, 1, dtype=DT)}, r"shape \(2, d\)"),
        ({"bounds": torch.tensor([[1.0], [0.0]], dtype=DT)}, "lower < upper"),
        ({"acquisition": "ei"}, "'ucb' or 'logei'"),
        ({"beta": 0.0}, "beta"),
    ],
    ids=["bounds-shape", "bounds-order", "acquisition", "beta"],
)
def test_bad_configuration_raises(kwargs: dict, match: str) -> None:
    args = {"bounds": torch.tensor([[0.0], [1.0]], dtype=DT), "hysteresis": {}}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        HysteresisBO(**args)


def test_tell_rejects_nan_and_mismatched_lengths() -> None:
    bo = HysteresisBO(torch.tensor([[0.0], [1.0]], dtype=DT), {})
    with pytest.raises(ValueError, match="finite"):
        bo.tell(torch.tensor([[0.2]], dtype=DT), torch.tensor([[float("nan")]]))
    with pytest.raises(ValueError, match="2 settings but Y has 1"):
        bo.tell(torch.tensor([[0.2], [0.3]], dtype=DT), torch.tensor([[1.0]]))
