"""Hard-edge quadrupole with a chromatic thick-lens body."""

from __future__ import annotations

import torch
from torch import Tensor

from diffaccel.dynamics._validate import as_p0c, check_nonnegative
from diffaccel.dynamics.elements._kernels import (
    focusing_functions,
    is_zero,
    quad_body,
    roll_matrix,
    to_element_frame,
    to_lab_frame,
)
from diffaccel.dynamics.elements.element import Coords, Element, bcast
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
        """Track particles ``(*K, N, 6)`` through the quadrupole (see class docs)."""
        return self._track_via_columns(particles, p0c, species)

    def track_columns(self, coords: Coords, p0c: Tensor, species: Species) -> Coords:
        """Unchecked column tracking (see :meth:`Element.track_columns`)."""
        x, px, y, py, z, pz = coords
        length = bcast(self.length, x)
        k1 = bcast(self.k1, x)
        mu2 = (species.mass_ev / p0c).square().unsqueeze(-1)
        rolled = not (is_zero(self.tilt) and is_zero(self.dx) and is_zero(self.dy))
        if rolled:
            frame = (bcast(self.dx, x), bcast(self.dy, x), bcast(self.tilt, x))
            x, px, y, py = to_element_frame(x, px, y, py, *frame)
        x, px, y, py, z = quad_body((x, px, y, py, z, pz), k1, length, mu2)
        if rolled:
            x, px, y, py = to_lab_frame(x, px, y, py, *frame)
        return x, px, y, py, z, pz

    def transfer_map(self, p0c: Tensor | float, species: Species = ELECTRON) -> Tensor:
        """Linear map at ``pz = 0`` about the magnet axis, shape ``(*K, 6, 6)``.

        Offsets ``dx, dy`` shift the orbit (a zeroth-order term) and do not enter
        this matrix; ``tilt`` rotates it.
        """
        p0c = as_p0c(p0c, self.length)
        length, k1, tilt, p0c = torch.broadcast_tensors(
            self.length, self.k1.to(p0c), self.tilt.to(p0c), p0c
        )
        c_x, s_x, c_y, s_y = focusing_functions(k1 * length.square())
        s_x, s_y = s_x * length, s_y * length
        mu2 = (species.mass_ev / p0c).square()
        r = length.new_zeros(*length.shape, 6, 6)
        r[..., 0, 0], r[..., 0, 1], r[..., 1, 0], r[..., 1, 1] = (
            c_x,
            s_x,
            -k1 * s_x,
            c_x,
        )
        r[..., 2, 2], r[..., 2, 3], r[..., 3, 2], r[..., 3, 3] = c_y, s_y, k1 * s_y, c_y
        r[..., 4, 4] = 1.0
        r[..., 4, 5] = length * mu2 / (1.0 + mu2)
        r[..., 5, 5] = 1.0
        rot = roll_matrix(tilt)
        return rot.transpose(-1, -2) @ r @ rot
