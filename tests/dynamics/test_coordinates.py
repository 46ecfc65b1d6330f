"""Coordinate conversions: round trips and physical consistency."""

from __future__ import annotations

import pytest
import torch

from diffaccel.dynamics import (
    PROTON,
    SPEED_OF_LIGHT,
    Drift,
    bmad_to_cheetah,
    bmad_to_openpmd,
    cheetah_to_bmad,
    energy_to_p0c,
    openpmd_to_bmad,
    p0c_to_energy,
)

F64 = torch.float64
P0C = 43.36e6
SIZES = (1e-3, 1e-4, 1e-3, 1e-4, 1e-3, 2e-2)


@pytest.mark.parametrize("species", [None, PROTON], ids=["electron", "proton"])
def test_cheetah_round_trip(species, make_beam) -> None:
    kw = {} if species is None else {"species": species}
    beam = make_beam(200, sizes=SIZES)
    back = cheetah_to_bmad(bmad_to_cheetah(beam, P0C, **kw), P0C, **kw)
    # P = sqrt(E^2 - m^2) loses eps * (E / p0c)^2 ~ 1e-13 for 43 MeV/c protons
    torch.testing.assert_close(back, beam, rtol=1e-12, atol=1e-13)


def test_cheetah_seven_columns_accepted(make_beam) -> None:
    beam = make_beam(10, sizes=SIZES)
    seven = torch.cat((bmad_to_cheetah(beam, P0C), torch.ones(10, 1, dtype=F64)), -1)
    torch.testing.assert_close(
        cheetah_to_bmad(seven, P0C), beam, rtol=1e-12, atol=1e-15
    )


def test_energy_p0c_round_trip() -> None:
    e = p0c_to_energy(P0C)
    assert energy_to_p0c(e).item() == pytest.approx(P0C, rel=1e-15)
    with pytest.raises(ValueError, match="rest energy"):
        energy_to_p0c(1e5)


def test_openpmd_round_trip(make_beam) -> None:
    beam = make_beam(200, sizes=SIZES)
    cols = bmad_to_openpmd(beam, P0C, s=2.5, t_ref=1e-9, total_charge=1e-12)
    assert cols["weight"].sum().item() == pytest.approx(1e-12)
    assert torch.all(cols["z"] == 2.5)
    back, p0c = openpmd_to_bmad(cols, P0C, t_ref=1e-9)
    torch.testing.assert_close(back, beam, rtol=1e-10, atol=1e-15)
    assert p0c.item() == P0C


def test_openpmd_time_matches_drift_velocity(make_beam) -> None:
    # a particle with z < 0 arrives later: t - t_ref = -z / (beta c)
    beam = torch.zeros(1, 6, dtype=F64)
    beam[0, 4] = -1e-3
    cols = bmad_to_openpmd(beam, P0C)
    beta = 1 / (1 + (0.51099895e6 / P0C) ** 2) ** 0.5
    assert cols["t"].item() == pytest.approx(1e-3 / (beta * SPEED_OF_LIGHT), rel=1e-12)
    # and an exact drift keeps p unchanged: z shift equals the arrival-time shift
    out = Drift("D", 1.0).track(beam, P0C)
    assert out[0, 4].item() == pytest.approx(-1e-3, rel=1e-15)


def test_openpmd_rejects_fixed_time_snapshot(make_beam) -> None:
    cols = bmad_to_openpmd(make_beam(10, sizes=SIZES), P0C)
    cols["z"] = torch.linspace(0, 1e-3, 10, dtype=F64)
    with pytest.raises(ValueError, match="share one z"):
        openpmd_to_bmad(cols)
    del cols["t"]
    with pytest.raises(ValueError, match="missing"):
        openpmd_to_bmad(cols)
