"""Hard-edge quadrupole with a chromatic thick-lens body."""

from __future__ import annotations

import torch
from torch import Tensor

from diffaccel.dynamics.elements._kernels import (
    affine_identity,
    focusing_functions,
    is_zero,
    lab_frame_map,
    quad_body,
    sinc_derivative,
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
    standard quadrupole tracking. No fringe fields. ``transfer_map`` is the exact
    first-order (affine) map about the reference orbit: offsets ``dx, dy`` move
    the orbit (a dipole kick) and give it dispersion; for ``pz = 0`` particles it
    reproduces ``track`` in ``x, px, y, py`` exactly.

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
        ``track``: ``(*K, N, 6) -> (*K, N, 6)``; ``transfer_map``: ``(*K, 7, 7)``.

    Raises:
        ValueError: if any ``length`` is negative or an attribute is not finite.

    Example:
        >>> quad = Quadrupole("Q1", length=0.1, k1=torch.linspace(-25.0, 15.0, 20))
        >>> quad.track(torch.zeros(1000, 6), p0c=43.36e6).shape
        torch.Size([20, 1000, 6])
    """

    param_names = ("length", "k1", "tilt", "dx", "dy")
    reads_z = False
    optional_params = ("tilt", "dx", "dy")
    nonnegative_params = (("length", "m"),)

    def __init__(
        self,
        name: str,
        length: Tensor | float = 0.0,
        k1: Tensor | float = 0.0,
        tilt: Tensor | float = 0.0,
        dx: Tensor | float = 0.0,
        dy: Tensor | float = 0.0,
    ) -> None:
        super().__init__(name, length=length, k1=k1, tilt=tilt, dx=dx, dy=dy)

    def track_columns(self, coords: Coords, p0c: Tensor, species: Species) -> Coords:
        """Unchecked column tracking (see :meth:`Element.track_columns`)."""
        x = coords[0]
        length = bcast(self.length, x)
        k1 = bcast(self.k1, x)
        mu2 = (species.mass_ev / p0c).square().unsqueeze(-1)

        def body(c: Coords) -> Coords:
            return (*quad_body(c, k1, length, mu2), c[5])

        return self._in_element_frame(coords, body)

    def transfer_map(self, p0c: Tensor | float, species: Species = ELECTRON) -> Tensor:
        """Affine first-order map about the reference orbit, shape ``(*K, 7, 7)``.

        The Jacobian of :meth:`track` at the reference particle (``u = 0``) and
        where that particle ends up. In the magnet frame the reference particle
        sits at ``(x0, y0) = roll(-dx, -dy)``, where the body is expanded: the
        transverse block is the thick-lens matrix, the ``pz`` column gets the
        dispersion of the off-axis orbit (``dC/dpz x0`` etc.), the ``z`` row the
        gradient of the path-length term.
        """
        length, k1, tilt, dx, dy, p0c = self._map_params(p0c, *self.param_names)
        mu2 = (species.mass_ev / p0c).square()
        u = k1 * length.square()
        c_x, s_x, c_y, s_y = focusing_functions(u)
        ds_x = sinc_derivative(u, c_x, s_x)  # d s(u) / du
        ds_y = sinc_derivative(-u, c_y, s_y)  # d s(v) / dv at v = -u
        big_sx, big_sy = s_x * length, s_y * length
        l3 = length * length.square()
        ct, st = tilt.cos(), tilt.sin()
        x0 = -(ct * dx + st * dy)  # reference particle in the magnet frame
        y0 = -(ct * dy - st * dx)
        zero = torch.zeros_like(x0)
        # where the reference particle ends up (magnet frame): the body itself
        xe, pxe, ye, pye, ze = quad_body(
            (x0, zero, y0, zero, zero, zero), k1, length, mu2
        )
        gx = length - c_x * big_sx  # d i_x / dx = k x0 gx (i_x: int x'^2 ds)
        gy = length - c_y * big_sy
        r = affine_identity(length.shape, length)
        r[..., 0, 0], r[..., 0, 1] = c_x, big_sx
        r[..., 1, 0], r[..., 1, 1] = -k1 * big_sx, c_x
        r[..., 2, 2], r[..., 2, 3] = c_y, big_sy
        r[..., 3, 2], r[..., 3, 3] = k1 * big_sy, c_y
        # chromatic terms of the off-axis orbit: k = k1 / (1 + pz)
        r[..., 0, 5] = 0.5 * k1 * length * big_sx * x0
        r[..., 1, 5] = k1.square() * l3 * ds_x * x0
        r[..., 2, 5] = -0.5 * k1 * length * big_sy * y0
        r[..., 3, 5] = k1.square() * l3 * ds_y * y0
        # z = z + L (beta/beta0 - 1) - (i_x + i_y) / 2, expanded about (x0, y0)
        r[..., 4, 0] = -0.5 * k1 * x0 * gx
        r[..., 4, 1] = 0.5 * k1 * x0 * big_sx.square()
        r[..., 4, 2] = 0.5 * k1 * y0 * gy
        r[..., 4, 3] = -0.5 * k1 * y0 * big_sy.square()
        di_x = (
            -0.5
            * k1
            * x0.square()
            * (gx + k1 * (0.5 * length * big_sx.square() - c_x * l3 * ds_x))
        )
        di_y = (
            0.5
            * k1
            * y0.square()
            * (gy + k1 * (c_y * l3 * ds_y - 0.5 * length * big_sy.square()))
        )
        r[..., 4, 5] = length * mu2 / (1.0 + mu2) - 0.5 * (di_x + di_y)
        r[..., 0, 6], r[..., 1, 6], r[..., 2, 6] = xe, pxe, ye
        r[..., 3, 6], r[..., 4, 6] = pye, ze
        return lab_frame_map(r, tilt, dx, dy)

    def linear_map_is_exact(self, monochromatic: bool) -> bool:
        """Exact for ``pz = 0`` beams, offsets included (chromatic otherwise)."""
        return monochromatic or is_zero(self.length)
