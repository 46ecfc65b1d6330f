"""How much of a 6D reconstruction the prior decides: the unseen correlations.

Along the directions of :func:`~diffaccel.reconstruction.unseen.unseen_directions`
(AWA 6D: the px-pz covariance traded against the pz variance, py-z against the
z variance) no screen's second moments change to first order, so the images
cannot tell a beam from its twin moved along one: the objective's prior term puts the
traded pair at zero partial correlation given the other coordinates (with the strength
``ReconstructionConfig.unseen_weight``) because nothing measured says where else. Two
Gaussian beams 35 % apart in z emittance gave training images that differ by less than
the sampling noise of two million particles.

:func:`prior_dependence` states what that choice is worth: for each direction,
the beam moved along it until the pair's partial correlation is each of a few
stated values (:data:`DEPENDENCE_PARTIALS`), and the relative change of the
moments that move (rms z or pz, z and 6D emittance). The summary of a 6D
reconstruction carries it (``prior_dependence``) and ``diffaccel reconstruct``
prints it: a z emittance that would change by 30 % for a partial correlation of
0.1 is a prior's value, whatever its ensemble spread.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from diffaccel.reconstruction.metrics import COORDINATES
from diffaccel.reconstruction.unseen import traded_pairs, unseen_directions

#: Partial correlations of a traded pair at which :func:`prior_dependence`
#: evaluates the beam: the range real beams take. README-family beams with a
#: transverse curvature in px (px ~ x^2) and a curved chirp tilted in x have
#: px-pz partial correlations of up to 0.27, a beam reconstructed from a real
#: photoinjector's 6D scan +0.56; the pair prior puts them at 0.
DEPENDENCE_PARTIALS = (-0.6, -0.3, -0.1, 0.1, 0.3, 0.6)

#: Points of the grid along a direction on which the partial correlation is
#: bracketed before bisection.
_GRID = 401


def partial_correlations(cov: Tensor, i: int, j: int) -> Tensor:
    """Correlation of coordinates ``i`` and ``j`` given the other four.

    ``-P_ij / sqrt(P_ii P_jj)`` with ``P`` the inverse of ``cov (..., 6, 6)``;
    returns shape ``(...)`` float64.
    """
    p = torch.linalg.inv(cov.to(torch.float64))
    return -p[..., i, j] / (p[..., i, i] * p[..., j, j]).sqrt()


def partial_correlation(cov: Tensor, i: int, j: int) -> float:
    """:func:`partial_correlations` of one covariance ``(6, 6)``."""
    return float(partial_correlations(cov, i, j))


def _positive_definite(cov: Tensor) -> bool:
    return bool(torch.linalg.eigvalsh(cov).min() > 0)


def _edge(cov: Tensor, direction: Tensor, sign: float) -> float:
    """Largest ``t >= 0`` with ``cov + sign t direction`` positive definite
    (to 1e-9 relative; ``inf`` when it stays so up to ``2**20``)."""
    hi = 1.0
    while _positive_definite(cov + sign * hi * direction):
        hi *= 2.0
        if hi > 2.0**20:
            return float("inf")
    lo = 0.0
    while hi - lo > 1e-9 * hi:
        mid = 0.5 * (lo + hi)
        if _positive_definite(cov + sign * mid * direction):
            lo = mid
        else:
            hi = mid
    return lo


def move_to_partial(
    cov: Tensor, direction: Tensor, pair: tuple[int, int], target: float
) -> Tensor | None:
    """``cov + t direction`` whose ``pair`` has partial correlation ``target``.

    The ``t`` closest to 0 (the given beam) on a grid over the positive
    definite stretch of the line, refined by bisection.

    Args:
        cov: Beam covariance ``(6, 6)`` [Bmad units].
        direction: One unseen direction ``(6, 6)``.
        pair: ``(i, j)``, the correlation the direction trades.
        target: Partial correlation in ``(-1, 1)``.

    Returns:
        The moved covariance ``(6, 6)`` float64, or None when no positive
        definite point of the line has that partial correlation.
    """
    return _moves(cov, direction, pair, [target])[0]


def _moves(
    cov: Tensor, direction: Tensor, pair: tuple[int, int], targets: Sequence[float]
) -> list[Tensor | None]:
    """:func:`move_to_partial` for several targets, on one grid of the line."""
    s = cov.to(torch.float64)
    d = direction.to(torch.float64)
    lo, hi = -_edge(s, d, -1.0), _edge(s, d, 1.0)
    lo, hi = max(lo, -64.0), min(hi, 64.0)  # correlation units: far enough
    ts = torch.linspace(lo, hi, _GRID, dtype=torch.float64)[1:-1]
    grid = partial_correlations(s + ts[:, None, None] * d, *pair)
    out: list[Tensor | None] = []
    for target in targets:
        vals = grid - target
        brackets = torch.nonzero(vals[:-1] * vals[1:] <= 0).flatten()
        if brackets.numel() == 0:
            out.append(None)
            continue
        k = int(brackets[ts[brackets].abs().argmin()])
        a, b = float(ts[k]), float(ts[k + 1])
        fa = float(vals[k])
        for _ in range(60):
            m = 0.5 * (a + b)
            fm = partial_correlation(s + m * d, *pair) - target
            if (fm <= 0) == (fa <= 0):
                a, fa = m, fm
            else:
                b = m
        out.append(s + 0.5 * (a + b) * d)
    return out


def _emittances(cov: Tensor) -> dict[str, float]:
    return {
        "emit_z": float(torch.linalg.det(cov[4:6, 4:6]).clamp_min(0).sqrt()),
        "emit_6d": float(torch.linalg.det(cov).clamp_min(0).sqrt()),
    }


def prior_dependence(
    maps: Sequence[Tensor],
    cov: Tensor,
    partials: Sequence[float] = DEPENDENCE_PARTIALS,
) -> list[dict]:
    """What the beam's moments would be, for the same images, elsewhere along
    each unseen direction (see the module).

    Args:
        maps: Each scan's affine maps of its training settings ``(K_s, 7, 7)``.
        cov: The reconstruction's covariance ``(6, 6)`` [Bmad units].
        partials: Partial correlations of the traded pair to evaluate.

    Returns:
        One JSON-ready dict per unseen direction (none in 4D layouts or where
        the scans see every longitudinal entry): ``pair`` (e.g. ``"px-pz"``),
        ``moves`` (the rms whose variance the direction trades, e.g.
        ``"rms_pz"``), ``partial_correlation`` (the beam's own), and
        ``if_partial_correlation``: per value, ``partial_correlation`` and
        ``relative_change`` (fractions keyed by ``moves``, ``"emit_z"`` and
        ``"emit_6d"``; None where no positive definite beam on the line has
        that value).

    Raises:
        ValueError: for a ``cov`` that is not a finite, positive definite
            ``(6, 6)`` matrix.

    Example:
        >>> from diffaccel.dynamics import Beamline
        >>> from diffaccel.reconstruction import ScreenForwardModel
        >>> line = Beamline.from_spec([
        ...     {"type": "Quadrupole", "name": "Q", "length": 0.1, "k1": 0.0},
        ...     {"type": "Drift", "name": "D", "length": 1.0},
        ...     {"type": "Screen", "name": "S", "shape": [32, 32],
        ...      "pixel_size": [1e-4, 1e-4]}])
        >>> fwd = ScreenForwardModel(line, ["Q.k1"], 43e6)
        >>> maps = [fwd.transfer_maps(torch.tensor([[-5.0], [0.0], [5.0]]))]
        >>> prior_dependence(maps, torch.eye(6, dtype=torch.float64) * 1e-6)
        []
    """
    s = cov.to(torch.float64)
    if s.shape != (6, 6) or not bool(torch.isfinite(s).all()):
        raise ValueError(f"cov must be a finite (6, 6) matrix; got {tuple(s.shape)}.")
    if not _positive_definite(s):
        raise ValueError("cov is not positive definite: no beam has it.")
    directions = unseen_directions(maps, s)
    if directions.shape[0] == 0:
        return []
    pairs = traded_pairs(directions, s)
    base = _emittances(s)
    out = []
    for d, (i, j) in zip(directions, pairs, strict=True):
        k = int(d.diagonal().abs().argmax())
        moves = f"rms_{COORDINATES[k]}"
        at = []
        for r, moved in zip(partials, _moves(s, d, (i, j), partials), strict=True):
            change = None
            if moved is not None:
                e = _emittances(moved)
                change = {
                    moves: float((moved[k, k] / s[k, k]).sqrt()) - 1.0,
                    **{n: e[n] / base[n] - 1.0 for n in e},
                }
            at.append({"partial_correlation": float(r), "relative_change": change})
        out.append(
            {
                "pair": f"{COORDINATES[i]}-{COORDINATES[j]}",
                "moves": moves,
                "partial_correlation": partial_correlation(s, i, j),
                "if_partial_correlation": at,
            }
        )
    return out
