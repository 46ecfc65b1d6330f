"""Preisach plane: hysteron thresholds on the half square ``0 <= beta <= alpha <= 1``.

Coordinates are *normalised* inputs: ``0`` is the lower end of the model's input
range and ``1`` its upper end. ``alpha`` is the up-switching threshold of a
hysteron (relay), ``beta`` its down-switching threshold.

A mesh may be regular in a *warped* coordinate ``t = warp(u)`` instead of in
``u`` itself (:func:`warp_input`): a piecewise-linear, strictly increasing map
of ``[0, 1]`` onto ``[0, 1]`` given by its knots ``(u_k, t_k)``. Where ``t``
rises fast, the mesh's thresholds lie close together in ``u``. A relay compares
its input with its thresholds, so a monotonic warp only moves thresholds: they
stay in ``u``, and the relays, saturation and streaming are those of any mesh.
"""

from __future__ import annotations

import itertools
import math

import torch
from torch import Tensor

from diffaccel.dynamics import is_integer

__all__ = [
    "MAX_CLI_MESH_SIZE",
    "PreisachMesh",
    "check_warp",
    "unwarp_input",
    "warp_input",
]

#: Largest ``n`` of :meth:`PreisachMesh.triangular` the command line accepts:
#: ``n (n + 1) / 2`` hysterons, 125,250 for 500 (memory grows with it; a typo
#: such as 100000 would ask for 5e9 and exhaust the memory before the first step).
MAX_CLI_MESH_SIZE = 500

_TRIANGLE_AREA = 0.5


Warp = tuple[tuple[float, ...], tuple[float, ...]]


def check_warp(warp) -> Warp | None:
    """A checked mesh warp ``(u_knots, t_knots)`` [1] or ``None``.

    Raises:
        ValueError: unless both are equally long (>= 2) sequences of finite
            numbers, strictly increasing, from 0 to 1.
    """
    if warp is None:
        return None
    try:
        uk, tk = (tuple(float(v) for v in part) for part in warp)
    except (TypeError, ValueError):
        raise ValueError(
            f"mesh warp must be two sequences of knots (u, t); got {warp!r:.80}."
        ) from None
    ok = len(uk) == len(tk) >= 2 and all(map(math.isfinite, uk + tk))
    ok = ok and all(b > a for a, b in itertools.pairwise(uk))
    ok = ok and all(b > a for a, b in itertools.pairwise(tk))
    ok = ok and uk[0] == tk[0] == 0.0 and uk[-1] == tk[-1] == 1.0
    if not ok:
        raise ValueError(
            "mesh warp needs equally long, strictly increasing knots u and t "
            "from 0 to 1 (normalised input units)."
        )
    return (uk, tk)


def _interp(x: Tensor, xp: tuple[float, ...], fp: tuple[float, ...]) -> Tensor:
    """Piecewise-linear interpolation of ``(xp, fp)`` at ``x`` (extrapolated)."""
    xk = torch.tensor(xp, dtype=x.dtype, device=x.device)
    fk = torch.tensor(fp, dtype=x.dtype, device=x.device)
    i = torch.searchsorted(xk, x.detach().contiguous()).clamp(1, xk.numel() - 1)
    x0, x1, f0, f1 = xk[i - 1], xk[i], fk[i - 1], fk[i]
    return f0 + (x - x0) * (f1 - f0) / (x1 - x0)


def warp_input(u: Tensor, warp: Warp | None) -> Tensor:
    """Warped coordinate ``t`` [1] of normalised inputs ``u`` [1] (any shape).

    ``warp = (u_knots, t_knots)``; ``None`` is the identity.
    """
    return u if warp is None else _interp(u, warp[0], warp[1])


def unwarp_input(t: Tensor, warp: Warp | None) -> Tensor:
    """Inverse of :func:`warp_input`: normalised inputs [1] of warped ones [1]."""
    return t if warp is None else _interp(t, warp[1], warp[0])


class PreisachMesh:
    """Hysteron positions and area weights on the normalised Preisach half square.

    Each mesh point stands for the patch of the plane closest to it; ``area`` is
    the area of that patch, so a density sampled at the points integrates as
    ``sum(area * density)`` whatever the point spacing. A mesh is immutable;
    ``to`` returns a new one.

    Args:
        alpha: Up-switching thresholds in normalised input units [1], shape ``(M,)``.
        beta: Down-switching thresholds in normalised input units [1], shape
            ``(M,)``, with ``beta <= alpha``.
        area: Area of the Preisach-plane patch of each point [1], shape ``(M,)``,
            positive. ``None`` gives every point the same share of the half
            square (area ``0.5 / M``).

    Shapes:
        ``alpha``, ``beta``, ``area``: ``(M,)``.

    Raises:
        ValueError: on mismatched shapes, non-finite values, points outside
            ``0 <= beta <= alpha <= 1`` or non-positive areas.

    Example:
        >>> mesh = PreisachMesh.triangular(n=10)
        >>> len(mesh), float(mesh.area.sum())
        (55, 0.5)
    """

    def __init__(self, alpha: Tensor, beta: Tensor, area: Tensor | None = None) -> None:
        alpha = torch.as_tensor(alpha)
        if not alpha.is_floating_point():
            alpha = alpha.to(torch.get_default_dtype())
        beta = torch.as_tensor(beta, dtype=alpha.dtype, device=alpha.device)
        if alpha.ndim != 1 or beta.shape != alpha.shape:
            raise ValueError(
                "PreisachMesh needs alpha and beta of equal shape (M,); got "
                f"{tuple(alpha.shape)} and {tuple(beta.shape)}."
            )
        if alpha.numel() < 1:
            raise ValueError("PreisachMesh needs at least one point; got M = 0.")
        if area is None:
            area = torch.full_like(alpha, _TRIANGLE_AREA / alpha.numel())
        area = torch.as_tensor(area, dtype=alpha.dtype, device=alpha.device)
        if area.shape != alpha.shape:
            raise ValueError(
                f"PreisachMesh area must have shape {tuple(alpha.shape)}; "
                f"got {tuple(area.shape)}."
            )
        for name, t in (("alpha", alpha), ("beta", beta), ("area", area)):
            if not torch.isfinite(t).all():
                raise ValueError(
                    f"PreisachMesh {name} contains NaN or infinite values."
                )
        tol = 1e-12
        if (beta > alpha + tol).any():
            bad = int((beta > alpha + tol).sum())
            raise ValueError(
                f"PreisachMesh points need beta <= alpha; {bad} points have "
                "beta > alpha."
            )
        if (beta < -tol).any() or (alpha > 1 + tol).any():
            raise ValueError(
                "PreisachMesh points must lie in the normalised range [0, 1]; got "
                f"beta min {float(beta.min()):.4g}, alpha max {float(alpha.max()):.4g}."
            )
        if (area <= 0).any():
            raise ValueError("PreisachMesh areas must be positive.")
        self._alpha = alpha
        self._beta = beta
        self._area = area

    @property
    def alpha(self) -> Tensor:
        """Up-switching thresholds [1], shape ``(M,)``."""
        return self._alpha

    @property
    def beta(self) -> Tensor:
        """Down-switching thresholds [1], shape ``(M,)``."""
        return self._beta

    @property
    def area(self) -> Tensor:
        """Patch areas [1], shape ``(M,)``; they sum to 0.5 for a full mesh."""
        return self._area

    def __len__(self) -> int:
        return self._alpha.numel()

    def __repr__(self) -> str:
        return f"PreisachMesh(M={len(self)}, dtype={self._alpha.dtype})"

    def to(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> PreisachMesh:
        """Return a copy on ``device`` with floating ``dtype``."""
        return PreisachMesh(
            self._alpha.to(device=device, dtype=dtype),
            self._beta.to(device=device, dtype=dtype),
            self._area.to(device=device, dtype=dtype),
        )

    def mirror_index(self, tol: float = 1e-9) -> Tensor:
        """Index of each point's mirror image about the anti-diagonal.

        The mirror of ``(alpha, beta)`` is ``(1 - beta, 1 - alpha)``: the point
        that a density symmetric about the centre of the input range,
        ``mu(alpha, beta) = mu(1 - beta, 1 - alpha)``, ties to it. Triangular
        meshes (refined or not) are mirror symmetric.

        Args:
            tol: Largest distance [1] between a mirrored point and the mesh
                point taken as its image.

        Returns:
            Long indices, shape ``(M,)``; ``mirror[mirror]`` is ``arange(M)``.

        Raises:
            ValueError: if some mirrored point has no mesh point within ``tol``
                or mirrored points share an image with unequal areas.
        """
        a, b = self._alpha.double(), self._beta.double()
        pts = torch.stack([a, b], dim=1)
        images = torch.stack([1.0 - b, 1.0 - a], dim=1)
        dist = torch.cdist(images, pts, compute_mode="donot_use_mm_for_euclid_dist")
        best, index = dist.min(dim=1)
        if (best > tol).any() or not torch.equal(
            index[index], torch.arange(len(self), device=index.device)
        ):
            bad = int((best > tol).sum())
            raise ValueError(
                f"mesh is not symmetric about the anti-diagonal alpha + beta = 1: "
                f"{bad} of {len(self)} points have no mirror image; use "
                "PreisachMesh.triangular for a symmetric density."
            )
        if not torch.allclose(self._area[index], self._area, rtol=1e-9, atol=0.0):
            raise ValueError(
                "mesh points and their mirror images have different areas; "
                "a symmetric density needs a mirror-symmetric mesh."
            )
        return index

    @classmethod
    def triangular(
        cls,
        n: int = 40,
        refine: int = 0,
        band: int = 1,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
        warp: Warp | None = None,
    ) -> PreisachMesh:
        """Regular mesh of ``n`` x ``n`` square cells clipped to ``beta <= alpha``.

        Cells below the diagonal get one point at their centre (area ``h**2``,
        ``h = 1 / n``); cells cut by the diagonal keep their lower-right
        triangle, represented by its centroid (area ``h**2 / 2``). The areas sum
        to exactly 0.5. With ``refine > 0`` every cell within ``band`` cells of
        the diagonal is split recursively ``refine`` times into 2 x 2 sub-cells,
        so that the narrow hysterons that shape the loop near turning points are
        resolved more finely.

        With ``warp`` the mesh is regular in the warped coordinate ``t`` of
        :func:`warp_input` and its points are mapped back to normalised
        inputs, ``alpha = unwarp_input(t_alpha)`` (likewise ``beta``); the areas
        are those of the regular mesh in ``t`` (they sum to 0.5), so that equal
        areas mean equal shares of the warped plane. A warp with ``t(1 - u) =
        1 - t(u)`` keeps the mesh mirror symmetric.

        Args:
            n: Cells per axis (>= 1); ``n * (n + 1) / 2`` points without
                refinement (n = 44: 990, n = 100: 5050, n = 200: 20100).
            refine: Levels of 2 x 2 splitting near the diagonal (>= 0).
            band: Width of the refined band in coarse cells (>= 1).
            dtype: Floating dtype of the coordinates.
            device: Device of the coordinates.
            warp: Knots ``(u, t)`` of :func:`warp_input` [1], or ``None``
                (regular in the normalised input).

        Returns:
            The mesh.

        Raises:
            ValueError: if ``n``, ``refine`` or ``band`` is not an int, or
                ``n < 1``, ``refine < 0`` or ``band < 1``, or for a bad warp.
        """
        warp = check_warp(warp)
        for name, v in (("n", n), ("refine", refine), ("band", band)):
            if not is_integer(v):
                raise ValueError(
                    f"triangular mesh needs an int {name}; got {v!r} "
                    f"({type(v).__name__})."
                )
        n, refine, band = int(n), int(refine), int(band)
        if n < 1:
            raise ValueError(f"triangular mesh needs n >= 1 cells per axis; got {n}.")
        if refine < 0 or band < 1:
            raise ValueError(
                "triangular mesh needs refine >= 0 and band >= 1; got "
                f"{refine}, {band}."
            )
        h = 1.0 / n
        i = torch.arange(n, dtype=torch.float64)
        ia, ib = torch.meshgrid(i, i, indexing="ij")  # alpha row, beta column
        lower = ib < ia
        coarse = (ia - ib >= band) if refine > 0 else lower
        alphas = [(ia[coarse] + 0.5) * h]
        betas = [(ib[coarse] + 0.5) * h]
        areas = [torch.full((int(coarse.sum()),), h * h, dtype=torch.float64)]
        if refine == 0:
            d = i
            alphas.append((d + 2.0 / 3.0) * h)
            betas.append((d + 1.0 / 3.0) * h)
            areas.append(torch.full((n,), h * h / 2, dtype=torch.float64))
        else:
            # refined band: off-diagonal cells and diagonal cells, split 2**refine
            k = 2**refine
            hs = h / k
            band_cells = lower & ~coarse
            a0 = ia[band_cells] * h
            b0 = ib[band_cells] * h
            j = torch.arange(k, dtype=torch.float64)
            ja, jb = torch.meshgrid(j, j, indexing="ij")
            alphas.append((a0[:, None] + (ja.flatten() + 0.5) * hs).flatten())
            betas.append((b0[:, None] + (jb.flatten() + 0.5) * hs).flatten())
            areas.append(
                torch.full((alphas[-1].numel(),), hs * hs, dtype=torch.float64)
            )
            sub = cls.triangular(k, dtype=torch.float64)
            d0 = i * h
            alphas.append((d0[:, None] + sub.alpha[None, :] * h).flatten())
            betas.append((d0[:, None] + sub.beta[None, :] * h).flatten())
            areas.append((sub.area[None, :] * h * h).expand(n, -1).flatten())
        alpha = torch.cat(alphas)
        beta = torch.cat(betas)
        area = torch.cat(areas)
        if not math.isclose(float(area.sum()), _TRIANGLE_AREA, rel_tol=1e-9):
            raise RuntimeError(
                "internal error: triangular mesh areas do not sum to 0.5"
            )
        if warp is not None:
            alpha = unwarp_input(alpha, warp).clamp(0.0, 1.0)
            beta = torch.minimum(unwarp_input(beta, warp).clamp(0.0, 1.0), alpha)
        return cls(
            alpha.to(device=device, dtype=dtype),
            beta.to(device=device, dtype=dtype),
            area.to(device=device, dtype=dtype),
        )

    @classmethod
    def from_points(
        cls, alpha: Tensor, beta: Tensor, area: Tensor | None = None
    ) -> PreisachMesh:
        """Mesh from user points; same as the constructor (equal areas if ``None``)."""
        return cls(alpha, beta, area)
