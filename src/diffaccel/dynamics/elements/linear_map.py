"""A user-given (or linearised) 6x6 transfer map."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from diffaccel.dynamics._validate import broadcast_shapes, check_nonnegative
from diffaccel.dynamics.elements.element import Coords, Element
from diffaccel.dynamics.species import ELECTRON, Species

__all__ = ["LinearMap"]


class LinearMap(Element):
    """Affine map ``u_out = R u_in + c`` on Bmad coordinates about ``p0c``.

    Built by hand or by ``Beamline.linearized`` (the linear fidelity of a lattice:
    one matrix product per particle, the fast path for scans where it is exact,
    see ``Beamline.linear_map_is_exact``). The map is taken as given for the
    ``p0c`` it was made for; ``p0c`` passed to ``track`` is not used.

    Args:
        name: Element name.
        matrix: ``(*K, 7, 7)`` affine map ``[[R, c], [0, 1]]`` (``c`` the offset
            [m, rad, m, rad, m, 1]), or a plain ``(*K, 6, 6)`` matrix ``R``
            (offset zero), stored as the affine ``(*K, 7, 7)``. The last row of
            a 7x7 map is not used (taken as ``(0, ..., 0, 1)``).
        length: Length [m] the map spans (bookkeeping only), >= 0.

    Shapes:
        ``track``: ``(*K, N, 6) -> (*K, N, 6)``; ``transfer_map``: ``(*K, 7, 7)``.

    Raises:
        ValueError: if ``matrix`` is not shaped ``(*K, 6, 6)`` or ``(*K, 7, 7)``.

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
        m = self.matrix
        shape = tuple(m.shape)
        if m.dim() < 2 or shape[-2:] not in ((6, 6), (7, 7)):
            raise ValueError(
                f"LinearMap {name!r}: matrix must be shaped (*K, 6, 6) or (*K, 7, 7); "
                f"got {shape}."
            )
        if shape[-1] == 6:
            affine = m.new_zeros(*shape[:-2], 7, 7)
            affine[..., :6, :6] = m
            affine[..., 6, 6] = 1.0
            self._set_param(
                "matrix",
                nn.Parameter(affine) if isinstance(matrix, nn.Parameter) else affine,
            )
        self._set_param("length", length)
        check_nonnegative("length [m]", self.length, f"LinearMap {name!r}")

    @property
    def batch_shape(self) -> torch.Size:
        """Batch shape ``K`` of the matrix (and length)."""
        return broadcast_shapes(self.matrix.shape[:-2], self.length.shape)

    def track_columns(self, coords: Coords, p0c: Tensor, species: Species) -> Coords:
        """Unchecked column tracking (see :meth:`Element.track_columns`)."""
        # coordinates as rows (..., 6, N): the product gives contiguous columns
        rows = torch.stack(torch.broadcast_tensors(*coords), dim=-2)
        m = self.matrix.to(rows)
        out = m[..., :6, :6] @ rows + m[..., :6, 6:]
        return tuple(out.unbind(-2))  # type: ignore[return-value]

    def track_xy(self, coords: Coords) -> tuple[Tensor, Tensor]:
        """Only the output ``x, y`` of :meth:`track_columns` (rows 0 and 2).

        For unbatched columns ``(N,)`` each of ``x, y`` is one matrix product
        ``(K, 6) @ (6, N)`` over all settings plus the offset: no
        ``(*K, 6, N)`` intermediate, and the backward is two ``(6, K) @ (K, N)``
        products. ``x`` and ``y`` come out contiguous, shaped ``(*K, N)``.
        """
        rows = torch.stack(torch.broadcast_tensors(*coords), dim=-2)
        m = self.matrix.to(rows)
        sel = m[..., 0:3:2, :6]  # (*K, 2, 6)
        off = m[..., 0:3:2, 6]  # (*K, 2)
        if rows.dim() == 2:
            n = rows.shape[-1]
            batch = sel.shape[:-2]
            mx, my = sel.reshape(-1, 2, 6).unbind(-2)  # (K, 6) each
            ox, oy = off.reshape(-1, 2, 1).unbind(-2)  # (K, 1) each
            return (
                torch.addmm(ox, mx, rows).reshape(*batch, n),
                torch.addmm(oy, my, rows).reshape(*batch, n),
            )
        out = sel @ rows + off.unsqueeze(-1)  # (*K, 2, N)
        return out[..., 0, :], out[..., 1, :]

    def transfer_map(self, p0c: Tensor | float, species: Species = ELECTRON) -> Tensor:
        """The affine map, shape ``(*K, 7, 7)`` (last row ``(0, ..., 0, 1)``)."""
        m = self.matrix
        unit = torch.zeros(7, dtype=m.dtype, device=m.device)
        unit[6] = 1.0
        return torch.cat([m[..., :6, :], unit.expand(*m.shape[:-2], 1, 7)], -2)

    def linear_map_is_exact(self, monochromatic: bool) -> bool:
        """Always: tracking is this map."""
        return True
