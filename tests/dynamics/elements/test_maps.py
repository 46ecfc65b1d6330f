"""Physics of the element maps: analytic matrices, symplecticity, chromaticity."""

from __future__ import annotations

import math

import pytest
import torch

from diffaccel.dynamics import (
    ELECTRON,
    PROTON,
    SPEED_OF_LIGHT,
    Dipole,
    Drift,
    Quadrupole,
    TransverseDeflectingCavity,
)

P0C = 43.36e6  # [eV]
F64 = torch.float64


def _gamma2(p0c: float, mass: float) -> float:
    return 1.0 + (p0c / mass) ** 2


def _quad_block(k: float, length: float) -> torch.Tensor:
    if k > 0:
        r = math.sqrt(k)
        c, s, sp = (
            math.cos(r * length),
            math.sin(r * length) / r,
            -r * math.sin(r * length),
        )
    elif k < 0:
        r = math.sqrt(-k)
        c, s, sp = (
            math.cosh(r * length),
            math.sinh(r * length) / r,
            r * math.sinh(r * length),
        )
    else:
        c, s, sp = 1.0, length, 0.0
    return torch.tensor([[c, s], [sp, c]], dtype=F64)


def _jacobian(element, point: torch.Tensor) -> torch.Tensor:
    return torch.autograd.functional.jacobian(
        lambda p: element.track(p.unsqueeze(0), P0C)[0], point
    )


J = torch.zeros(6, 6, dtype=F64)
for _i in range(3):
    J[2 * _i, 2 * _i + 1] = 1.0
    J[2 * _i + 1, 2 * _i] = -1.0


# ---- analytic linear maps -------------------------------------------------------


@pytest.mark.parametrize("species", [ELECTRON, PROTON], ids=["electron", "proton"])
def test_drift_matrix(species) -> None:
    length = 1.3
    r = Drift("D", length=length).transfer_map(P0C, species)
    expected = torch.eye(7, dtype=F64)
    expected[0, 1] = expected[2, 3] = length
    expected[4, 5] = length / _gamma2(P0C, species.mass_ev)
    torch.testing.assert_close(r, expected, rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize(
    "k1", [12.0, -7.5, 0.0], ids=["focusing", "defocusing", "zero"]
)
def test_quadrupole_matrix(k1: float) -> None:
    length = 0.25
    r = Quadrupole("Q", length=length, k1=k1).transfer_map(P0C)
    torch.testing.assert_close(
        r[:2, :2], _quad_block(k1, length), rtol=1e-13, atol=1e-15
    )
    torch.testing.assert_close(
        r[2:4, 2:4], _quad_block(-k1, length), rtol=1e-13, atol=1e-15
    )
    assert r[4, 5].item() == pytest.approx(
        length / _gamma2(P0C, ELECTRON.mass_ev), rel=1e-13
    )


def test_quadrupole_skew_matrix_rotates() -> None:
    q = Quadrupole("Q", length=0.2, k1=5.0, tilt=math.pi / 4)
    r = q.transfer_map(P0C)
    # a 45 degree roll couples the planes: R13 = (C_x - C_y) / 2
    c_x, c_y = _quad_block(5.0, 0.2)[0, 0], _quad_block(-5.0, 0.2)[0, 0]
    assert r[0, 2].item() == pytest.approx(((c_x - c_y) / 2).item(), rel=1e-12)


def test_dipole_matrix_with_edges() -> None:
    length, angle, e1, e2 = 0.6, 0.25, 0.1, -0.05
    g = angle / length
    r = Dipole("B", length=length, angle=angle, e1=e1, e2=e2).transfer_map(P0C)
    c, s = math.cos(angle), math.sin(angle)
    body = torch.eye(7, dtype=F64)
    body[0, 0], body[0, 1], body[0, 5] = c, s / g, (1 - c) / g
    body[1, 0], body[1, 1], body[1, 5] = -g * s, c, s
    body[2, 3] = length
    body[4, 0], body[4, 1] = -s, -(1 - c) / g
    body[4, 5] = length / _gamma2(P0C, ELECTRON.mass_ev) - (length - s / g)

    def edge(e: float) -> torch.Tensor:
        m = torch.eye(7, dtype=F64)
        m[1, 0] = g * math.tan(e)
        m[3, 2] = -g * math.tan(e)
        return m

    torch.testing.assert_close(r, edge(e2) @ body @ edge(e1), rtol=1e-12, atol=1e-14)


def test_tdc_matrix() -> None:
    length, volt, freq, phase = 0.4, 1.5e6, 2.856e9, 0.3
    r = TransverseDeflectingCavity("T", length, volt, freq, phase).transfer_map(P0C)
    beta0 = 1 / math.sqrt(1 + (ELECTRON.mass_ev / P0C) ** 2)
    k = 2 * math.pi * freq / SPEED_OF_LIGHT
    a = volt / P0C  # electrons: +V / p0c
    half = Drift("D", length / 2).transfer_map(P0C)
    thin = torch.eye(7, dtype=F64)
    thin[1, 4] = thin[5, 0] = a * k * math.cos(phase) / beta0
    thin[1, 6] = a * math.sin(phase)  # centroid kick
    torch.testing.assert_close(r, half @ thin @ half, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize(
    ("tilt", "kicked", "quiet"),
    [(0.0, 1, 3), (math.pi / 2, 3, 1)],
    ids=["tilt0-horizontal", "tilt90-vertical"],
)
def test_tdc_streak_plane_follows_bmad(tilt: float, kicked: int, quiet: int) -> None:
    # Bmad's crab cavity: tilt 0 kicks px, tilt pi/2 kicks py; the head (z > 0)
    # of an electron bunch goes to +x (+y) at zero phase
    tdc = TransverseDeflectingCavity("T", 0.0, 1e6, 1.3e9, 0.0, tilt=tilt)
    head = torch.tensor([[0.0, 0.0, 0.0, 0.0, 1e-3, 0.0]], dtype=F64)
    out = tdc.track(head, P0C)[0]
    assert out[kicked].item() > 1e-4
    # the other plane only sees round-off of cos(pi / 2) ~ 6e-17
    assert abs(out[quiet].item()) < 1e-15 * out[kicked].item()


# ---- affine maps vs autograd Jacobians of the tracking ---------------------------

AFFINE = {
    "drift": Drift("D", 1.0),
    "quad_offset": Quadrupole("Q", 0.2, 15.0, dx=2e-3, dy=-1e-3),
    "quad_offset_tilted": Quadrupole("Q", 0.2, -9.0, tilt=0.3, dx=-1e-3, dy=2e-3),
    "quad_offset_weak": Quadrupole("Q", 0.2, 1e-3, dx=2e-3),  # series branch
    "dipole_tilted": Dipole("B", 0.5, 0.3, e1=0.1, e2=-0.05, tilt=0.4),
    "tdc_tilted": TransverseDeflectingCavity("T", 0.3, 1e6, 1.3e9, 0.0, tilt=0.7),
}


@pytest.mark.parametrize("name", sorted(AFFINE), ids=sorted(AFFINE))
def test_transfer_map_is_jacobian_and_orbit(name: str) -> None:
    element = AFFINE[name]
    m = element.transfer_map(P0C)
    zero = torch.zeros(6, dtype=F64)
    # all 36 entries (dispersion and path-length terms of the offset orbit
    # included) and the orbit offset agree to round-off
    torch.testing.assert_close(m[:6, :6], _jacobian(element, zero), rtol=0, atol=1e-13)
    orbit = element.track(zero.unsqueeze(0), P0C)[0]
    torch.testing.assert_close(m[:6, 6], orbit, rtol=0, atol=1e-17)
    assert m[6].tolist() == [0.0] * 6 + [1.0]
    # first-order maps about the reference orbit are symplectic
    torch.testing.assert_close(m[:6, :6].T @ J @ m[:6, :6], J, rtol=0, atol=1e-12)


def test_quad_offset_is_a_dipole_kick() -> None:
    # thin-lens limit: an offset dx gives the orbit a kick k1 L dx
    k1, length, dx = 10.0, 1e-4, 2e-3
    m = Quadrupole("Q", length, k1, dx=dx).transfer_map(P0C)
    assert m[1, 6].item() == pytest.approx(k1 * length * dx, rel=1e-6)


@pytest.mark.parametrize(
    ("element", "mono", "exact"),
    [
        (Drift("D", 1.0), True, True),
        (Drift("D", 1.0), False, False),
        (Quadrupole("Q", 0.1, 5.0, dx=1e-3), True, True),
        (Quadrupole("Q", 0.1, 5.0), False, False),
        (Dipole("B", 0.5, 0.0), True, True),
        (Dipole("B", 0.5, 0.2), True, False),
        (TransverseDeflectingCavity("T", 0.1, 0.0, 1.3e9), True, True),
        (TransverseDeflectingCavity("T", 0.1, 1e6, 1.3e9), True, False),
        (
            TransverseDeflectingCavity("T", 0.1, torch.tensor([0.0, 1e6]), 1.3e9),
            True,
            False,
        ),
    ],
    ids=[
        "drift-mono",
        "drift-spread",
        "quad-offset-mono",
        "quad-spread",
        "dipole-off",
        "dipole-bending",
        "tdc-off",
        "tdc-on",
        "tdc-scanned-on",
    ],
)
def test_linear_map_is_exact_flags(element, mono: bool, exact: bool) -> None:
    assert element.linear_map_is_exact(mono) is exact


# ---- tracking vs linear maps at small amplitude ------------------------------------

ELEMENTS = {
    "drift": Drift("D", 1.0),
    "quad_focus": Quadrupole("Q", 0.1, 20.0),
    "quad_defocus": Quadrupole("Q", 0.1, -20.0),
    "quad_tilted": Quadrupole("Q", 0.1, 20.0, tilt=0.3),
    "dipole": Dipole("B", 0.5, 0.3, e1=0.1, e2=0.05),
    "dipole_vertical": Dipole("B", 0.5, 0.3, tilt=math.pi / 2),
    "tdc": TransverseDeflectingCavity("T", 0.3, 1e6, 2.856e9, 0.0),
    "tdc_x": TransverseDeflectingCavity("T", 0.3, 1e6, 2.856e9, 0.0, tilt=math.pi / 2),
}


@pytest.mark.parametrize("name", sorted(ELEMENTS), ids=sorted(ELEMENTS))
def test_track_matches_transfer_map_near_axis(name: str, make_beam) -> None:
    element = ELEMENTS[name]
    scale = 1e-7
    beam = make_beam(100, sizes=(scale,) * 6)
    out = element.track(beam, P0C)
    m = element.transfer_map(P0C)
    lin = beam @ m[:6, :6].T + m[:6, 6]
    # the difference is second order: ~ (amplitude)^2 * O(100), far below 1e-9 * scale
    assert (out - lin).abs().max().item() < 1e-6 * scale


@pytest.mark.parametrize("name", sorted(ELEMENTS), ids=sorted(ELEMENTS))
def test_jacobian_is_symplectic(name: str) -> None:
    element = ELEMENTS[name]
    point = torch.tensor([1e-3, -2e-4, 5e-4, 3e-4, 2e-4, 1e-2], dtype=F64)
    m = _jacobian(element, point)
    # symplectic maps satisfy M^T J M = J to round-off (float64)
    torch.testing.assert_close(m.T @ J @ m, J, rtol=0, atol=1e-12)


def test_quad_with_zero_k1_equals_drift(make_beam) -> None:
    beam = make_beam(100, sizes=(1e-3, 1e-3, 1e-3, 1e-3, 1e-3, 2e-2))
    length = 0.5
    q = Quadrupole("Q", length, 0.0).track(beam, P0C)
    d = Drift("D", length).track(beam, P0C)
    # the quad body is paraxial (x' = px / P), the drift exact (x' = px / ps): they
    # differ by L px (px^2 + py^2) / (2 P^3) to leading order
    px, py, pz = beam[:, 1], beam[:, 3], beam[:, 5]
    bound = length * (px.square() + py.square()) / (2 * (1 + pz) ** 3)
    assert ((q[:, 0] - d[:, 0]).abs() <= 1.01 * bound * px.abs() + 1e-16).all()
    assert ((q[:, 2] - d[:, 2]).abs() <= 1.01 * bound * py.abs() + 1e-16).all()
    torch.testing.assert_close(q[:, [1, 3, 5]], d[:, [1, 3, 5]], rtol=0, atol=0)


def test_dipole_small_angle_limit_is_drift(make_beam) -> None:
    beam = make_beam(20)
    b = Dipole("B", 0.5, 0.0).track(beam, P0C)
    d = Drift("D", 0.5).track(beam, P0C)
    torch.testing.assert_close(b, d, rtol=1e-14, atol=1e-16)


def test_dipole_scan_through_zero_angle_equals_each_setting(make_beam) -> None:
    # a scan with straight (angle 0) and bending settings takes the path that
    # handles both; every row must equal the dipole of that one setting
    beam = make_beam(30)
    angles = torch.tensor([0.0, 0.3, -0.2], dtype=F64)
    out = Dipole("B", 0.5, angles, e1=0.05).track(beam, P0C)
    for i, a in enumerate(angles.tolist()):
        ref = Dipole("B", 0.5, a, e1=0.05).track(beam, P0C)
        torch.testing.assert_close(out[i], ref, rtol=1e-14, atol=1e-17)
    torch.testing.assert_close(
        out[0], Drift("D", 0.5).track(beam, P0C), rtol=1e-14, atol=1e-16
    )


def test_dipole_reference_orbit_stays_on_axis() -> None:
    zero = torch.zeros(1, 6, dtype=F64)
    out = Dipole("B", 1.0, 0.7, e1=0.2, e2=0.3).track(zero, P0C)
    assert out.abs().max().item() < 1e-15


def test_dipole_off_momentum_dispersion() -> None:
    # an off-momentum particle in a sector bend ends at x = rho (1 - cos a) d/(1+d)
    # exactly (circle of radius rho (1 + d) through the same entry point)
    length, angle, d = 1.0, 0.5, 0.01
    rho = length / angle
    p = torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.0, d]], dtype=F64)
    out = Dipole("B", length, angle).track(p, P0C)
    # exit plane at angle a: solve the circle/ray intersection analytically
    r = rho * (1 + d)
    center = -rho * d  # centre of the particle's circle, relative to the bend centre
    # point on the exit ray at distance t from the bend centre: (t cos a, t sin a)
    # |(t cos a - center, t sin a)| = r
    a = angle
    t = center * math.cos(a) + math.sqrt(r**2 - (center * math.sin(a)) ** 2)
    assert out[0, 0].item() == pytest.approx(t - rho, rel=1e-12)


# ---- chromatic focusing vs an independent thin-slice integration ---------------------


def _thin_slice_quad(
    p: torch.Tensor, k1: float, length: float, slices: int
) -> torch.Tensor:
    """Drift-kick-drift with many slices: x' = px / P, dpx/ds = -k1 x."""
    x, px, y, py, _, pz = p.unbind(-1)
    big_p = 1 + pz
    ds = length / slices
    for _ in range(slices):
        x = x + 0.5 * ds * px / big_p
        y = y + 0.5 * ds * py / big_p
        px = px - ds * k1 * x
        py = py + ds * k1 * y
        x = x + 0.5 * ds * px / big_p
        y = y + 0.5 * ds * py / big_p
    return torch.stack((x, px, y, py), -1)


@pytest.mark.parametrize("k1", [25.0, -25.0], ids=["focusing", "defocusing"])
def test_chromatic_focusing_matches_thin_slices(k1: float, make_beam) -> None:
    beam = make_beam(200, sizes=(1e-3, 1e-4, 1e-3, 1e-4, 1e-3, 3e-2))
    length = 0.2
    out = Quadrupole("Q", length, k1).track(beam, P0C)[:, :4]
    # leapfrog is second order: Richardson-extrapolate 400 and 800 slices, leaving
    # an O(h^4) error ~ (sqrt(k) L / 400)^4 ~ 4e-11 relative
    coarse = _thin_slice_quad(beam, k1, length, slices=400)
    fine = _thin_slice_quad(beam, k1, length, slices=800)
    ref = (4 * fine - coarse) / 3
    scale = beam[:, :4].abs().max()
    assert ((out - ref).abs().max() / scale).item() < 1e-8
    # and chromaticity is really there: the linear map differs at the pz level
    lin = (beam @ Quadrupole("Q", length, k1).transfer_map(P0C)[:6, :6].T)[:, :4]
    assert ((out - lin).abs().max() / scale).item() > 1e-3
