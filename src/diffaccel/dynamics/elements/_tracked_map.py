"""First-order maps of elements by differentiating their tracking (private)."""

from __future__ import annotations

import torch
from torch import Tensor

from diffaccel.dynamics._validate import as_p0c, broadcast_shapes
from diffaccel.dynamics.species import Species

__all__ = ["tracked_affine_map"]


def tracked_affine_map(element, p0c: Tensor | float, species: Species) -> Tensor:
    """Affine map ``(*K, 7, 7)`` of ``element.track_columns`` about ``u = 0``.

    The offset column is where the reference particle (``u = 0``) ends up; the
    linear part is the Jacobian there, from six reverse-mode passes (one per
    output coordinate; the ``K`` settings are independent, so each pass gives
    that row for all of them). When a parameter (or ``p0c``) requires grad the
    graph is kept, so the map is differentiable in it; otherwise the map is
    detached. Computed in the dtype of ``element.length``.
    """
    p0c = as_p0c(p0c, element.length)
    shape = broadcast_shapes(element.batch_shape, p0c.shape)
    u = torch.zeros(
        *shape, 1, 6, dtype=p0c.dtype, device=p0c.device, requires_grad=True
    )
    graph = p0c.requires_grad or any(t.requires_grad for t in element.params().values())
    with torch.enable_grad():
        out = element.track_columns(tuple(u.unbind(-1)), p0c.expand(shape), species)
        rows = []
        for col in out:
            col = col.expand(*shape, 1)
            if not col.requires_grad:
                rows.append(torch.zeros_like(u))
                continue
            (g,) = torch.autograd.grad(
                col.sum(), u, retain_graph=True, create_graph=graph, allow_unused=True
            )
            rows.append(torch.zeros_like(u) if g is None else g)
    jac = torch.stack([g[..., 0, :] for g in rows], dim=-2)  # (*K, 6, 6)
    offset = torch.stack([c.expand(*shape, 1)[..., 0] for c in out], dim=-1)
    top = torch.cat([jac, offset.unsqueeze(-1)], dim=-1)  # (*K, 6, 7)
    unit = torch.zeros(7, dtype=p0c.dtype, device=p0c.device)
    unit[6] = 1.0
    out = torch.cat([top, unit.expand(*shape, 1, 7)], dim=-2)
    return out if graph else out.detach()
