"""Contract tests every Element subclass must pass (one case per class)."""

from __future__ import annotations

import pytest
import torch

import diffaccel.dynamics as dyn
from diffaccel.dynamics import Element

P0C = 50e6  # [eV]

# name -> (class, unbatched kwargs, batched kwargs with K = 3)
CASES: dict[str, tuple[type[Element], dict, dict]] = {
    "Drift": (dyn.Drift, {"length": 0.7}, {"length": [0.2, 0.7, 1.1]}),
    "Quadrupole": (
        dyn.Quadrupole,
        {"length": 0.2, "k1": 8.0, "tilt": 0.1, "dx": 2e-4, "dy": -1e-4},
        {"length": 0.2, "k1": [-12.0, 0.0, 9.0], "tilt": 0.1},
    ),
    "Dipole": (
        dyn.Dipole,
        {"length": 0.5, "angle": 0.2, "e1": 0.05, "e2": 0.08},
        {"length": 0.5, "angle": [0.1, 0.2, -0.3], "e1": 0.05},
    ),
    "TransverseDeflectingCavity": (
        dyn.TransverseDeflectingCavity,
        {"length": 0.3, "voltage": 2e5, "frequency": 2.856e9, "phase": 0.2},
        {"length": 0.3, "voltage": [1e5, 2e5, 3e5], "frequency": 2.856e9},
    ),
    "Screen": (dyn.Screen, {}, {}),
    "Solenoid": (
        dyn.Solenoid,
        {"length": 0.3, "ks": 3.0, "dx": 2e-4, "dy": -1e-4},
        {"length": 0.3, "ks": [-2.0, 0.0, 4.0]},
    ),
    "Sextupole": (
        dyn.Sextupole,
        {"length": 0.2, "k2": 80.0, "tilt": 0.1, "dx": 2e-4, "dy": -1e-4},
        {"length": 0.2, "k2": [-50.0, 0.0, 90.0], "tilt": 0.1},
    ),
    "RFCavity": (
        dyn.RFCavity,
        {"length": 0.5, "voltage": 2e6, "frequency": 1.3e9, "phase": 0.3},
        {"length": 0.5, "voltage": [1e6, 0.0, 3e6], "frequency": 1.3e9, "phase": 0.2},
    ),
    "LinearMap": (
        dyn.LinearMap,
        {"matrix": (torch.eye(6) + 0.1 * torch.ones(6, 6)).tolist()},
        {"matrix": (torch.eye(6) + 0.1 * torch.arange(3.0).view(3, 1, 1)).tolist()},
    ),
}


def _all_subclasses(cls: type) -> set[type]:
    out = set()
    for sub in cls.__subclasses__():
        out |= {sub} | _all_subclasses(sub)
    return out


def _build(cls: type[Element], kwargs: dict) -> Element:
    return cls(
        "E", **{k: torch.tensor(v, dtype=torch.float64) for k, v in kwargs.items()}
    )


def test_every_element_has_a_case() -> None:
    public = {
        c for c in _all_subclasses(Element) if c.__module__.startswith("diffaccel")
    }
    missing = sorted(c.__name__ for c in public if c.__name__ not in CASES)
    assert not missing, f"add contract cases for {missing}"


@pytest.mark.parametrize("name", sorted(CASES), ids=sorted(CASES))
def test_batched_equals_loop(name: str, make_beam) -> None:
    cls, _, batched = CASES[name]
    element = _build(cls, batched)
    beam = make_beam(50, seed=1)
    out = element.track(beam, P0C)
    k = 3 if batched else 1
    if not batched:
        assert out.shape == beam.shape
        return
    assert out.shape == (k, 50, 6)
    for i in range(k):
        single = {
            key: (v[i] if isinstance(v, list) else v) for key, v in batched.items()
        }
        ref = _build(cls, single).track(beam, P0C)
        # same arithmetic per setting: float64 round-off only
        torch.testing.assert_close(out[i], ref, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("name", sorted(CASES), ids=sorted(CASES))
def test_gradcheck(name: str, make_beam) -> None:
    cls, kwargs, _ = CASES[name]
    element = _build(cls, kwargs)
    beam = make_beam(4, seed=2).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: element.track(p, P0C), (beam,))


@pytest.mark.parametrize(
    "name",
    sorted(n for n in CASES if CASES[n][1]),
    ids=sorted(n for n in CASES if CASES[n][1]),
)
def test_gradcheck_parameters(name: str, make_beam) -> None:
    cls, kwargs, _ = CASES[name]
    beam = make_beam(4, seed=3)
    keys = [k for k in kwargs if k != "length" or cls is dyn.Drift]
    values = tuple(
        torch.tensor(kwargs[k], dtype=torch.float64, requires_grad=True) for k in keys
    )

    def f(*vals: torch.Tensor) -> torch.Tensor:
        params = {k: torch.tensor(v, dtype=torch.float64) for k, v in kwargs.items()}
        params.update(dict(zip(keys, vals, strict=True)))
        return cls("E", **params).track(beam, P0C)

    assert torch.autograd.gradcheck(f, values)


@pytest.mark.parametrize("name", sorted(CASES), ids=sorted(CASES))
def test_with_params_does_not_mutate(name: str) -> None:
    cls, kwargs, _ = CASES[name]
    element = _build(cls, kwargs)
    before = {k: v.clone() for k, v in element.params().items()}
    if element.param_names:
        key = element.param_names[0]
        new = element.with_params(**{key: element.params()[key] * 0.5})
        assert new is not element
    for k, v in element.params().items():
        assert torch.equal(v, before[k])


@pytest.mark.parametrize("name", sorted(CASES), ids=sorted(CASES))
def test_spec_round_trip(name: str) -> None:
    cls, kwargs, _ = CASES[name]
    element = _build(cls, kwargs)
    line = dyn.Beamline.from_spec([element.to_spec()])
    assert line.to_spec() == [element.to_spec()]


@pytest.mark.parametrize("name", sorted(CASES), ids=sorted(CASES))
def test_float32_in_float32_out(name: str, make_beam) -> None:
    cls, kwargs, _ = CASES[name]
    beam = make_beam(10, dtype=torch.float32)
    out = _build(cls, kwargs).track(beam, P0C)
    assert out.dtype == torch.float32
    assert torch.isfinite(out).all()
