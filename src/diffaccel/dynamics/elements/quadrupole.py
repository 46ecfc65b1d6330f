"""Hard-edge quadrupole with a chromatic thick-lens body."""

from __future__ import annotations

import torch
from torch import Tensor

from diffaccel.dynamics._validate import as_p0c, check_nonnegative, check_particles
from diffaccel.dynamics.elements._kernels import (
    quad_body,
    quad_body_coefficients,
    to_element_frame,
    to_lab_frame,
)
from diffaccel.dynamics.elements.element import Element, bcast
from diffaccel.dynamics.species import ELECTRON, Species

__all__ = ["Quadrupole"]


class Quadrupole(Element):
    """Hard-edge quadrupole tracked with the exact chromatic thick-lens map.

    ``track`` gives each particle its own focusing ``k = k1 / (1 + pz)`` and uses
    ``x' = px / (1 + pz)`` (px is Px/P0). Approximation: the body is paraxial
    (linear in x, x', y, y' for each particle); ``z`` changes by
    ``L (beta/beta0 - 1) - 1/2 int (x'^2 + y'^2) ds`` (second order), as in Bmad's
    standard quadrupole tracking. No fringe fields. ``transfer_map`` is the linear
    map at ``pz = 0`` (no chromatic terms).

    Args:
        name: Element name.
        length: Magnetic length [m], shape ``()`` or ``(*K,)``; must be >= 0.
        k1: Normalised gradient g / (B rho) at ``p0c`` [1/m^2], shape ``()`` or
            ``(*K,)``; positive values focus in x for the design species.
            Pass an ``nn.Parameter`` to fit it.
        tilt: Roll about the beam axis [rad]; ``pi / 4`` makes a skew quadrupole.
        dx: Horizontal offset of the magnet [m].
        dy: Vertical offset of the magnet [m].

    Shapes:
        ``track``: ``(*K, N, 6) -> (*K, N, 6)``; ``transfer_map``: ``(*K, 6, 6)``.

    Raises:
        ValueError: if any ``length`` is negative or an attribute is not finite.

    Example:
        >>> quad = Quadrupole("Q1", length=0.1, k1=torch.linspace(-25.0, 15.0, 20))
        >>> quad.track(torch.zeros(1000, 6), p0c=43.36e6).shape
        torch.Size([20, 1000, 6])
    """

    param_names = ("length", "k1", "tilt", "dx", "dy")
    optional_params = ("tilt", "dx", "dy")

    def __init__(
        self,
        name: str,
        length: Tensor | float = 0.0,
        k1: Tensor | float = 0.0,
        tilt: Tensor | float = 0.0,
        dx: Tensor | float = 0.0,
        dy: Tensor | float = 0.0,
    ) -> None:
        super().__init__(name)
        for key, value in (
            ("length", length),
            ("k1", k1),
            ("tilt", tilt),
            ("dx", dx),
            ("dy", dy),
        ):
            self._set_param(key, value)
        check_nonnegative("length [m]", self.length, f"Quadrupole {name!r}")

    def track(
        self, particles: Tensor, p0c: Tensor | float, species: Species = ELECTRON
    ) -> Tensor:
        """Track particles through the quadrupole (see class docstring)."""
        check_particles(particles)
        p0c = as_p0c(p0c, particles)
        x, px, y, py, z, pz = particles.unbind(-1)
        length = bcast(self.length, particles)
        # Field polarity relative to the design species: k1 is defined for the
        # species being tracked, so no sign flip is applied here.
        k1 = bcast(self.k1, particles)
        tilt = bcast(self.tilt, particles)
        dx = bcast(self.dx, particles)
        dy = bcast(self.dy, particles)
        mu2 = bcast((species.mass_ev / p0c).square(), particles)
        x, px, y, py = to_element_frame(x, px, y, py, dx, dy, tilt)
        x, px, y, py, z = quad_body(x, px, y, py, z, pz, k1, length, mu2)
        x, px, y, py = to_lab_frame(x, px, y, py, dx, dy, tilt)
        return torch.stack(torch.broadcast_tensors(x, px, y, py, z, pz), dim=-1)

    def transfer_map(self, p0c: Tensor | float, species: Species = ELECTRON) -> Tensor:
        """Linear map at ``pz = 0`` about the magnet axis, shape ``(*K, 6, 6)``.

        Offsets ``dx, dy`` shift the orbit (a zeroth-order term) and do not enter
        this matrix; ``tilt`` rotates it.
        """
        length, k1, tilt = torch.broadcast_tensors(self.length, self.k1, self.tilt)
        p0c = as_p0c(p0c, length)
        length, k1, tilt, p0c = torch.broadcast_tensors(length, k1, tilt, p0c)
        cx, sx, dcx = quad_body_coefficients(k1, length)
        cy, sy, dcy = quad_body_coefficients(-k1, length)
        mu2 = (species.mass_ev / p0c).square()
        r = length.new_zeros(*length.shape, 6, 6)
        r[..., 0, 0], r[..., 0, 1], r[..., 1, 0], r[..., 1, 1] = cx, sx, dcx, cx
        r[..., 2, 2], r[..., 2, 3], r[..., 3, 2], r[..., 3, 3] = cy, sy, dcy, cy
        r[..., 4, 4] = 1.0
        r[..., 4, 5] = length * mu2 / (1.0 + mu2)
        r[..., 5, 5] = 1.0
        c, s = tilt.cos(), tilt.sin()
        rot = torch.eye(6, dtype=r.dtype, device=r.device).expand_as(r).clone()
        for i in (0, 1):
            rot[..., i, i] = c
            rot[..., i, i + 2] = s
            rot[..., i + 2, i] = -s
            rot[..., i + 2, i + 2] = c
        return rot.transpose(-1, -2) @ r @ rot
