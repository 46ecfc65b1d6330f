"""Longitudinal second moments the scans cannot see, and the prior that sets them.

In the AWA 6D layout (quadrupole, deflecting cavity, then a drift or a
spectrometer dipole) the energy spread reaches the dipole screen only as
``2 R16 (R11 S_x,pz + R12 S_px,pz) + R16^2 S_pz,pz`` with ``R16`` the same at
every quadrupole strength and ``R11, R12`` nearly linear in it: the images fix
two of the three numbers, and the variance of pz can be traded against the
px-pz covariance without changing any image to first order. The streak of the
cavity does the same to ``S_z,z`` and ``S_py,z``. Without a prior, training
drifts along these directions wherever the entropy pushes: to the largest 6D
volume (pz 8-44 % and z up to 9 % above the truth on synthetic beams).

This module finds those directions from the transfer maps
(:func:`unseen_directions`: the null space of the linear map from the
longitudinal covariance entries to the screen second moments, the transverse
ones held), names the correlation each one trades (:func:`traded_pairs`) and
states the prior point along them (:func:`place_unseen`): where the correlation
that each direction trades (AWA 6D: px-pz, py-z) carries no information beyond
the other four coordinates (zero partial correlation of that pair,
``P_ij = 0`` with ``P`` the precision matrix).
:class:`UnseenHold` is the prior term of the training objective
(``ReconstructionConfig.unseen_weight``): a quadratic penalty on the beam's
displacement from that point along the unseen directions, flat along every
direction the screens' second moments see.

The pair's partial correlation is the criterion, not the direction's whole
off-diagonal part: a direction also touches seen entries (the z-pz chirp), and
weighing their partial correlations in would place strongly chirped beams off.

Known limit: a beam whose traded correlation is not zero (dispersion at the
reconstruction point, a transverse curvature times a tilted chirp) is put at
zero by the prior, and its z or pz is off by as much as that correlation moves
them. Conditioning the partial correlation also on quadratic monomials of (x,
px, y, py) would rest on the reconstruction's fourth moments, which the images
do not pin closely enough, so the prior conditions on the second moments
alone. :mod:`diffaccel.reconstruction.prior_dependence` states with every
result how much the prior decides, and :mod:`diffaccel.reconstruction.design`
which added settings would see these directions.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from diffaccel.dynamics.linalg import lstsq
from diffaccel.reconstruction.hold import MomentHold
from diffaccel.reconstruction.screen_moments import (
    ENTRIES,
    moment_design,
    scaled_design,
)

#: Covariance entries (i <= j) that involve z or pz: the unknowns.
_LONGITUDINAL = [(i, j) for i in range(6) for j in range(i, 6) if j >= 4]
#: A direction is unseen when its singular value of the scaled moment design is
#: below this fraction of the largest. AWA 6D layout (shared 6D training file):
#: 1e-4 (pz: px-pz vs pz-pz) and 4e-3 (z: py-z vs z-z), the next 0.19.
UNSEEN_TOLERANCE = 0.02


def _longitudinal_design(
    maps: Sequence[Tensor], cov: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The scaled moment design (:func:`~diffaccel.reconstruction.screen_moments.
    scaled_design`) of the longitudinal entries :data:`_LONGITUDINAL`.

    Returns:
        ``(design (3K, E), sig (6,), ii (E,), jj (E,))`` float64.
    """
    scaled, _ = scaled_design(moment_design(maps), cov)
    cols = [ENTRIES.index(e) for e in _LONGITUDINAL]
    sig = cov.to(torch.float64).diagonal().clamp_min(1e-300).sqrt()
    ii = torch.tensor([e[0] for e in _LONGITUDINAL])
    jj = torch.tensor([e[1] for e in _LONGITUDINAL])
    return scaled[:, cols], sig, ii, jj


def _directions(
    design: Tensor, sig: Tensor, ii: Tensor, jj: Tensor, tolerance: float
) -> Tensor:
    """Null-space directions (singular value below ``tolerance`` of the largest)
    of ``design`` as symmetric ``(F, 6, 6)`` matrices in Bmad units."""
    _, sv, vh = torch.linalg.svd(design, full_matrices=True)
    full = torch.zeros(vh.shape[0], dtype=torch.float64)
    full[: sv.shape[0]] = sv
    flat = vh[full < tolerance * float(sv[0])]
    out = torch.zeros(flat.shape[0], 6, 6, dtype=torch.float64)
    for k, vec in enumerate(flat):
        m = torch.zeros(6, 6, dtype=torch.float64)
        m[ii, jj] = vec * sig[ii] * sig[jj]
        out[k] = m + m.T - torch.diag(m.diagonal())
    return out


def unseen_directions(
    maps: Sequence[Tensor], cov: Tensor, tolerance: float = UNSEEN_TOLERANCE
) -> Tensor:
    """Longitudinal covariance directions that leave every screen's moments unchanged.

    Args:
        maps: Each scan's affine maps to its screen ``(K_s, 7, 7)`` (or
            ``(K_s, 6, 6)``).
        cov: Covariance of the beam ``(6, 6)`` [Bmad units]: scales the
            unknowns (to correlations) and the rows (to relative moments).
        tolerance: See :data:`UNSEEN_TOLERANCE`.

    Returns:
        ``(F, 6, 6)`` float64 symmetric directions in Bmad units (each of unit
        norm in correlation units); ``F = 0`` when the scans see every
        longitudinal entry, or do not see z or pz at all (no dispersion or no
        deflecting cavity: then the prior sets that coordinate).
    """
    design, sig, ii, jj = _longitudinal_design(maps, cov)
    scale = design.abs().amax(0)
    if any(
        float(scale[_LONGITUDINAL.index((i, i))]) <= 1e-9 * float(scale.max())
        for i in (4, 5)
    ):
        # z or pz not seen at all (e.g. a quadrupole scan alone): nothing is
        # traded against a correlation; their prior sets them
        return torch.zeros(0, 6, 6, dtype=torch.float64)
    return _directions(design, sig, ii, jj, tolerance)


def traded_pairs(directions: Tensor, cov: Tensor) -> list[tuple[int, int]]:
    """The correlation each direction trades: its largest off-diagonal entry.

    Args:
        directions: ``(F, 6, 6)`` from :func:`unseen_directions`.
        cov: Beam covariance ``(6, 6)`` (entries compared as correlations).

    Returns:
        ``(i, j)`` with ``i < j`` per direction (AWA 6D: ``(1, 5)`` px-pz and
        ``(3, 4)`` py-z).
    """
    sig = cov.to(torch.float64).diagonal().clamp_min(1e-300).sqrt()
    out = []
    for v in directions.to(torch.float64):
        c = v / (sig[:, None] * sig[None, :])
        c = c - torch.diag(c.diagonal())
        i, j = divmod(int(c.abs().argmax()), 6)
        out.append((min(i, j), max(i, j)))
    return out


def place_unseen(
    cov: Tensor,
    directions: Tensor,
    iterations: int = 30,
) -> Tensor:
    """``cov`` moved along ``directions`` to zero partial correlation of their trade.

    Solves ``P_ij = 0`` for the pair ``(i, j)`` that each direction ``V_k``
    trades (:func:`traded_pairs`; AWA 6D: px-pz, py-z), ``P`` the inverse of
    ``cov + sum_k t_k V_k``: those two coordinates are uncorrelated given the
    other four. Damped Newton steps that keep the covariance positive definite.

    Shapes:
        ``cov (6, 6)``, ``directions (F, 6, 6)`` -> ``(6, 6)`` float64.
    """
    s0 = cov.to(torch.float64)
    if directions.shape[0] == 0:
        return s0
    v = directions.to(torch.float64)
    pairs = traded_pairs(v, s0)
    ii = torch.tensor([p[0] for p in pairs], dtype=torch.long)
    jj = torch.tensor([p[1] for p in pairs], dtype=torch.long)
    sel = torch.zeros(len(pairs), 6, 6, dtype=torch.float64)
    sel[torch.arange(len(pairs)), ii, jj] = 1.0
    sel = 0.5 * (sel + sel.transpose(1, 2))  # P_ij = tr(P E), E symmetric
    t = torch.zeros(v.shape[0], dtype=torch.float64)

    def precision(t: Tensor) -> Tensor | None:
        s = s0 + torch.einsum("k,kij->ij", t, v)
        if float(torch.linalg.eigvalsh(s).min()) <= 0:
            return None
        return torch.linalg.inv(s)

    for _ in range(iterations):
        p = precision(t)
        if p is None:  # cov itself not positive definite: nothing to place
            break
        g = torch.einsum("ij,kji->k", p, sel)
        if float(g.abs().max()) < 1e-12 * float(p.diagonal().max()):
            break
        # d tr(P E_j) / d t_k = -tr(P V_k P E_j)
        jac = -torch.einsum("ab,kbc,cd,jda->jk", p, v, p, sel)
        step = lstsq(jac, -g[:, None])[:, 0]
        for _half in range(30):
            trial = precision(t + step)
            if trial is not None:
                g_new = torch.einsum("ij,kji->k", trial, sel)
                if float(g_new.norm()) < float(g.norm()):
                    break
            step = step / 2
        else:
            break
        t = t + step
    return s0 + torch.einsum("k,kij->ij", t, v)


def transport_map(cov: Tensor, target: Tensor) -> Tensor:
    """Symmetric ``A`` with ``A cov A^T = target``, closest to the identity.

    The optimal-transport (Monge) map between two centred Gaussians:
    ``A = S^-1/2 (S^1/2 T S^1/2)^1/2 S^-1/2``; every particle moves as little as
    possible (in mean square) for the covariance to become ``target``.
    """

    def sqrt_psd(m: Tensor) -> tuple[Tensor, Tensor]:
        w, q = torch.linalg.eigh(0.5 * (m + m.T))
        w = w.clamp_min(0)
        return q @ torch.diag(w.sqrt()) @ q.T, q @ torch.diag(w.rsqrt()) @ q.T

    # whitened by the diagonal first: Bmad coordinates differ by orders of magnitude
    d = cov.diagonal().sqrt()
    s = cov / (d[:, None] * d[None, :])
    t = target / (d[:, None] * d[None, :])
    root, inv_root = sqrt_psd(s)
    middle, _ = sqrt_psd(root @ t @ root)
    a = inv_root @ middle @ inv_root
    return a * (d[:, None] / d[None, :])


class UnseenHold(MomentHold):
    """The prior term on the unseen directions: a penalty toward the prior point.

    ``w sum_k t_k^2``, with ``t_k`` the displacement of the beam's covariance
    from the prior point of :func:`place_unseen` along each unseen direction
    ``V_k`` of :func:`unseen_directions`, in correlation units (the coordinate
    of ``S - S_prior`` on the unit direction). The penalty depends on the
    covariance only through those coordinates, and the unseen directions are
    orthogonal (in correlation units) to every direction the screens' second
    moments see: it is flat along whatever the images decide. It stops the
    entropy from widening the beam along them, so that the generator fits the
    image *shapes* at the prior point.

    The directions and the prior point are refreshed from the beam's plain
    moments every few steps (:meth:`update`, on the host; training does it
    every ``HOLD_EVERY`` steps); each step then needs only the moments it has
    anyway and no host read (:meth:`surrogate`).

    The 6D default (``ReconstructionConfig.unseen_weight``, ``w = 1e3``): at
    that strength a beam's displacement from the prior point costs as much as
    an image misfit of ``1e3 t^2 / lambda`` (``lambda = 3e4`` the image
    penalty), so a direction the images see even weakly follows the images.

    Args:
        maps: Each scan's affine maps of its training settings ``(K_s, 7, 7)``.
        weight: ``w``.
        scale: Per-coordinate scale ``(6,)`` of the moments [Bmad units]
            (``RelativeEntropy.scale``).
        n: Particles of the beam (all processes together).
    """

    def __init__(
        self,
        maps: Sequence[Tensor],
        weight: float,
        scale: Tensor,
        n: int,
    ) -> None:
        super().__init__(weight, scale, n)
        self.maps = [m.detach().to("cpu", torch.float64) for m in maps]

    def update(self, moments: Tensor) -> None:
        """Directions and prior point of the beam whose moments are given (host)."""
        cov = self.covariance(moments).cpu()
        v = unseen_directions(self.maps, cov)
        if v.shape[0] == 0 or not bool(torch.isfinite(cov).all()):
            self.set(torch.zeros(0, 6, 6), cov)  # nothing to hold
            return
        sig = cov.diagonal().clamp_min(1e-300).sqrt()
        # V_k = sum_e u_e sig_i sig_j (E_ij + E_ji), so
        # t_k = sum_e u_e S_ij / (sig_i sig_j) over the upper triangle
        q = torch.triu(v / (sig[:, None] * sig[None, :]) ** 2)
        self.set(q, place_unseen(cov, v))
