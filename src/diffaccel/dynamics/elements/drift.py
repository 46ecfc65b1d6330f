"""Field-free drift space."""

from __future__ import annotations

import torch
from torch import Tensor

from diffaccel.dynamics.elements._kernels import (
    affine_identity,
    exact_drift,
    is_zero,
)
from diffaccel.dynamics.elements.element import Coords, Element, bcast
from diffaccel.dynamics.species import ELECTRON, Species

__all__ = ["Drift", "drift_matrix"]


def drift_matrix(length: Tensor, p0c: Tensor, species: Species) -> Tensor:
    """Affine drift map ``(*K, 7, 7)``; ``R12 = R34 = L``, ``R56 = L / gamma0^2``."""
    length, p0c = torch.broadcast_tensors(length, p0c.to(length))
    r = affine_identity(length.shape, length)
    mu2 = (species.mass_ev / p0c).square()
    r[..., 0, 1] = length
    r[..., 2, 3] = length
    r[..., 4, 5] = length * mu2 / (1.0 + mu2)
    return r


class Drift(Element):
    """Field-free drift tracked with the exact (non-paraxial) map.

    ``x += L px / ps`` with ``ps = sqrt((1 + pz)^2 - px^2 - py^2)``, and
    ``z += L (beta / beta0 - (1 + pz) / ps)`` with the particle velocity ``beta``
    from the species mass (Bmad ``z = -beta c (t - t0)``).

    Args:
        name: Element name.
        length: Length [m], shape ``()`` or ``(*K,)``; must be >= 0.

    Shapes:
        ``track``: ``(*K, N, 6) -> (*K, N, 6)``; ``transfer_map``: ``(*K, 7, 7)``.

    Raises:
        ValueError: if any ``length`` is negative.

    Example:
        >>> d = Drift("D1", length=1.0)
        >>> p = torch.tensor([[1e-3, 1e-3, 0.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
        >>> round(d.track(p, p0c=1e9)[0, 0].item(), 12)  # x + L * px / ps
        0.0020000005
    """

    param_names = ("length",)
    reads_z = False
    nonnegative_params = (("length", "m"),)

    def __init__(self, name: str, length: Tensor | float = 0.0) -> None:
        super().__init__(name, length=length)

    def track_columns(self, coords: Coords, p0c: Tensor, species: Species) -> Coords:
        """Unchecked column tracking (see :meth:`Element.track_columns`)."""
        x, px, y, py, z, pz = coords
        length = bcast(self.length, x)
        mu2 = (species.mass_ev / p0c).square().unsqueeze(-1)
        x, y, z = exact_drift(x, px, y, py, z, pz, length, mu2)
        return x, px, y, py, z, pz

    def transfer_map(self, p0c: Tensor | float, species: Species = ELECTRON) -> Tensor:
        """Affine map about the reference orbit, shape ``(*K, 7, 7)``."""
        return drift_matrix(*self._map_params(p0c, "length"), species)

    def linear_map_is_exact(self, monochromatic: bool) -> bool:
        """Exact for ``pz = 0`` beams (or zero length); chromatic otherwise."""
        return monochromatic or is_zero(self.length)
