"""Sector bending magnet with hard-edge entrance and exit faces."""

from __future__ import annotations

import torch
from torch import Tensor

from diffaccel.dynamics.elements._kernels import (
    affine_identity,
    exact_drift,
    is_zero,
    lab_frame_map,
    none_true,
    velocity_z_shift,
)
from diffaccel.dynamics.elements.element import Coords, Element, bcast
from diffaccel.dynamics.species import ELECTRON, Species

__all__ = ["Dipole"]

# Below this bending angle [rad] the body is tracked as a drift.
_SMALL_ANGLE = 1e-9


class Dipole(Element):
    """Sector bend (uniform field, no gradient) tracked with the exact map.

    The body is the exact solution in a uniform field: each particle moves on a
    helix of horizontal radius ``sqrt((1 + pz)^2 - py^2) / g`` with ``g = angle /
    length`` the reference curvature; positive ``angle`` bends towards -x (Bmad).
    Hard-edge pole faces with angles ``e1`` (entrance) and ``e2`` (exit) give
    linear kicks ``px += g tan(e) x``, ``py -= g tan(e - psi) y``, with Bmad's
    linear fringe correction ``psi = 2 fint hgap g (1 + sin^2 e) / cos e``
    (``psi = 0`` without a fringe-field integral or gap: the default).
    Chromatic effects follow from the exact body. ``z`` follows Bmad:
    ``z += L beta/beta0 - (path length)``.

    Args:
        name: Element name.
        length: Arc length of the reference orbit [m], must be > 0 if ``angle``
            is non-zero.
        angle: Bending angle [rad].
        e1: Entrance pole-face angle [rad] (0 for a pure sector bend).
        e2: Exit pole-face angle [rad].
        tilt: Roll about the beam axis [rad]; ``pi / 2`` bends vertically.
        hgap: Half gap of the magnet at the entrance [m] (Bmad/elegant HGAP).
        hgapx: Half gap at the exit [m].
        fint: Fringe-field integral of the entrance face (Bmad/elegant FINT).
        fintx: Fringe-field integral of the exit face.

    Shapes:
        ``track``: ``(*K, N, 6) -> (*K, N, 6)``; ``transfer_map``: ``(*K, 7, 7)``.

    Example:
        >>> b = Dipole("B1", length=0.5, angle=0.2, e1=0.1, e2=0.1)
        >>> b.transfer_map(1e9).shape
        torch.Size([7, 7])
    """

    param_names = (
        "length",
        "angle",
        "e1",
        "e2",
        "tilt",
        "hgap",
        "hgapx",
        "fint",
        "fintx",
    )
    reads_z = False
    optional_params = ("e1", "e2", "tilt", "hgap", "hgapx", "fint", "fintx")
    nonnegative_params = (("length", "m"),)

    def __init__(
        self,
        name: str,
        length: Tensor | float = 0.0,
        angle: Tensor | float = 0.0,
        e1: Tensor | float = 0.0,
        e2: Tensor | float = 0.0,
        tilt: Tensor | float = 0.0,
        hgap: Tensor | float = 0.0,
        hgapx: Tensor | float = 0.0,
        fint: Tensor | float = 0.0,
        fintx: Tensor | float = 0.0,
    ) -> None:
        super().__init__(
            name,
            length=length,
            angle=angle,
            e1=e1,
            e2=e2,
            tilt=tilt,
            hgap=hgap,
            hgapx=hgapx,
            fint=fint,
            fintx=fintx,
        )
        bad = (self.length.detach() == 0) & (self.angle.detach() != 0)
        if bool(bad.any()):
            raise ValueError(f"{self.owner}: a non-zero angle needs a length > 0 m.")

    def track_columns(self, coords: Coords, p0c: Tensor, species: Species) -> Coords:
        """Unchecked column tracking (see :meth:`Element.track_columns`)."""
        like = coords[0]
        length, angle = bcast(self.length, like), bcast(self.angle, like)
        g = _curvature(length, angle)
        e1, e2 = bcast(self.e1, like), bcast(self.e2, like)
        h1, h2 = g * e1.tan(), g * e2.tan()
        v1 = _vertical_edge(g, e1, bcast(self.fint, like), bcast(self.hgap, like))
        v2 = _vertical_edge(g, e2, bcast(self.fintx, like), bcast(self.hgapx, like))
        mu2 = (species.mass_ev / p0c).square().unsqueeze(-1)
        return self._in_element_frame(
            coords, lambda c: _bend_body(c, g, length, angle, (h1, v1), (h2, v2), mu2)
        )

    def transfer_map(self, p0c: Tensor | float, species: Species = ELECTRON) -> Tensor:
        """Affine first-order map with the edge kicks, shape ``(*K, 7, 7)``.

        The reference particle stays on the axis (zero offset column).
        """
        length, angle, e1, e2, tilt, hgap, hgapx, fint, fintx, p0c = self._map_params(
            p0c, *self.param_names
        )
        g = _curvature(length, angle)
        mu2 = (species.mass_ev / p0c).square()
        c, s = angle.cos(), angle.sin()
        sinc = torch.sinc(angle / torch.pi)  # sin(a) / a
        half = torch.sinc(angle / (2 * torch.pi))
        one_minus_c_over_g = length * angle * 0.5 * half.square()  # (1 - cos a) / g
        r = g.new_zeros(*g.shape, 7, 7)
        r[..., 6, 6] = 1.0
        r[..., 0, 0] = c
        r[..., 0, 1] = length * sinc
        r[..., 0, 5] = one_minus_c_over_g
        r[..., 1, 0] = -g * s
        r[..., 1, 1] = c
        r[..., 1, 5] = s
        r[..., 2, 2] = 1.0
        r[..., 2, 3] = length
        r[..., 3, 3] = 1.0
        r[..., 4, 0] = -s
        r[..., 4, 1] = -one_minus_c_over_g
        r[..., 4, 4] = 1.0
        r[..., 4, 5] = length * mu2 / (1.0 + mu2) - length * (1.0 - sinc)
        r[..., 5, 5] = 1.0
        entrance = _edge_map(g, e1, _vertical_edge(g, e1, fint, hgap))
        exit_ = _edge_map(g, e2, _vertical_edge(g, e2, fintx, hgapx))
        return lab_frame_map(exit_ @ r @ entrance, tilt)

    def linear_map_is_exact(self, monochromatic: bool) -> bool:
        """Only when it does not bend (a drift); the exact body has ``g x^2`` terms."""
        return is_zero(self.length) or (monochromatic and is_zero(self.angle))


def _curvature(length: Tensor, angle: Tensor) -> Tensor:
    """Reference curvature ``g = angle / length`` [1/m] (0 where length is 0)."""
    return angle / length.where(length > 0, torch.ones_like(length))


def _vertical_edge(g: Tensor, e: Tensor, fint: Tensor, hgap: Tensor) -> Tensor:
    """Vertical edge focusing ``g tan(e - psi)`` [1/m] with Bmad's fringe ``psi``."""
    psi = 2 * fint * hgap * g * (1 + e.sin().square()) / e.cos()
    return g * (e - psi).tan()


def _edge_map(g: Tensor, e: Tensor, v: Tensor) -> Tensor:
    """Affine map ``(*K, 7, 7)`` of a pole face at angle ``e`` [rad].

    ``v`` is the vertical focusing of :func:`_vertical_edge` [1/m].
    """
    r = affine_identity(g.shape, g)
    r[..., 1, 0] = g * e.tan()
    r[..., 3, 2] = -v
    return r


def _bend_body(
    coords: Coords,
    g: Tensor,
    length: Tensor,
    angle: Tensor,
    edge1: tuple[Tensor, Tensor],
    edge2: tuple[Tensor, Tensor],
    mu2: Tensor,
) -> Coords:
    """Bend-frame body: entrance face kicks, exact body, exit face kicks.

    ``edge1``, ``edge2``: horizontal and vertical focusing ``(h, v)`` [1/m] of
    the entrance and exit faces.
    """
    x, px, y, py, z, pz = coords
    px, py = px + edge1[0] * x, py - edge1[1] * y

    small = angle.abs() < _SMALL_ANGLE
    one = torch.ones_like(angle)
    th = angle.where(~small, one)
    gs = g.where(~small, th / length.where(length > 0, one))
    p = 1.0 + pz
    pperp2 = p.square() - py.square()
    ps = (pperp2 - px.square()).sqrt()
    c, s = th.cos(), th.sin()
    px1 = px * c + (ps - 1.0 - gs * x) * s
    ps1 = (pperp2 - px1.square()).sqrt()
    x1 = x * c + (px * s + ps1 - ps * c - (1.0 - c)) / gs
    turn = th + torch.atan2(px, ps) - torch.atan2(px1, ps1)
    y1 = y + py * turn / gs
    z1 = None
    if z is not None:  # (None: not needed downstream)
        z1 = z + length * velocity_z_shift(pz, mu2) + (length - p * turn / gs)
    if none_true(small):  # every setting bends
        x, y, z, px = x1, y1, z1, px1
    else:  # a straight setting is a drift
        xd, yd, zd = exact_drift(x, px, y, py, z, pz, length, mu2)
        x = xd.where(small, x1)
        y = yd.where(small, y1)
        z = None if zd is None else zd.where(small, z1)
        px = px.where(small, px1)

    px, py = px + edge2[0] * x, py - edge2[1] * y
    return x, px, y, py, z, pz
