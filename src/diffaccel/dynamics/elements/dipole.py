"""Sector bending magnet with hard-edge entrance and exit faces."""

from __future__ import annotations

import torch
from torch import Tensor

from diffaccel.dynamics._validate import as_p0c, check_nonnegative
from diffaccel.dynamics.elements._kernels import (
    exact_drift,
    is_zero,
    roll_matrix,
    to_element_frame,
    to_lab_frame,
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
    linear kicks ``px += g tan(e) x``, ``py -= g tan(e) y`` (no fringe-field
    integral). Chromatic effects follow from the exact body. ``z`` follows Bmad:
    ``z += L beta/beta0 - (path length)``.

    Args:
        name: Element name.
        length: Arc length of the reference orbit [m], must be > 0 if ``angle``
            is non-zero.
        angle: Bending angle [rad].
        e1: Entrance pole-face angle [rad] (0 for a pure sector bend).
        e2: Exit pole-face angle [rad].
        tilt: Roll about the beam axis [rad]; ``pi / 2`` bends vertically.

    Shapes:
        ``track``: ``(*K, N, 6) -> (*K, N, 6)``; ``transfer_map``: ``(*K, 7, 7)``.

    Example:
        >>> b = Dipole("B1", length=0.5, angle=0.2, e1=0.1, e2=0.1)
        >>> b.transfer_map(1e9).shape
        torch.Size([7, 7])
    """

    param_names = ("length", "angle", "e1", "e2", "tilt")
    optional_params = ("e1", "e2", "tilt")

    def __init__(
        self,
        name: str,
        length: Tensor | float = 0.0,
        angle: Tensor | float = 0.0,
        e1: Tensor | float = 0.0,
        e2: Tensor | float = 0.0,
        tilt: Tensor | float = 0.0,
    ) -> None:
        super().__init__(name)
        for key, value in (
            ("length", length),
            ("angle", angle),
            ("e1", e1),
            ("e2", e2),
            ("tilt", tilt),
        ):
            self._set_param(key, value)
        owner = f"Dipole {name!r}"
        check_nonnegative("length [m]", self.length, owner)
        bad = (self.length.detach() == 0) & (self.angle.detach() != 0)
        if bool(bad.any()):
            raise ValueError(f"{owner}: a non-zero angle needs a length > 0 m.")

    def _curvature(self, like: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        length = self.length.to(like)
        angle = self.angle.to(like)
        safe_length = length.where(length > 0, torch.ones_like(length))
        return angle / safe_length, length, angle

    def track(
        self, particles: Tensor, p0c: Tensor | float, species: Species = ELECTRON
    ) -> Tensor:
        """Track particles ``(*K, N, 6)`` through the bend (see class docstring)."""
        return self._track_via_columns(particles, p0c, species)

    def track_columns(self, coords: Coords, p0c: Tensor, species: Species) -> Coords:
        """Unchecked column tracking (see :meth:`Element.track_columns`)."""
        x, px, y, py, z, pz = coords
        g, length, angle = self._curvature(x)
        g, length, angle = g.unsqueeze(-1), length.unsqueeze(-1), angle.unsqueeze(-1)
        h1 = g * bcast(self.e1, x).tan()
        h2 = g * bcast(self.e2, x).tan()
        mu2 = (species.mass_ev / p0c).square().unsqueeze(-1)
        rolled = not is_zero(self.tilt)
        if rolled:
            zero = x.new_zeros(())
            frame = (zero, zero, bcast(self.tilt, x))
            x, px, y, py = to_element_frame(x, px, y, py, *frame)
        px, py = px + h1 * x, py - h1 * y

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
        z1 = z + length * velocity_z_shift(pz, mu2) + (length - p * turn / gs)
        xd, yd, zd = exact_drift(x, px, y, py, z, pz, length, mu2)
        x = xd.where(small, x1)
        y = yd.where(small, y1)
        z = zd.where(small, z1)
        px = px.where(small, px1)

        px, py = px + h2 * x, py - h2 * y
        if rolled:
            x, px, y, py = to_lab_frame(x, px, y, py, *frame)
        return x, px, y, py, z, pz

    def transfer_map(self, p0c: Tensor | float, species: Species = ELECTRON) -> Tensor:
        """Affine first-order map with the edge kicks, shape ``(*K, 7, 7)``.

        The reference particle stays on the axis (zero offset column).
        """
        g, length, angle = self._curvature(self.length)
        g, length, angle, e1, e2, tilt = torch.broadcast_tensors(
            g, length, angle, self.e1.to(g), self.e2.to(g), self.tilt.to(g)
        )
        p0c = as_p0c(p0c, g)
        g, length, angle, e1, e2, tilt, p0c = torch.broadcast_tensors(
            g, length, angle, e1, e2, tilt, p0c
        )
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
        eye = torch.eye(7, dtype=r.dtype, device=r.device).expand_as(r)
        edge1 = eye.clone()
        edge1[..., 1, 0] = g * e1.tan()
        edge1[..., 3, 2] = -g * e1.tan()
        edge2 = eye.clone()
        edge2[..., 1, 0] = g * e2.tan()
        edge2[..., 3, 2] = -g * e2.tan()
        rot = roll_matrix(tilt)
        return rot.transpose(-1, -2) @ edge2 @ r @ edge1 @ rot

    def linear_map_is_exact(self, monochromatic: bool) -> bool:
        """Only when it does not bend (a drift); the exact body has ``g x^2`` terms."""
        return is_zero(self.length) or (monochromatic and is_zero(self.angle))
