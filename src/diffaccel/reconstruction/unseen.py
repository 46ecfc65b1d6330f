"""Longitudinal second moments the scans cannot see, and where to put them.

In the AWA 6D layout (quadrupole, deflecting cavity, then a drift or a
spectrometer dipole) the energy spread reaches the dipole screen only as
``2 R16 (R11 S_x,pz + R12 S_px,pz) + R16^2 S_pz,pz`` with ``R16`` the same at
every quadrupole strength and ``R11, R12`` nearly linear in it: the images fix
two of the three numbers, and the variance of pz can be traded against the
px-pz covariance without changing any image to first order. The streak of the
cavity does the same to ``S_z,z`` and ``S_py,z``. Training then drifts along
these directions wherever the entropy pushes: to the largest 6D volume, which
on synthetic beams put pz 8-44 % and z up to 9 % above the truth, and Adam
keeps moving along such a direction at full step however weak its gradient.

This module finds those directions from the transfer maps (the null space of
the linear map from the longitudinal covariance entries to the screen second
moments, the transverse ones held) and moves each ensemble member along them
to a stated prior point: the one where the correlation that each direction
trades (AWA 6D: px-pz, py-z) carries no information beyond the other
coordinates and the shape of the transverse distribution, i.e. zero partial
correlation of that pair given the other four coordinates and the quadratic
monomials of (x, px, y, py). The quadratic terms matter on non-Gaussian beams:
a beam whose px and pz both follow x^2 (transverse curvature, and a curved
chirp with an x-z tilt) has a px-pz covariance that the images do pin (through
the curvature of the image shapes), and a Gaussian (linear) partial
correlation would count it as traded (own beam ``chirp_negative``: the
Gaussian criterion put its truth at pz +3 %, emit_z +5 %; this one at
+0.3 %, +0.3 %; on the beams with no such curvature the two agree).

Training holds the same point (:class:`UnseenPenalty`, weight
``ReconstructionConfig.unseen_weight``, from the first step on, acting on z
and pz only), so the generator fits the image shapes with the unseen
directions already at the prior; the move after training then only removes
what is left. Without the penalty the move is large (own beam
``chirp_negative``: pz +82 % before it) and, being linear, reshapes what the
images do see: held-out image error 0.076 -> 0.153 on that beam (0.184 with
the all-coordinate map below), 0.078 with the penalty.

The move leaves the transverse coordinates of every particle unchanged and
maps (z, pz) affinely (their regression on the transverse coordinates set to
the target, the residual moved by the optimal-transport map between the two
Gaussians of the residuals), folded into the generator's last linear layers:
straight-ahead images with the cavity off do not change at all, and the others
only at the order the data cannot see.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from diffaccel.reconstruction.generator import BeamGenerator

#: Covariance entries (i <= j) that involve z or pz: the unknowns.
_LONGITUDINAL = [(i, j) for i in range(6) for j in range(i, 6) if j >= 4]
#: A direction is unseen when its singular value of the scaled moment design is
#: below this fraction of the largest. AWA 6D layout (shared 6D training file):
#: 1e-4 (pz: px-pz vs pz-pz) and 4e-3 (z: py-z vs z-z), the next 0.19.
UNSEEN_TOLERANCE = 0.02


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
    s = cov.to(torch.float64)
    sig = s.diagonal().clamp_min(1e-300).sqrt()
    r = torch.cat([m.to(torch.float64)[:, :6, :6] for m in maps])
    ii = torch.tensor([e[0] for e in _LONGITUDINAL])
    jj = torch.tensor([e[1] for e in _LONGITUDINAL])
    mult = torch.where(ii == jj, 1.0, 2.0).to(torch.float64)
    rows = []
    for a, b in ((0, 0), (2, 2), (0, 2)):
        u, v = r[:, a], r[:, b]  # (K, 6)
        # <(u.x)(v.x)> = sum_ij u_i v_j S_ij, symmetrised, in correlation units
        coef = 0.5 * (u[:, ii] * v[:, jj] + v[:, ii] * u[:, jj]) * mult
        coef = coef * (sig[ii] * sig[jj])
        su = torch.einsum("ki,ij,kj->k", u, s, u).clamp_min(1e-300)
        sv = torch.einsum("ki,ij,kj->k", v, s, v).clamp_min(1e-300)
        rows.append(coef / (su * sv).sqrt()[:, None])  # relative to the sizes
    design = torch.cat(rows)
    scale = design.abs().amax(0)
    if any(
        float(scale[_LONGITUDINAL.index((i, i))]) <= 1e-9 * float(scale.max())
        for i in (4, 5)
    ):
        # z or pz not seen at all (e.g. a quadrupole scan alone): nothing is
        # traded against a correlation; their prior sets them
        return torch.zeros(0, 6, 6, dtype=torch.float64)
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


#: Coordinates kept by the placement and whose quadratic monomials condition
#: the partial correlations: x, px, y, py.
_TRANSVERSE = 4


def traded_pairs(directions: Tensor, cov: Tensor) -> list[tuple[int, int]]:
    """The correlation each direction trades: its largest off-diagonal entry.

    Args:
        directions: ``(F, 6, 6)`` from :func:`unseen_directions`.
        cov: Beam covariance ``(6, 6)`` (the entries are compared as
            correlations).

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


def residual_covariance(particles: Tensor) -> Tensor:
    """Covariance of the particles left after their transverse curvature.

    The covariance of the residuals of a least-squares regression of all six
    coordinates on the ten quadratic monomials of ``(x, px, y, py)`` (centred):
    what the partial correlations of :func:`place_unseen` are conditioned on
    besides the coordinates themselves. Equal to the covariance for a
    Gaussian beam (up to sampling noise).

    Shapes:
        ``particles (N, 6)`` -> ``(6, 6)`` float64.
    """
    x = particles.to(torch.float64)
    sig = x.std(0).clamp_min(1e-300)
    u = (x - x.mean(0)) / sig  # standardised: the monomials are O(1)
    i, j = torch.triu_indices(_TRANSVERSE, _TRANSVERSE)
    q = u[:, i] * u[:, j]
    c = torch.cov(torch.cat([u, q], 1).T)
    cxq, cqq = c[:6, 6:], c[6:, 6:]
    res = c[:6, :6] - cxq @ torch.linalg.solve(cqq, cxq.T)
    return res * (sig[:, None] * sig[None, :])


class UnseenPenalty:
    """Training penalty that holds the unseen directions at the prior point.

    ``weight * sum_k g_k^2`` with ``g_k`` the partial correlation of the pair
    that direction ``k`` trades (:func:`traded_pairs`), given the other
    coordinates and the quadratic transverse monomials (as in
    :func:`residual_covariance`), of the particles of one training step:
    the images do not see these directions, so without it the generator's
    shape along them is whatever the entropy and the last placement left,
    and a linear move after training cannot re-fit the image shapes (own beam
    ``chirp_negative``: pz +82 % before the move, held-out L1 0.15 after).
    Differentiable (float64 moments of one ``(N, 16)`` matrix).

    Args:
        pairs: Traded pairs ``(i, j)``.
        scale: Per-coordinate scale ``(6,)`` (standardises the monomials).
        weight: Factor of the squared partial correlations.

    Shapes:
        ``__call__(particles (N, 6))`` -> ``()`` float64.
    """

    def __init__(
        self, pairs: Sequence[tuple[int, int]], scale: Tensor, weight: float
    ) -> None:
        self.ii = torch.tensor([p[0] for p in pairs], device=scale.device)
        self.jj = torch.tensor([p[1] for p in pairs], device=scale.device)
        self.inv_scale = 1.0 / scale.to(torch.float64)
        self.tri = torch.triu_indices(_TRANSVERSE, _TRANSVERSE, device=scale.device)
        self.weight = weight

    def partial_correlations(self, particles: Tensor) -> Tensor:
        """``g_k`` of every pair ``(F,)`` (differentiable in z and pz only)."""
        # the transverse coordinates are seen: the penalty moves only z and pz
        # (on the shared 6D training file, a gradient into them as well cost
        # the y emittance, y-py correlation 0.98: +6.9 % instead of +1.3 %)
        t = _TRANSVERSE
        x = torch.cat([particles[:, :t].detach(), particles[:, t:]], 1)
        u = x.to(torch.float64) * self.inv_scale
        u = u - u.mean(0)
        q = u[:, self.tri[0]] * u[:, self.tri[1]]
        z = torch.cat([u, q - q.mean(0)], 1)
        c = z.T @ z / (z.shape[0] - 1)
        cxq = c[:6, 6:]
        res = c[:6, :6] - cxq @ torch.linalg.solve(c[6:, 6:], cxq.T)
        p = torch.linalg.inv(res)
        d = p.diagonal()
        return p[self.ii, self.jj] / (d[self.ii] * d[self.jj]).sqrt()

    def __call__(self, particles: Tensor) -> Tensor:
        return self.weight * self.partial_correlations(particles).square().sum()


def longitudinal_map(cov: Tensor, target: Tensor) -> Tensor:
    """``K`` with ``K cov K^T = target`` that keeps x, px, y, py.

    ``target`` must share the transverse block of ``cov``. With ``L = (z, pz)``
    and ``T`` the transverse coordinates: ``L' = B' T + M (L - B T)``, with
    ``B, B'`` the regressions of ``L`` on ``T`` in ``cov`` and ``target`` and
    ``M`` the optimal-transport map (:func:`transport_map`) between the
    residual covariances.

    Shapes:
        ``cov (6, 6)``, ``target (6, 6)`` -> ``(6, 6)`` float64.
    """
    t = _TRANSVERSE

    def regression(s: Tensor) -> tuple[Tensor, Tensor]:
        b = torch.linalg.solve(s[:t, :t], s[:t, t:]).T  # (2, 4)
        return b, s[t:, t:] - b @ s[:t, t:]

    b0, e0 = regression(cov.to(torch.float64))
    b1, e1 = regression(target.to(torch.float64))
    m = transport_map(e0, e1)
    k = torch.eye(cov.shape[0], dtype=torch.float64)
    k[t:, t:] = m
    k[t:, :t] = b1 - m @ b0
    return k


def place_unseen(
    cov: Tensor,
    directions: Tensor,
    residual: Tensor | None = None,
    iterations: int = 30,
) -> Tensor:
    """``cov`` moved along ``directions`` to zero partial correlation of their trade.

    For every direction ``V_k`` (traded pair ``(i, j)`` from
    :func:`traded_pairs`) solves ``P_ij = 0``, ``P`` the inverse of
    ``K R K^T``: ``R`` the ``residual`` covariance
    (:func:`residual_covariance`; default ``cov``, i.e. Gaussian partial
    correlations) carried by the map ``K`` (:func:`longitudinal_map`) from
    ``cov`` to ``cov + sum_k t_k V_k``. Damped Newton steps (finite-difference
    Jacobian, ``F x F``) that keep the covariance positive definite.

    Shapes:
        ``cov (6, 6)``, ``directions (F, 6, 6)``, ``residual (6, 6)`` ->
        ``(6, 6)`` float64.
    """
    s0 = cov.to(torch.float64)
    if directions.shape[0] == 0:
        return s0
    v = directions.to(torch.float64)
    r = s0 if residual is None else residual.to(torch.float64)
    pairs = traded_pairs(v, s0)
    ii = torch.tensor([p[0] for p in pairs])
    jj = torch.tensor([p[1] for p in pairs])

    def partial(t: Tensor) -> Tensor | None:
        s = s0 + torch.einsum("k,kij->ij", t, v)
        if float(torch.linalg.eigvalsh(s).min()) <= 0:
            return None
        k = longitudinal_map(s0, s)
        p = torch.linalg.inv(k @ r @ k.T)
        d = p.diagonal()
        return p[ii, jj] / (d[ii] * d[jj]).sqrt()

    t = torch.zeros(v.shape[0], dtype=torch.float64)
    g = partial(t)
    eye = torch.eye(v.shape[0], dtype=torch.float64)
    h = 1e-6  # t is in correlation units (directions of unit norm there)
    for _ in range(iterations):
        if g is None or float(g.abs().max()) < 1e-10:
            break
        cols = [partial(t + h * e) for e in eye]
        if any(c is None for c in cols):
            break
        jac = torch.stack([(c - g) / h for c in cols], 1)  # type: ignore[operator]
        step = torch.linalg.lstsq(jac, -g[:, None]).solution[:, 0]
        for _half in range(30):
            trial = partial(t + step)
            if trial is not None and float(trial.norm()) < float(g.norm()):
                break
            step = step / 2
        else:
            break
        t, g = t + step, trial
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


def place_members(
    snapshots: Sequence[dict],
    dims: int,
    width: int,
    depth: int,
    maps: Sequence[Tensor],
    *,
    n_particles: int = 65536,
    seed: int = 0,
) -> list[dict]:
    """Each member's generator moved along the unseen directions (see the module).

    Args:
        snapshots: Generator state dicts (``BeamGenerator``) of the members.
        dims: Generated coordinates (only 6 has longitudinal ones; 4 returns
            the snapshots unchanged).
        width: MLP width of the generators.
        depth: MLP depth of the generators.
        maps: Each scan's affine maps of its training settings ``(K_s, 7, 7)``.
        n_particles: Quasi-random particles per member for its covariance.
        seed: Seed of those samples.

    Returns:
        New state dicts (the inputs are not changed): with ``A`` the map of
        :func:`longitudinal_map` and ``mu`` the member's centroid, particles
        become ``mu + A (x - mu)``, written into the offset, the mixing matrix and
        the last linear layer of the generator.
    """
    if dims != 6:
        return [dict(s) for s in snapshots]
    out = []
    for state in snapshots:
        gen = BeamGenerator(dims, width=width, depth=depth, scale=torch.ones(dims))
        gen.load_state_dict(state)
        gen.requires_grad_(False)
        g = torch.Generator().manual_seed(seed)
        x = gen(n_particles, generator=g, quasi_random=True).to(torch.float64)
        mu = x.mean(0)
        cov = torch.cov(x.T)
        directions = unseen_directions(maps, cov)
        if directions.shape[0] == 0:
            out.append(dict(state))
            continue
        target = place_unseen(cov, directions, residual_covariance(x))
        out.append(_fold(state, longitudinal_map(cov, target), mu))
    return out


def _fold(state: dict, a: Tensor, mu: Tensor) -> dict:
    """State dict of the generator whose particles are ``mu + A (x - mu)``.

    ``x = s0 (b + e^l u)`` with ``u = mix base + W h + c``: with
    ``D = diag(s0 e^l)`` the new ``u' = D^-1 A D u`` (mixing matrix and last
    layer multiplied by ``M = D^-1 A D``) and ``b' = (A s0 b + (I - A) mu) / s0``.
    """
    new = {k: v.clone() for k, v in state.items()}
    dtype = state["mix"].dtype
    s0 = state["ref_scale"].to(torch.float64)
    d = s0 * state["log_scale"].to(torch.float64).exp()
    m = a / d[:, None] * d[None, :]
    new["mix"] = (m @ state["mix"].to(torch.float64)).to(dtype)
    last = max(
        (k for k in state if k.startswith("mlp.") and k.endswith(".weight")),
        key=lambda k: int(k.split(".")[1]),
    )
    bias = last[: -len("weight")] + "bias"
    new[last] = (m @ state[last].to(torch.float64)).to(dtype)
    new[bias] = (m @ state[bias].to(torch.float64)).to(dtype)
    b = state["offset"].to(torch.float64)
    eye = torch.eye(a.shape[0], dtype=torch.float64)
    new["offset"] = ((a @ (s0 * b) + (eye - a) @ mu) / s0).to(dtype)
    return new
