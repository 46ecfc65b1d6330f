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
trades (AWA 6D: px-pz, py-z) carries no information beyond the other four
coordinates (zero partial correlation of that pair, ``P_ij = 0`` with ``P`` the
precision matrix; ``prior="pair"``, the default). The move is the smallest
displacement of the particles that gives the new covariance (the
optimal-transport map between the two Gaussians), folded into the generator's
last linear layers, so the screens' second moments do not change. The shapes
of non-Gaussian images can: a member that training had widened along a
direction loses part of its fit (on a weakly chirped, x-z tilted synthetic
beam: held-out dipole-on relative L1 0.075 before the move, 0.199 after it).
The default therefore refits each placed member's shape with its covariance
held at the placed one (``ReconstructionConfig.refit_steps``, ``refit_hold``;
:func:`~diffaccel.reconstruction.pipeline.refit_members`). :class:`UnseenHold`
(opt-in: the config's ``hold_unseen``) holds the beam at the prior point
during training instead, so that the generator fits the image shapes there;
it trades those image misses for moment misses on other beams.

The alternative criterion ``prior="gaussian"`` solves ``tr(P V_off) = 0`` over
the direction's whole off-diagonal part: the direction also touches seen
entries (the z-pz chirp), so it weighs in their partial correlations and
places strongly chirped truths off (a compressed double-horn bunch, z-pz
-0.91: emit_z +11.9 % at its truth, where ``"pair"`` leaves it).

Known limit: a beam whose traded correlation is set by its shape is placed
wrong. A beam with a px-pz partial correlation of +0.09 (from a transverse
curvature times a tilted curved chirp, z-pz -0.95) is placed at emit_z -35 %
at its truth by ``"pair"`` (+16 % by ``"gaussian"``); with a z-pz coefficient
of 0.95 a 10 % limit leaves rms pz about 1 % of room. Conditioning the partial
correlation also on quadratic monomials of (x, px, y, py) would rest on the
reconstruction's fourth moments, which the images do not pin closely enough,
so the prior conditions on the second moments alone.
:mod:`diffaccel.reconstruction.prior_dependence` states with every result how
much the prior decides.

The transverse plane has a barely seen direction too: x-y coupling
(:func:`coupling_directions`; x-py and px-y against px-py, singular value
0.03-0.07 of the largest where the longitudinal ones are below 0.005).
Training settles along it where the image shapes pull: a beam of three modes
in x-y comes out with 4D and 6D emittances 10-16 % low while each plane's
emittance is within 1 %. For beams not turned in x-y the largest determinant
along the direction is the truth (within 0.2 % of 6D emittance on the
synthetic test beams, x-y correlations of up to 0.38 from the mode structure
included), and :func:`place_members` with ``coupling=True`` moves each member
there (``ReconstructionConfig.place_coupling``, ``reconstruct --uncoupled``).
It is off by default: a beam rotated in x-y (after a solenoid) is not at that
point, and training finds its coupling from the image shapes (6D emittance
-3.9 % trained, +11.7 % placed).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import torch
from torch import Tensor

from diffaccel.dynamics.linalg import lstsq
from diffaccel.reconstruction.generator import BeamGenerator
from diffaccel.reconstruction.hold import MomentHold

#: Covariance entries (i <= j) that involve z or pz: the unknowns.
_LONGITUDINAL = [(i, j) for i in range(6) for j in range(i, 6) if j >= 4]
#: A direction is unseen when its singular value of the scaled moment design is
#: below this fraction of the largest. AWA 6D layout (shared 6D training file):
#: 1e-4 (pz: px-pz vs pz-pz) and 4e-3 (z: py-z vs z-z), the next 0.19.
UNSEEN_TOLERANCE = 0.02


def _moment_design(
    maps: Sequence[Tensor], cov: Tensor, entries: Sequence[tuple[int, int]]
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Linear map from covariance ``entries`` to every screen's second moments.

    Unknowns in correlation units (``S_ij / (sig_i sig_j)``), rows relative to
    the screen sizes of ``cov``: rows ``<xx>, <yy>, <xy>`` of every setting.

    Returns:
        ``(design (3K, E), sig (6,), ii (E,), jj (E,))`` float64.
    """
    s = cov.to(torch.float64)
    sig = s.diagonal().clamp_min(1e-300).sqrt()
    r = torch.cat([m.to(torch.float64)[:, :6, :6] for m in maps])
    ii = torch.tensor([e[0] for e in entries])
    jj = torch.tensor([e[1] for e in entries])
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
    return torch.cat(rows), sig, ii, jj


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
    design, sig, ii, jj = _moment_design(maps, cov, _LONGITUDINAL)
    scale = design.abs().amax(0)
    if any(
        float(scale[_LONGITUDINAL.index((i, i))]) <= 1e-9 * float(scale.max())
        for i in (4, 5)
    ):
        # z or pz not seen at all (e.g. a quadrupole scan alone): nothing is
        # traded against a correlation; their prior sets them
        return torch.zeros(0, 6, 6, dtype=torch.float64)
    return _directions(design, sig, ii, jj, tolerance)


#: Transverse cross-plane covariance entries: x-y, x-py, px-y, px-py.
_COUPLING = [(0, 2), (0, 3), (1, 2), (1, 3)]
#: A cross-plane direction is barely seen when its singular value of the
#: scaled moment design (the other entries held) is below this fraction of the
#: largest. AWA 6D layout, synthetic test beams and x-y rotated ones: 0.028-0.072
#: for one direction (x-py and px-y against px-py), the next 0.175 or more.
COUPLING_TOLERANCE = 0.1


def coupling_directions(
    maps: Sequence[Tensor], cov: Tensor, tolerance: float = COUPLING_TOLERANCE
) -> Tensor:
    """Transverse x-y coupling directions that the screens barely see.

    After one quadrupole and a drift of length ``L`` to the screen
    (``R12 = R34 = L`` to first order in the quadrupole's length) the
    cross-plane second moment ``<x y>`` at the screen weighs the beam's
    ``S_x,py`` and ``S_px,y`` alike and ``S_px,py`` by ``L``: moving the first
    two by ``t`` and the third by ``-2 t / L`` leaves every image's second
    moments nearly unchanged (a second screen at another distance, and the
    quadrupole's length, see it weakly: singular value 0.03-0.07 of the
    largest on the AWA 6D layout). Training then settles along it where the
    fit of the image shapes pulls, not at the largest entropy: a beam of three
    modes in x-y comes out with 4D and 6D emittances 10-16 % low while each
    plane's emittance is within 1 %.

    Args:
        maps: Each scan's affine maps to its screen ``(K_s, 7, 7)``.
        cov: Covariance of the beam ``(6, 6)`` [Bmad units].
        tolerance: See :data:`COUPLING_TOLERANCE`.

    Returns:
        ``(F, 6, 6)`` float64 symmetric directions in Bmad units, with only
        cross-plane entries (each of unit norm in correlation units).
    """
    design, sig, ii, jj = _moment_design(maps, cov, _COUPLING)
    return _directions(design, sig, ii, jj, tolerance)


#: Quasi-random particles per member for the covariance the placement moves
#: (and the refit holds).
PLACEMENT_PARTICLES = 65536

#: Priors of :func:`place_unseen` (see there).
UNSEEN_PRIORS = ("pair", "gaussian")


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
    prior: str = "pair",
    coupling: Tensor | None = None,
) -> Tensor:
    """``cov`` moved along ``directions`` to zero partial correlation of their trade.

    ``prior="pair"`` (the default) solves ``P_ij = 0`` for the pair ``(i, j)``
    that each direction ``V_k`` trades (:func:`traded_pairs`; AWA 6D: px-pz,
    py-z), ``P`` the inverse of ``cov + sum_k t_k V_k``: those two coordinates
    are uncorrelated given the other four. ``prior="gaussian"`` solves
    ``tr(P V_k,off) = 0`` with ``V_off`` the direction's whole off-diagonal
    part instead, which also weighs in the partial correlations of the seen
    entries the direction touches (z-pz: a strongly chirped beam's truth is
    placed off, see the module). ``coupling`` directions
    (:func:`coupling_directions`, cross-plane entries only) are moved at the
    same time to the largest determinant along them (``tr(P V_k) = 0``): the
    largest entropy of a Gaussian, the point of the maximum-entropy
    loss. Damped Newton steps that keep the covariance positive definite.

    Shapes:
        ``cov (6, 6)``, ``directions (F, 6, 6)``, ``coupling (G, 6, 6)`` ->
        ``(6, 6)`` float64.

    Raises:
        ValueError: for a ``prior`` other than those of :data:`UNSEEN_PRIORS`.
    """
    if prior not in UNSEEN_PRIORS:
        raise ValueError(f"prior must be one of {UNSEEN_PRIORS}; got {prior!r}.")
    s0 = cov.to(torch.float64)
    extra = (
        torch.zeros(0, 6, 6, dtype=torch.float64)
        if coupling is None
        else coupling.to(torch.float64)
    )
    if directions.shape[0] + extra.shape[0] == 0:
        return s0
    v = directions.to(torch.float64)
    # units of the pair criteria P_ij sig_i sig_j and of the stopping test:
    # correlation units beside coupling criteria (the damped steps compare
    # the norm of all of them), precision units alone
    sig = (
        s0.diagonal().clamp_min(1e-300).sqrt()
        if extra.shape[0]
        else torch.ones(6, dtype=torch.float64)
    )
    if prior == "pair":
        pairs = traded_pairs(v, s0)
        ii = torch.tensor([p[0] for p in pairs], dtype=torch.long)
        jj = torch.tensor([p[1] for p in pairs], dtype=torch.long)
        sel = torch.zeros(len(pairs), 6, 6, dtype=torch.float64)
        sel[torch.arange(len(pairs)), ii, jj] = sig[ii] * sig[jj]
        sel = 0.5 * (sel + sel.transpose(1, 2))  # P_ij = tr(P E), E symmetric
    else:
        sel = v - torch.diag_embed(v.diagonal(dim1=-2, dim2=-1))
    # the coupling directions: largest determinant, tr(P V) = 0
    v = torch.cat([v, extra])
    sel = torch.cat([sel, extra])
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
        if float(g.abs().max()) < 1e-12 * float((p.diagonal() * sig.square()).max()):
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
    """Penalty that holds the beam at the prior point along unseen directions.

    ``w sum_k t_k^2``, with ``t_k`` the displacement of the beam's covariance
    from the prior point of :func:`place_unseen` along each unseen direction
    ``V_k`` of :func:`unseen_directions`, in correlation units (the coordinate
    of ``S - S_prior`` on the unit direction). The gradient of the penalty with
    respect to the covariance lies along those directions only, so it moves
    nothing the screens' second moments see; it stops the entropy from widening
    the beam along them during training, so that the generator fits the image
    *shapes* at the prior point instead of being moved there afterwards by a
    linear map (:func:`place_members` still runs after training and then moves
    little).

    The directions and the prior point are refreshed from the beam's plain
    moments every few steps (:meth:`update`, on the host; training does it
    every ``HOLD_EVERY`` steps); each step then needs only the moments it has
    anyway and no host read (:meth:`surrogate`).

    Opt-in (``ReconstructionConfig.hold_unseen``): on the synthetic test beams
    of ``benchmarks/reconstruction_6d_beams.py`` it brings every held-out image
    within 0.10 relative L1 (0.14-0.20 placed after training on a weakly
    chirped tilted beam) but moves the seen z-pz chirp on other beams (the z
    direction carries 0.19 of it per unit), so it is not the default.

    Args:
        maps: Each scan's affine maps of its training settings ``(K_s, 7, 7)``.
        weight: ``w``.
        scale: Per-coordinate scale ``(6,)`` of the moments [Bmad units]
            (``RelativeEntropy.scale``).
        n: Particles of the beam (all processes together).
        prior: ``"pair"`` or ``"gaussian"`` (:func:`place_unseen`).
    """

    refreshes = True

    def __init__(
        self,
        maps: Sequence[Tensor],
        weight: float,
        scale: Tensor,
        n: int,
        prior: str = "pair",
    ) -> None:
        super().__init__(weight, scale, n)
        self.maps = [m.detach().to("cpu", torch.float64) for m in maps]
        self.prior = prior

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
        self.set(q, place_unseen(cov, v, prior=self.prior))


def place_members(
    snapshots: Sequence[dict],
    dims: int,
    width: int,
    depth: int,
    maps: Sequence[Tensor],
    *,
    n_particles: int = PLACEMENT_PARTICLES,
    seed: int = 0,
    prior: str = "pair",
    coupling: bool = False,
    shift: dict[tuple[int, int], float] | None = None,
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
        prior: Prior point of :func:`place_unseen` (``"pair"`` or
            ``"gaussian"``).
        coupling: Where a member has unseen longitudinal directions, also
            move it along the barely seen x-y coupling directions
            (:func:`coupling_directions`) to the largest determinant.
        shift: ``{(i, j): t}``: from the prior point, move ``t`` further along
            the direction that trades the ``(i, j)`` correlation (correlation
            units, as :func:`unseen_directions`; the point
            :func:`~diffaccel.reconstruction.probe.probe_members` chose),
            the coupling directions (with ``coupling``) then placed again.
            Ignored where no direction trades that pair or where the shifted
            covariance would not be positive definite.

    Returns:
        New state dicts (the inputs are not changed): with ``A`` the transport
        map and ``mu`` the member's centroid, particles become
        ``mu + A (x - mu)``, written into the offset, the mixing matrix and
        the last linear layer of the generator.
    """
    if dims != 6:
        return [dict(s) for s in snapshots]
    out = []
    for state in snapshots:
        mu, cov = member_moments(state, dims, width, depth, n_particles, seed)
        directions = unseen_directions(maps, cov)
        if directions.shape[0] == 0:
            out.append(dict(state))
            continue
        extra = coupling_directions(maps, cov) if coupling else None
        target = place_unseen(cov, directions, prior=prior, coupling=extra)
        if shift:
            pairs = traded_pairs(directions, cov)
            moved = target + sum(
                t * directions[pairs.index(p)] for p, t in shift.items() if p in pairs
            )
            if float(torch.linalg.eigvalsh(moved).min()) > 0:
                target = moved
                if coupling:  # the largest determinant again, there
                    target = place_unseen(
                        target,
                        directions[:0],
                        coupling=coupling_directions(maps, target),
                    )
        out.append(_fold(state, transport_map(cov, target), mu))
    return out


class PlacementSettings(Protocol):
    """What :func:`place_configured` reads of a
    :class:`~diffaccel.reconstruction.ReconstructionConfig`."""

    @property
    def dims(self) -> int: ...
    @property
    def width(self) -> int: ...
    @property
    def depth(self) -> int: ...
    @property
    def seed(self) -> int: ...
    @property
    def unseen_prior(self) -> str: ...
    @property
    def place_coupling(self) -> bool: ...


def place_configured(
    snapshots: Sequence[dict],
    config: PlacementSettings,
    maps: Sequence[Tensor],
    shift: dict[tuple[int, int], float] | None = None,
) -> list[dict]:
    """:func:`place_members` with a run's settings (generator size, ``seed``,
    ``unseen_prior``, ``place_coupling``) and an optional ``shift``."""
    return place_members(
        snapshots,
        config.dims,
        config.width,
        config.depth,
        maps,
        seed=config.seed,
        prior=config.unseen_prior,
        coupling=config.place_coupling,
        shift=shift,
    )


def member_moments(
    state: dict, dims: int, width: int, depth: int, n_particles: int, seed: int
) -> tuple[Tensor, Tensor]:
    """Centroid ``(dims,)`` and covariance ``(dims, dims)`` (float64, Bmad
    units) of one member, from ``n_particles`` quasi-random particles drawn
    with ``seed`` (the same particles every call)."""
    gen = BeamGenerator(dims, width=width, depth=depth, scale=torch.ones(dims))
    gen.load_state_dict(state)
    gen.requires_grad_(False)
    g = torch.Generator().manual_seed(seed)
    x = gen(n_particles, generator=g, quasi_random=True).to(torch.float64)
    return x.mean(0), torch.cov(x.T)


def _fold(state: dict, a: Tensor, mu: Tensor) -> dict:
    """State dict of the generator whose particles are ``mu + A (x - mu)``.

    ``x = s0 (b + e^l u)`` with ``u = mix base + Q q + W h + c``: with
    ``D = diag(s0 e^l)`` the new ``u' = D^-1 A D u`` (mixing matrix, quadratic
    term and last layer multiplied by ``M = D^-1 A D``) and
    ``b' = (A s0 b + (I - A) mu) / s0``.
    """
    new = {k: v.clone() for k, v in state.items()}
    dtype = state["mix"].dtype
    s0 = state["ref_scale"].to(torch.float64)
    d = s0 * state["log_scale"].to(torch.float64).exp()
    m = a / d[:, None] * d[None, :]
    new["mix"] = (m @ state["mix"].to(torch.float64)).to(dtype)
    if "quad" in state:  # the quadratic term, like the mixing matrix
        new["quad"] = (m @ state["quad"].to(torch.float64)).to(dtype)
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
