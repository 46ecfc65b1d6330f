"""A user-given (or linearised) 6x6 transfer map."""

from __future__ import annotations

import torch
from torch import Tensor

from diffaccel.dynamics._validate import check_nonnegative
from diffaccel.dynamics.elements.element import Coords, Element
from diffaccel.dynamics.species import ELECTRON, Species

__all__ = ["LinearMap"]


class LinearMap(Element):
    """Linear 6x6 map ``u_out = R u_in`` on Bmad coordinates about ``p0c``.

    Built by hand or by ``Beamline.linearized`` (the linear fidelity of a lattice:
    one matrix product per particle, the fast path for quad scans where chromatic
    terms do not matter). The map is taken as given for the ``p0c`` it was made
    for; ``p0c`` passed to ``track`` is not used.

    Args:
        name: Element name.
        matrix: Transfer matrix ``R``, shape ``(*K, 6, 6)`` (dimensionless and
            metres per unit of momentum as usual for Bmad coordinates).
        length: Length [m] the map spans (bookkeeping only), >= 0.

    Shapes:
        ``track``: ``(*K, N, 6) -> (*K, N, 6)``; ``transfer_map``: ``(*K, 6, 6)``.

    Example:
        >>> m = LinearMap("M", torch.eye(6))
        >>> m.track(torch.ones(3, 6), p0c=1e9).sum().item()
        18.0
    """

    param_names = ("matrix", "length")
    optional_params = ("length",)

    def __init__(
        self, name: str, matrix: Tensor | list, length: Tensor | float = 0.0
    ) -> None:
        super().__init__(name)
        self._set_param("matrix", matrix)
        if self.matrix.dim() < 2 or self.matrix.shape[-2:] != (6, 6):
            raise ValueError(
                f"LinearMap {name!r}: matrix must be shaped (*K, 6, 6); "
                f"got {tuple(self.matrix.shape)}."
            )
        self._set_param("length", length)
        check_nonnegative("length [m]", self.length, f"LinearMap {name!r}")

    @property
    def batch_shape(self) -> torch.Size:
        """Batch shape ``K`` of the matrix (and length)."""
        return torch.broadcast_shapes(self.matrix.shape[:-2], self.length.shape)

    def track(
        self, particles: Tensor, p0c: Tensor | float, species: Species = ELECTRON
    ) -> Tensor:
        """Apply the matrix to particles ``(*K, N, 6)``."""
        return self._track_via_columns(particles, p0c, species)

    def track_columns(self, coords: Coords, p0c: Tensor, species: Species) -> Coords:
        """Unchecked column tracking (see :meth:`Element.track_columns`)."""
        # coordinates as rows (..., 6, N): the product gives contiguous columns
        rows = torch.stack(torch.broadcast_tensors(*coords), dim=-2)
        return tuple((self.matrix.to(rows) @ rows).unbind(-2))  # type: ignore[return-value]

    def track_xy(self, coords: Coords) -> tuple[Tensor, Tensor]:
        """Only the output ``x, y`` of :meth:`track_columns` (rows 0 and 2 of R).

        For unbatched columns ``(N,)`` each of ``x, y`` is one matrix product
        ``(K, 6) @ (6, N)`` over all settings: no ``(*K, 6, N)`` intermediate,
        and the backward is two ``(6, K) @ (K, N)`` products. ``x`` and ``y``
        come out contiguous, shaped ``(*K, N)``.
        """
        rows = torch.stack(torch.broadcast_tensors(*coords), dim=-2)
        sel = self.matrix.to(rows)[..., 0:3:2, :]  # (*K, 2, 6)
        if rows.dim() == 2:
            n = rows.shape[-1]
            batch = sel.shape[:-2]
            mx, my = sel.reshape(-1, 2, 6).unbind(-2)  # (K, 6) each
            return (mx @ rows).reshape(*batch, n), (my @ rows).reshape(*batch, n)
        out = sel @ rows  # (*K, 2, N)
        return out[..., 0, :], out[..., 1, :]

    def transfer_map(self, p0c: Tensor | float, species: Species = ELECTRON) -> Tensor:
        """The matrix itself, shape ``(*K, 6, 6)``."""
        return self.matrix
