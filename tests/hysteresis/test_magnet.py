"""Tests of hysteretic magnets (diffaccel.hysteresis.magnet)."""

from __future__ import annotations

import pytest
import torch

from diffaccel.dynamics import ELECTRON, PROTON, Beamline, Drift, Quadrupole
from diffaccel.hysteresis import (
    HystereticMagnet,
    PreisachMesh,
    PreisachModel,
    hysteretic_settings,
    magnetic_rigidity,
)

DT = torch.float64


def _magnet(name: str = "Q1", g_max: float = 0.2) -> HystereticMagnet:
    pm = PreisachModel(PreisachMesh.triangular(n=12), input_range=(-10.0, 10.0))
    with torch.no_grad():
        pm.slope.zero_()
        pm.output_scale.fill_(g_max)  # integrated gradient = g_max * m [T]
    return HystereticMagnet(name, pm, length=0.1)


@pytest.mark.parametrize(
    ("p0c", "species", "brho"),
    [(1e9, ELECTRON, 3.3356409519815204), (1e9, PROTON, 3.3356409519815204)],
    ids=["electron-1GeV", "proton-1GeV"],
)
def test_magnetic_rigidity(p0c: float, species, brho: float) -> None:
    # B rho [T m] = p [GeV/c] / 0.299792458 (exact by definition of c)
    assert float(magnetic_rigidity(p0c, species)) == pytest.approx(brho, rel=1e-14)


def test_rigidity_rejects_nonpositive_momentum() -> None:
    with pytest.raises(ValueError, match="p0c must be positive"):
        magnetic_rigidity(torch.tensor([1e6, -1.0]))


def test_k1_is_integrated_gradient_over_length_and_rigidity() -> None:
    q1 = _magnet()
    u = torch.tensor([-10.0, 10.0, 0.0, -5.0, 5.0], dtype=DT)
    g = q1.integrated_gradient(u)
    k1 = q1.k1(u, p0c=50e6)
    expected = g / (0.1 * 50e6 / 299_792_458.0)
    torch.testing.assert_close(k1, expected, rtol=1e-14, atol=0)


def test_same_current_gives_branch_dependent_k1() -> None:
    q1 = _magnet()
    up = q1.k1(torch.tensor([-10.0, 0.0], dtype=DT), p0c=50e6)[-1]
    down = q1.k1(torch.tensor([10.0, 0.0], dtype=DT), p0c=50e6)[-1]
    # the descending branch keeps remanent field: clearly higher k1 at 0 A
    assert float(down - up) > 1.0


def test_continuing_from_final_state_equals_full_history() -> None:
    q1 = _magnet()
    hist = torch.tensor([0.0, 8.0, -3.0, 6.0], dtype=DT)
    fut = torch.tensor([2.0, -7.0, 4.0], dtype=DT)
    full = q1.k1(torch.cat([hist, fut]), p0c=50e6)[-3:]
    cont = q1.k1(fut, p0c=50e6, initial_state=q1.final_state(hist))
    # both exact relays: identical up to summation order
    torch.testing.assert_close(cont, full, rtol=1e-12, atol=1e-12)


def test_hysteretic_settings_drive_beamline_tracking() -> None:
    magnets = [_magnet("Q1"), _magnet("Q2")]
    line = Beamline(
        [
            Quadrupole("Q1", length=0.1),
            Drift("D1", length=0.5),
            Quadrupole("Q2", length=0.1),
            Drift("D2", length=1.0),
        ]
    )
    currents = torch.tensor([[5.0, -5.0], [-5.0, 5.0], [5.0, -5.0]], dtype=DT)
    settings, names = hysteretic_settings(magnets, currents, p0c=50e6)
    assert names == ["Q1.k1", "Q2.k1"]
    assert settings.shape == (3, 2)
    gen = torch.Generator().manual_seed(0)
    particles = torch.randn(200, 6, generator=gen, dtype=DT) * 1e-3
    out = line.track(particles, p0c=50e6, settings=settings, names=names)
    ref = line.track(particles, p0c=50e6, settings=settings[2:].clone(), names=names)
    torch.testing.assert_close(out[2], ref[0], rtol=0, atol=0)
    # same currents at steps 0 and 2, different magnetic states: k1 differs
    assert (settings[0] - settings[2]).abs().max() > 0.1


def test_bad_magnet_input_raises() -> None:
    pm = PreisachModel(PreisachMesh.triangular(n=4), input_range=(0.0, 1.0))
    with pytest.raises(ValueError, match="length must be > 0"):
        HystereticMagnet("Q1", pm, length=0.0)
    with pytest.raises(ValueError, match="P = 2 magnets"):
        hysteretic_settings([_magnet("Q1"), _magnet("Q2")], torch.zeros(4, 3), 1e8)
    with pytest.raises(ValueError, match="its own element"):
        hysteretic_settings([_magnet("Q1"), _magnet("Q1")], torch.zeros(4, 2), 1e8)
