"""Hard-edge solenoid (Bmad's body map, canonical momenta)."""

from __future__ import annotations

import torch
from torch import Tensor

from diffaccel.dynamics.elements._kernels import velocity_z_shift
from diffaccel.dynamics.elements._tracked_map import tracked_affine_map
from diffaccel.dynamics.elements.element import Coords, Element, bcast
from diffaccel.dynamics.species import ELECTRON, Species

__all__ = ["Solenoid"]


class Solenoid(Element):
    """Hard-edge solenoid tracked with Bmad's solenoid map.

    Bmad conventions: ``ks = B_s / (B rho)`` [1/m] at ``p0c``; ``px, py`` are
    canonical (``Px / P0`` including the vector potential), so the hard-edge
    fringe needs no separate kick. With ``kappa = ks / 2``, the mechanical
    momenta ``px + kappa y`` and ``py - kappa x`` set the particle's
    longitudinal momentum ``ps`` (exact, not paraxial), which is constant in the
    body; the transverse motion is the rotation-and-focusing map with angle
    ``theta = kappa L / ps``::

        x'  = C^2 x + C S / kappa px + C S y + S^2 / kappa py
        px' = -kappa C S x + C^2 px - kappa S^2 y + C S py
        y'  = -C S x - S^2 / kappa px + C^2 y + C S / kappa py
        py' = kappa S^2 x - C S px - kappa C S y + C^2 py

    (``C = cos theta``, ``S = sin theta``), and
    ``z += L (beta / beta0 - (1 + pz) / ps)``. cheetah 0.8.4's ``Solenoid`` is
    this map's linear part at ``pz = 0`` (its ``k`` is ``ks / 2``; it has no
    chromatic or path-length terms).

    Args:
        name: Element name.
        length: Length [m], >= 0.
        ks: Solenoid strength ``B_s / (B rho)`` [1/m]; positive rotates a
            particle's ``(x, y)`` from ``+x`` towards ``-y`` as above.
        dx: Horizontal offset of the magnet [m].
        dy: Vertical offset of the magnet [m].

    Shapes:
        ``track``: ``(*K, N, 6) -> (*K, N, 6)``; ``transfer_map``: ``(*K, 7, 7)``.

    Example:
        >>> sol = Solenoid("S1", length=0.2, ks=2.0)
        >>> sol.transfer_map(1e9).shape
        torch.Size([7, 7])
    """

    param_names = ("length", "ks", "dx", "dy")
    optional_params = ("dx", "dy")
    nonnegative_params = (("length", "m"),)
    reads_z = False

    def __init__(
        self,
        name: str,
        length: Tensor | float = 0.0,
        ks: Tensor | float = 0.0,
        dx: Tensor | float = 0.0,
        dy: Tensor | float = 0.0,
    ) -> None:
        super().__init__(name, length=length, ks=ks, dx=dx, dy=dy)

    def track_columns(self, coords: Coords, p0c: Tensor, species: Species) -> Coords:
        """Unchecked column tracking (see :meth:`Element.track_columns`)."""
        like = coords[0]
        length = bcast(self.length, like)
        kappa = bcast(self.ks, like) / 2
        mu2 = (species.mass_ev / p0c).square().unsqueeze(-1)
        return self._in_element_frame(
            coords, lambda c: _solenoid_body(c, kappa, length, mu2)
        )

    def transfer_map(self, p0c: Tensor | float, species: Species = ELECTRON) -> Tensor:
        """Affine map about the reference orbit, shape ``(*K, 7, 7)``.

        The Jacobian of :meth:`track` at ``u = 0`` (by differentiation) and where
        that particle ends up (an offset solenoid kicks the reference orbit).
        """
        return tracked_affine_map(self, p0c, species)

    def linear_map_is_exact(self, monochromatic: bool) -> bool:
        """As a drift: exact for ``pz = 0`` beams up to the paraxial terms."""
        return monochromatic or bool((self.length.detach() == 0).all())


def _solenoid_body(
    coords: Coords, kappa: Tensor, length: Tensor, mu2: Tensor
) -> Coords:
    """Body map in the magnet frame (``kappa = ks / 2``)."""
    x, px, y, py, z, pz = coords
    p = 1.0 + pz
    mx = px + kappa * y  # mechanical momenta / P0
    my = py - kappa * x
    pt2 = mx.square() + my.square()
    ps = (p.square() - pt2).sqrt()
    lps = length / ps
    theta = kappa * lps
    c, s = theta.cos(), theta.sin()
    sinc = torch.sinc(theta / torch.pi)  # sin(theta) / theta, smooth at 0
    cs_k = lps * c * sinc  # C S / kappa
    s2_k = lps * s * sinc  # S^2 / kappa
    c2, s2, cs = c.square(), s.square(), c * s
    x_new = c2 * x + cs_k * px + cs * y + s2_k * py
    px_new = -kappa * cs * x + c2 * px - kappa * s2 * y + cs * py
    y_new = -cs * x - s2_k * px + c2 * y + cs_k * py
    py_new = kappa * s2 * x - cs * px - kappa * cs * y + c2 * py
    if z is not None:
        # beta / beta0 - p / ps, with p / ps - 1 = pt2 / (ps (p + ps))
        z = z + length * velocity_z_shift(pz, mu2) - lps * pt2 / (p + ps)
    return x_new, px_new, y_new, py_new, z, pz
