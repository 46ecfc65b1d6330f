"""Bad arguments to the hysteresis API raise a ValueError naming the argument."""

from __future__ import annotations

import pytest
import torch

from diffaccel.hysteresis import (
    HysteresisBO,
    HysteresisGP,
    HystereticMagnet,
    PreisachMesh,
    PreisachModel,
    fit_magnet,
    hysteretic_settings,
    invert_preisach,
    next_step_output,
    synthetic_measurement,
)
from diffaccel.hysteresis.predictive import (
    MAX_MESH_SIZE,
    band_memory_bytes,
    default_input_range,
    symmetric_default,
)

DT = torch.float64
NAN = float("nan")


@pytest.fixture(scope="module")
def measured():
    u, y, model = synthetic_measurement()
    return u, y, model


def _pm() -> PreisachModel:
    return PreisachModel(mesh=PreisachMesh.triangular(n=6), input_range=(0, 1))


def _xy() -> tuple[torch.Tensor, torch.Tensor]:
    u = torch.cat([torch.linspace(0, 1, 15), torch.linspace(1, 0, 15)]).double()
    X = u.unsqueeze(-1)
    return X, torch.sin(3 * X)


# 1. invert_preisach ---------------------------------------------------------
@pytest.mark.parametrize("max_iter", [0, -1, 1.5, True])
def test_invert_refuses_bad_max_iter(measured, max_iter) -> None:
    u, _, model = measured
    with pytest.raises(ValueError, match="max_iter"):
        invert_preisach(model, torch.tensor(0.1), u[:10], max_iter=max_iter)


@pytest.mark.parametrize("tol", [0.0, -1.0, NAN, float("inf")])
def test_invert_refuses_bad_tol(measured, tol) -> None:
    u, _, model = measured
    with pytest.raises(ValueError, match="tol"):
        invert_preisach(model, torch.tensor(0.1), u[:10], tol=tol)


@pytest.mark.parametrize("limits", [(NAN, 1.0), (0.0,), (0.0, 1.0, 2.0)])
def test_invert_refuses_bad_limits(measured, limits) -> None:
    u, _, model = measured
    with pytest.raises(ValueError, match="limits"):
        invert_preisach(model, torch.tensor(0.1), u[:10], limits=limits)


def test_invert_max_iter_one_still_works(measured) -> None:
    u, _, model = measured
    res = invert_preisach(model, torch.tensor(0.1), u[:10], max_iter=1)
    assert res.iterations == 1


# 2. HysteresisGP / HysteresisBO bounds and settings ------------------------
@pytest.mark.parametrize(
    "bounds",
    [[[1.0], [0.0]], [[NAN], [1.0]], [[0.0], [float("inf")]]],
    ids=["reversed", "nan", "inf"],
)
def test_hgp_refuses_bad_bounds(bounds) -> None:
    X, Y = _xy()
    with pytest.raises(ValueError, match="bounds"):
        HysteresisGP(X, Y, {}, bounds=torch.tensor(bounds, dtype=DT))


def test_bo_refuses_nonfinite_bounds() -> None:
    with pytest.raises(ValueError, match="bounds contain NaN"):
        HysteresisBO(torch.tensor([[NAN], [1.0]], dtype=DT), {})


@pytest.mark.parametrize("beta", [NAN, float("inf"), -1.0, 0.0, "x"])
def test_bo_refuses_bad_beta(beta) -> None:
    with pytest.raises(ValueError, match="beta"):
        HysteresisBO(torch.tensor([[0.0], [1.0]], dtype=DT), {}, beta=beta)


@pytest.mark.parametrize(
    "name", ["num_restarts", "raw_samples", "fit_restarts", "fit_max_iter"]
)
@pytest.mark.parametrize("value", [0, -2, 1.5])
def test_bo_refuses_bad_counts(name, value) -> None:
    with pytest.raises(ValueError, match=name):
        HysteresisBO(torch.tensor([[0.0], [1.0]], dtype=DT), {}, **{name: value})


def test_bo_refuses_unknown_hysteretic_column() -> None:
    with pytest.raises(ValueError, match="column 3"):
        HysteresisBO(torch.tensor([[0.0], [1.0]], dtype=DT), {3: _pm()})


@pytest.mark.parametrize("q", [1.5, 0, "2"])
def test_bo_ask_refuses_bad_q(q) -> None:
    bo = HysteresisBO(torch.tensor([[0.0], [1.0]], dtype=DT), {}, fit_max_iter=5)
    X = torch.tensor([[0.1], [0.5], [0.9]], dtype=DT)
    bo.tell(X, torch.tensor([[0.0], [1.0], [0.0]], dtype=DT))
    with pytest.raises(ValueError, match="q must be"):
        bo.ask(q)


# 3b. fit_magnet mesh_size beyond what its band can hold ----------------------
@pytest.mark.parametrize(
    ("mesh_size", "memory"),
    [(101, "1.49 GB"), (500, "879 GB"), (10**6, "1.4e+16 GB")],
    ids=["101", "500", "1e6"],
)
def test_fit_magnet_refuses_a_mesh_its_band_cannot_hold(
    measured, mesh_size: int, memory: str
) -> None:
    # the band's dense (M + 3)^2 matrices: 500 failed after the fit with a
    # 125 GB allocation, 10**6 with a raw torch error building the mesh
    u, y, _ = measured
    with pytest.raises(ValueError, match=f"mesh_size {mesh_size} is beyond 100") as e:
        fit_magnet(u, y, mesh_size=mesh_size, steps=3)
    assert memory in str(e.value)


def test_band_memory_is_that_of_dense_hysteron_matrices() -> None:
    # 7 float64 matrices of (M + 3)^2, M = n (n + 1) / 2: n = 100 -> 5050
    assert band_memory_bytes(100) == 7 * 8 * 5053**2
    assert MAX_MESH_SIZE == 100


# 3. fit_magnet validation_fraction ------------------------------------------
@pytest.mark.parametrize("fraction", [-0.1, 1.0, NAN])
def test_fit_magnet_refuses_bad_validation_fraction(measured, fraction) -> None:
    u, y, _ = measured
    with pytest.raises(ValueError, match="validation_fraction"):
        fit_magnet(u, y, validation_fraction=fraction, steps=3)


# 4. non-finite and empty inputs ---------------------------------------------
def test_next_step_output_refuses_nonfinite_u_last(measured) -> None:
    _, _, model = measured
    state = torch.zeros(len(model.alpha), dtype=DT)
    with pytest.raises(ValueError, match="u_last"):
        next_step_output(model, torch.tensor([1.0], dtype=DT), state, NAN)
    with pytest.raises(ValueError, match="u_last"):
        next_step_output(
            model, torch.tensor([1.0], dtype=DT), state, torch.tensor(float("inf"))
        )


@pytest.mark.parametrize(
    "current", [torch.tensor([NAN, 1.0]), torch.zeros(0)], ids=["nan", "empty"]
)
def test_default_input_range_refuses_bad_current(current) -> None:
    with pytest.raises(ValueError, match="current"):
        default_input_range(current)


# 5. hysteresis keys, empty magnets, state size ------------------------------
@pytest.mark.parametrize("key", ["0", 0.0, True])
def test_hgp_refuses_non_int_hysteresis_keys(key) -> None:
    X, Y = _xy()
    with pytest.raises(ValueError, match="hysteresis keys"):
        HysteresisGP(X, Y, hysteresis={key: _pm()})


def test_hysteretic_settings_refuses_no_magnets() -> None:
    with pytest.raises(ValueError, match="magnets is empty"):
        hysteretic_settings([], torch.ones(5, 0), 43e6)


def test_hysteretic_settings_still_works_for_one_magnet(measured) -> None:
    u, _, model = measured
    settings, names = hysteretic_settings(
        [HystereticMagnet("Q1", model, 0.1)], u[:, None], 43e6
    )
    assert settings.shape == (u.numel(), 1) and names == ["Q1.k1"]


@pytest.mark.parametrize("shape", ["short", "long", "batched short", "3d"])
def test_next_step_output_refuses_wrong_state_size(measured, shape) -> None:
    _, _, model = measured
    m = len(model.alpha)
    bad = {"short": (3,), "long": (m + 1,), "batched short": (1, 3), "3d": (1, 1, m)}
    state = torch.zeros(bad[shape], dtype=DT)
    with pytest.raises(ValueError, match="state must have shape"):
        next_step_output(model, torch.tensor([1.0], dtype=DT), state, 0.0)


# 6. PreisachModel / PreisachMesh / symmetric_default / predict --------------
@pytest.mark.parametrize("dtype", [torch.int64, torch.bool, "float64"])
def test_preisach_model_refuses_non_float_dtype(dtype) -> None:
    with pytest.raises(ValueError, match="dtype must be a floating"):
        PreisachModel(dtype=dtype)


@pytest.mark.parametrize(
    "kwargs", [{"n": 1.5}, {"n": 4.0}, {"n": 4, "refine": 0.5}, {"n": 4, "band": "1"}]
)
def test_triangular_mesh_needs_ints(kwargs) -> None:
    with pytest.raises(ValueError, match="needs an int"):
        PreisachMesh.triangular(**kwargs)


@pytest.mark.parametrize("rng", [(1.0,), (0.0, 1.0, 2.0), (NAN, 1.0)])
def test_symmetric_default_needs_two_finite_numbers(rng) -> None:
    with pytest.raises(ValueError, match="input_range must be two finite"):
        symmetric_default(rng)


def test_predict_names_history_and_u_on_batch_mismatch() -> None:
    m = _pm()
    with pytest.raises(ValueError, match=r"history .*\(2, 5\).* u .*\(3, 4\)"):
        m.predict(torch.ones(3, 4) * 0.5, history=torch.ones(2, 5) * 0.5)
