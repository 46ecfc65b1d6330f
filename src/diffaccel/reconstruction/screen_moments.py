"""The moment design: the linear map from a beam's covariance to its screen moments.

At a setting with first-order map ``R`` the screen's second moments are
``(R Sigma R^T)`` restricted to (x, y): ``<xx> = a Sigma a^T``, ``<xy> = a Sigma
b^T``, ``<yy> = b Sigma b^T`` with ``a, b`` the x and y rows of ``R``. Stacked
over every setting of every scan this is one linear operator from the
upper-triangular entries of ``Sigma`` to the screen moments. It is the one
design behind the initial Gaussian
(:func:`~diffaccel.reconstruction.initial.fit_gaussian`), the unseen
directions and their prior term (:mod:`~diffaccel.reconstruction.unseen`), the
prior report
(:mod:`~diffaccel.reconstruction.prior_dependence`), the moment posterior
(:mod:`~diffaccel.reconstruction.uncertainty`) and the experiment design
(:mod:`~diffaccel.reconstruction.design`). It is exact to first order; the
tests check it against tracked particles and their images.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor


def pair_indices(dims: int | Sequence[int]) -> list[tuple[int, int]]:
    """Upper-triangular index pairs ``(i, j), i <= j`` of a ``dims x dims`` matrix,
    or of the coordinates ``dims`` (a sequence of indices) of a larger one.

    Example:
        >>> pair_indices(2)
        [(0, 0), (0, 1), (1, 1)]
        >>> pair_indices([0, 5])
        [(0, 0), (0, 5), (5, 5)]
    """
    coords = list(range(dims)) if isinstance(dims, int) else list(dims)
    return [(i, j) for n, i in enumerate(coords) for j in coords[n:]]


#: The 21 entries ``(i, j), i <= j`` of a 6D covariance, in the column order of
#: :func:`moment_design`.
ENTRIES = pair_indices(6)


def _sym_coeff(a: Tensor, b: Tensor, pairs: Sequence[tuple[int, int]]) -> Tensor:
    """Coefficients of ``a Sigma b^T`` in the entries ``pairs`` of Sigma.

    Shapes: ``a, b (K, 6)`` -> ``(K, P)``.
    """
    cols = []
    for i, j in pairs:
        if i == j:
            cols.append(a[:, i] * b[:, i])
        else:
            cols.append(a[:, i] * b[:, j] + a[:, j] * b[:, i])
    return torch.stack(cols, -1)


def covariance_design(maps: Tensor, dims: int | Sequence[int]) -> Tensor:
    """Linear operator from beam covariance to screen second moments.

    Args:
        maps: First-order transfer matrices to the screen ``(K, 6, 6)`` (or
            affine ``(K, 7, 7)``: the first 6 x 6 block is used).
        dims: Reconstructed coordinates: 4 (x, px, y, py), 6 (all) or a
            sequence of coordinate indices (e.g. ``[0, 1, 2, 3, 5]``).

    Returns:
        ``(3K, P)`` with rows ``<xx>_k, <xy>_k, <yy>_k`` (setting-major) and
        columns the ``P`` entries of :func:`pair_indices` of ``dims``.

    Example:
        >>> r = torch.eye(6)[None]  # a screen at the source
        >>> covariance_design(r, 4)[0].tolist()  # <xx> = Sigma_00
        [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    """
    pairs = pair_indices(dims)
    a = maps[:, 0, :6]
    b = maps[:, 2, :6]
    rows = torch.stack(
        [_sym_coeff(a, a, pairs), _sym_coeff(a, b, pairs), _sym_coeff(b, b, pairs)],
        1,
    )  # (K, 3, P)
    return rows.reshape(-1, rows.shape[-1])


def centroid_design(maps: Tensor, dims: int) -> Tensor:
    """Linear operator from beam centroid to screen centroids ``(2K, dims)``.

    Rows ``<x>_k, <y>_k`` (setting-major); offsets of misaligned elements add a
    constant that cancels in residuals.
    """
    return maps[:, [0, 2], :dims].reshape(-1, dims)


def moment_design(maps: Sequence[Tensor]) -> Tensor:
    """:func:`covariance_design` of all 21 entries over several scans.

    Args:
        maps: First-order maps of each scan's settings ``(K_s, 6, 6)`` or
            affine ``(K_s, 7, 7)``.

    Returns:
        ``(3 K, 21)`` float64, rows ``<xx>_k, <xy>_k, <yy>_k`` setting-major
        over the scans in order, columns :data:`ENTRIES` [Bmad units].
    """
    rows = [covariance_design(m.to(torch.float64)[:, :6, :6], 6) for m in maps]
    if not rows:
        return torch.zeros(0, len(ENTRIES), dtype=torch.float64)
    return torch.cat(rows)


def theta_of(cov: Tensor) -> Tensor:
    """The 21 entries :data:`ENTRIES` of a covariance ``(6, 6)`` -> ``(21,)``."""
    ii = torch.tensor([e[0] for e in ENTRIES])
    jj = torch.tensor([e[1] for e in ENTRIES])
    return cov.to(torch.float64)[ii, jj]


def symmetric(v: Tensor, iu: Tensor, n: int) -> Tensor:
    """The symmetric ``(n, n)`` matrix whose upper-triangular entries at ``iu``
    (``(2, P)`` row and column indices) are ``v`` ``(P,)``; others are zero."""
    s = v.new_zeros(n, n)
    s[iu[0], iu[1]] = v
    return s + s.T - torch.diag(s.diagonal())


def scaled_design(design: Tensor, cov: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`moment_design` in correlation units, rows relative to the screen sizes.

    Args:
        design: ``(3 K, 21)`` from :func:`moment_design`.
        cov: Beam covariance ``(6, 6)`` [Bmad units].

    Returns:
        ``(scaled (3 K, 21), moments (3 K,))``: column ``(i, j)`` times
        ``sig_i sig_j``, row ``<uv>`` divided by ``sqrt(<uu><vv>)`` (so ``<xx>``
        rows by ``<xx>``) of the beam; ``moments`` the beam's screen moments.
    """
    s = cov.to(torch.float64)
    sig = s.diagonal().clamp_min(1e-300).sqrt()
    col = torch.stack([sig[i] * sig[j] for i, j in ENTRIES])
    m = design @ theta_of(s)
    k = m.reshape(-1, 3)
    xx, yy = k[:, 0].clamp_min(1e-300), k[:, 2].clamp_min(1e-300)
    row = torch.stack([xx, (xx * yy).sqrt(), yy], -1).reshape(-1)
    return design * col[None, :] / row[:, None], m
