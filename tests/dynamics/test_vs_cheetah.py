"""Agreement with cheetah-accelerator 0.8.4 (test-only oracle) in float64.

Tolerance: all six coordinates (cheetah's tau, delta converted to Bmad z, pz by
``cheetah_to_bmad``) to 1e-9 of each coordinate's range at the exit. Both codes solve
the same equations (Bmad's), so only round-off (~1e-14) and cheetah's approximated
low-energy z correction (a series in pz, ~1e-10 of the z range here) separate them.
"""

from __future__ import annotations

import math

import cheetah
import pytest
import torch
from cheetah.utils import cloud_in_cell_charge_deposition

from diffaccel.dynamics import (
    Dipole,
    Drift,
    Quadrupole,
    TransverseDeflectingCavity,
    bmad_to_cheetah,
    cheetah_to_bmad,
    cic_image,
    energy_to_p0c,
    p0c_to_energy,
)

F64 = torch.float64
P0C = 43.36e6  # [eV]
SPREAD = (1e-3, 1e-4, 1e-3, 1e-4, 1e-3, 2e-2)  # 2 % energy spread


def _t(v: float) -> torch.Tensor:
    return torch.tensor(v, dtype=F64)


def _track_cheetah(element, beam: torch.Tensor) -> torch.Tensor:
    particles = torch.ones(beam.shape[0], 7, dtype=F64)
    particles[:, :6] = bmad_to_cheetah(beam, P0C)
    incoming = cheetah.ParticleBeam(particles, energy=p0c_to_energy(_t(P0C)))
    out = element.track(incoming)
    return cheetah_to_bmad(out.particles, energy_to_p0c(out.energy))


def _rel(theirs: torch.Tensor, ours: torch.Tensor) -> torch.Tensor:
    """Largest difference per coordinate over the coordinate's range at the exit."""
    return (theirs - ours).abs().amax(0) / ours.abs().amax(0).clamp(min=1e-30)


def _tdc(tilt: float, phase: float):
    # cheetah's phase is in units of 2 pi; ours in rad
    return (
        lambda: cheetah.TransverseDeflectingCavity(
            length=_t(0.3),
            voltage=_t(4e6),
            frequency=_t(1.3e9),
            phase=_t(phase / (2 * math.pi)),
            tilt=_t(tilt),
            dtype=F64,
        ),
        lambda: TransverseDeflectingCavity("T", 0.3, 4e6, 1.3e9, phase, tilt=tilt),
    )


CASES = {
    "drift": (
        lambda: cheetah.Drift(length=_t(1.0), tracking_method="drift_kick_drift"),
        lambda: Drift("D", 1.0),
    ),
    "quad_focusing": (
        lambda: cheetah.Quadrupole(
            length=_t(0.1), k1=_t(20.0), tracking_method="drift_kick_drift", dtype=F64
        ),
        lambda: Quadrupole("Q", 0.1, 20.0),
    ),
    "quad_defocusing": (
        lambda: cheetah.Quadrupole(
            length=_t(0.1), k1=_t(-25.0), tracking_method="drift_kick_drift", dtype=F64
        ),
        lambda: Quadrupole("Q", 0.1, -25.0),
    ),
    "quad_tilted": (
        lambda: cheetah.Quadrupole(
            length=_t(0.2),
            k1=_t(10.0),
            tilt=_t(0.3),
            tracking_method="drift_kick_drift",
            dtype=F64,
        ),
        lambda: Quadrupole("Q", 0.2, 10.0, tilt=0.3),
    ),
    "quad_offsets": (
        lambda: cheetah.Quadrupole(
            length=_t(0.2),
            k1=_t(10.0),
            misalignment=torch.tensor([2e-3, -1e-3], dtype=F64),
            tilt=_t(0.3),
            tracking_method="drift_kick_drift",
            dtype=F64,
        ),
        lambda: Quadrupole("Q", 0.2, 10.0, tilt=0.3, dx=2e-3, dy=-1e-3),
    ),
    "dipole_tilted": (
        lambda: cheetah.Dipole(
            length=_t(0.5),
            angle=_t(-0.35),
            dipole_e2=_t(-0.35),
            tilt=_t(0.4),
            tracking_method="drift_kick_drift",
            dtype=F64,
        ),
        lambda: Dipole("B", 0.5, -0.35, e2=-0.35, tilt=0.4),
    ),
    "tdc_tilt0_horizontal": _tdc(0.0, 0.0),
    "tdc_tilt90_vertical": _tdc(math.pi / 2, 0.0),
    "tdc_off_crest": _tdc(0.2, 0.3),
    "dipole_with_edges": (
        lambda: cheetah.Dipole(
            length=_t(0.5),
            angle=_t(0.2),
            dipole_e1=_t(0.05),
            dipole_e2=_t(0.08),
            tracking_method="drift_kick_drift",
            dtype=F64,
        ),
        lambda: Dipole("B", 0.5, 0.2, 0.05, 0.08),
    ),
}


@pytest.mark.parametrize("name", sorted(CASES), ids=sorted(CASES))
def test_exact_tracking_with_energy_spread(name: str, make_beam) -> None:
    theirs, ours = CASES[name]
    beam = make_beam(500, sizes=SPREAD)
    rel = _rel(_track_cheetah(theirs(), beam), ours().track(beam, P0C))
    assert rel.max().item() < 1e-9, rel


@pytest.mark.parametrize(
    "k1", [12.0, -7.0, 0.0], ids=["focusing", "defocusing", "zero"]
)
def test_quadrupole_linear_map(k1: float) -> None:
    theirs = cheetah.Quadrupole(length=_t(0.2), k1=_t(k1), dtype=F64)
    r_theirs = theirs.first_order_transfer_map(
        p0c_to_energy(_t(P0C)), cheetah.Species("electron")
    )
    r_ours = Quadrupole("Q", 0.2, k1).transfer_map(P0C)[:6, :6]
    torch.testing.assert_close(r_ours[:4, :4], r_theirs[:4, :4], rtol=1e-12, atol=1e-14)


def test_dipole_linear_map_transverse() -> None:
    theirs = cheetah.Dipole(
        length=_t(0.5), angle=_t(0.2), dipole_e1=_t(0.05), dipole_e2=_t(0.08), dtype=F64
    )
    r_theirs = theirs.first_order_transfer_map(
        p0c_to_energy(_t(P0C)), cheetah.Species("electron")
    )
    r_ours = Dipole("B", 0.5, 0.2, 0.05, 0.08).transfer_map(P0C)[:6, :6]
    torch.testing.assert_close(r_ours[:4, :4], r_theirs[:4, :4], rtol=1e-12, atol=1e-14)


def test_coordinates_match_cheetah_conversion(make_beam) -> None:
    from cheetah.utils import bmadx

    beam = make_beam(100, sizes=SPREAD)
    theirs, _ = bmadx.bmad_to_cheetah_coords(
        beam, _t(P0C), _t(cheetah.Species("electron").mass_eV.item())
    )
    # delta = (E - E0) / p0c is a difference: compare to 1e-13 of the spread
    torch.testing.assert_close(
        bmad_to_cheetah(beam, P0C), theirs[:, :6], rtol=1e-11, atol=1e-15
    )


@pytest.mark.parametrize("shape", [(40, 50), (31, 17)], ids=["40x50", "31x17"])
def test_cloud_in_cell_matches_cheetah(shape: tuple[int, int]) -> None:
    g = torch.Generator().manual_seed(4)
    # inside the screen: beyond the outer pixel edge cheetah drops a particle while
    # ours still gives the edge pixel its bilinear share (continuous in position)
    x = torch.randn(2, 1000, generator=g, dtype=F64) * 1e-3
    y = torch.randn(2, 1000, generator=g, dtype=F64) * 2e-3 + 1e-3
    h, w = shape
    px, py = 1e-3, 0.8e-3
    extent = torch.tensor(
        [[-w * px / 2, w * px / 2], [-h * py / 2, h * py / 2]], dtype=F64
    )
    theirs = cloud_in_cell_charge_deposition(torch.stack([x, y], -1), (w, h), extent)
    ours = cic_image(x, y, shape, (px, py))
    # cheetah sums unit charges in (x, y) order; ours is row = y, divided by N
    torch.testing.assert_close(ours, theirs.mT / 1000, rtol=1e-12, atol=1e-15)
