"""Gaussian first guess of a beam from the second moments of quad-scan images."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from diffaccel.dynamics.linalg import lstsq
from diffaccel.reconstruction.forward import ScreenForwardModel
from diffaccel.reconstruction.screen_moments import covariance_design, symmetric

#: Transverse prior widths of the entropy term in units of the widths of the
#: Gaussian fitted to the image moments: broad enough to bound only what the
#: images leave free (a seen coordinate's fitted width is 1/3 of its prior's).
PRIOR_FACTOR = 3.0


@dataclass(frozen=True)
class GaussianGuess:
    """Centroid and covariance of a Gaussian beam fitted to image moments.

    Args:
        mean: Centroid in Bmad coordinates ``(6,)`` float64.
        cov: Covariance ``(6, 6)`` float64; rows and columns of coordinates
            the scans do not see (z, pz after quadrupoles and drifts only) are
            zero.
    """

    mean: Tensor
    cov: Tensor

    def generator_init(
        self,
        dims: int,
        longitudinal_scale: tuple[float, float],
        prior_factor: float = PRIOR_FACTOR,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Initial scale, offset, correlation and prior widths for a generator.

        A longitudinal coordinate the scans see (fitted variance > 0: z with a
        deflecting cavity, pz with dispersion) starts from the fitted Gaussian
        like the transverse ones; one they do not see starts uncorrelated with
        rms ``longitudinal_scale``.

        Returns:
            ``scale (dims,)``, ``offset (dims,)``, ``correlation (dims, dims)`` and
            ``prior_std (dims,)`` (``prior_factor`` times the fitted widths;
            unseen longitudinal coordinates: ``longitudinal_scale``), all float64.
        """
        cov = self.cov[:dims, :dims].clone()
        mean = self.mean[:dims].clone()
        seen = [True] * dims
        if dims == 6:
            for i in (4, 5):
                if not float(cov[i, i]) > 0:
                    seen[i] = False
                    cov[i, :] = 0.0
                    cov[:, i] = 0.0
                    cov[i, i] = longitudinal_scale[i - 4] ** 2
        scale = cov.diagonal().sqrt()
        corr = cov / (scale[:, None] * scale[None, :])
        prior = scale.clone()
        prior[torch.tensor(seen)] *= prior_factor
        return scale, mean, corr, prior


#: Largest rms size [m] and rms or centroid angle [rad] (px, py) of a
#: plausible initial guess. Beams a quadrupole scan images are mm-sized with
#: mrad divergences (the shared files: rms 0.5-5 mm, 0.3-3 mrad); a guess 10-100
#: times beyond these comes from images read with the wrong scale (a pixel size
#: in mm typed as m gives rms divergences of 0.2-2 rad, which the tracking and
#: the openPMD writer cannot hold: |px| >= 1 + pz is no forward motion).
MAX_GUESS_SIZE = 0.05
MAX_GUESS_ANGLE = 0.05


def check_guess(
    guess: GaussianGuess, scans: Sequence[str] = (), focusing_scanned: bool = True
) -> None:
    """Refuse an initial guess whose beam no quadrupole scan could image.

    Args:
        guess: The fit of :func:`fit_gaussian`.
        scans: Names of the scans it was fitted to (named in the error).
        focusing_scanned: Whether any scan varies a focusing strength
            (quadrupole ``k1``, solenoid ``ks``); without one the angles are
            not determined, and the error says so first.

    Raises:
        ValueError: if an rms size (x, y) exceeds :data:`MAX_GUESS_SIZE` or an
            rms or centroid angle (px, py) exceeds :data:`MAX_GUESS_ANGLE`,
            naming the moment, its value and the likely causes.
    """
    rms = guess.cov.diagonal().clamp_min(0.0).sqrt()
    found = []
    for i, name in ((0, "x"), (2, "y")):
        if not float(rms[i]) <= MAX_GUESS_SIZE:
            found.append(f"rms {name} {float(rms[i]):.3g} m")
    for i, name in ((1, "px"), (3, "py")):
        if not float(rms[i]) <= MAX_GUESS_ANGLE:
            found.append(f"rms {name} {float(rms[i]):.3g} rad")
        if not abs(float(guess.mean[i])) <= MAX_GUESS_ANGLE:
            found.append(f"mean {name} {float(guess.mean[i]):.3g} rad")
    if found:
        where = f" of scan(s) {', '.join(repr(s) for s in scans)}" if scans else ""
        first = (
            "check the screen calibration first (pixel_size_x/y and center_x/y "
            "are in m: 1 mm is 1e-3), then the settings' units, the beamline "
            "(drift to the screen) and p0c."
        )
        if not focusing_scanned:
            first = (
                "no scan varies a focusing strength (a quadrupole's k1 or a "
                "solenoid's ks), so the images cannot tell the beam's angles: add "
                "a quadrupole scan; if one is there, " + first
            )
        raise ValueError(
            f"the image moments{where} imply an unphysical beam ("
            + ", ".join(found)
            + f"; expected rms sizes <= {MAX_GUESS_SIZE:g} m and angles <= "
            f"{MAX_GUESS_ANGLE:g} rad): " + first
        )


def _psd_2x2(s00: Tensor, s01: Tensor, s11: Tensor, floor: float) -> tuple:
    """Project a 2x2 (s00, s01, s11) onto positive definite with |r| <= 0.95."""
    s00 = s00.clamp_min(floor**2)
    s11 = s11.clamp_min(floor**2 * 1e-6)
    lim = 0.95 * (s00 * s11).sqrt()
    return s00, s01.clamp(-lim, lim), s11


def _observed(rows: Tensor, tolerance: float = 1e-3) -> list[int]:
    """Coordinates whose column of the screen rows ``(M, 6)`` is not ~0.

    Positions (x, y, z) are compared with the largest x/y column, momenta
    (px, py, pz) with the largest px/py column.
    """
    col = rows.abs().amax(0)
    ref_pos = float(col[[0, 2]].max())
    ref_mom = float(col[[1, 3]].max())
    refs = (ref_pos, ref_mom, ref_pos, ref_mom, ref_pos, ref_mom)
    return [i for i in range(6) if float(col[i]) > tolerance * refs[i]]


def _nearest_correlation(cov: Tensor, max_corr: float = 0.98) -> Tensor:
    """``cov`` made positive definite in correlation space (eigenvalues clipped)."""
    d = cov.diagonal().clamp_min(1e-300).sqrt()
    c = cov / (d[:, None] * d[None, :])
    c = 0.5 * (c + c.T)
    w, v = torch.linalg.eigh(c)
    c = v @ torch.diag(w.clamp_min(1.0 - max_corr)) @ v.T
    e = c.diagonal().sqrt()
    c = c / (e[:, None] * e[None, :])
    return c * (d[:, None] * d[None, :])


#: Weight of ``-log det`` against the squared moment residuals (in units of
#: the mean screen variance) in :func:`_max_entropy_fit`. The linear moments
#: are not exact (chromatic focusing, curved chirps), and a weak weight lets
#: the weakly seen directions (x-y coupling, py-z) follow those errors:
#: a synthetic shared-file-like beam starts with transverse correlations off by 0.46
#: at 1e-3, 0.39 at 2e-3, 0.035 at 3e-3. A strong one widens what is seen:
#: the shared 6D file starts with rms py +8.7 % and correlations within 0.09 at
#: 3e-3, +10.6 % and 0.12 at 5e-3 (with the 6D default blur).
ENTROPY_WEIGHT = 3e-3


def _max_entropy_fit(
    start: Tensor, design: Tensor, target: Tensor, iu: Tensor, iterations: int = 60
) -> Tensor:
    """The covariance that fits the screen moments, largest ``det`` where they
    leave it free.

    Minimises ``|design vech(S) - target|^2 - w log det S`` (``w`` =
    :data:`ENTROPY_WEIGHT`) over positive definite ``S``: a convex problem,
    solved by Newton steps from ``start`` that keep ``S`` positive definite.
    The plain least squares leaves the directions the scans do not see (pz
    variance against the px-pz covariance behind a dipole) at its
    minimum-norm point, often not positive definite, and the projection onto
    positive definite matrices then spoils seen entries too: on the shared 6D
    file the start had rms pz -60 % and a correlation off by 0.86; on the
    synthetic shared-file-like beam pz -89 %, and that start ends its
    reconstruction at rms pz -9 % where the truth's covariance as the start
    gives -0.8 %. The largest determinant is the
    maximum-entropy Gaussian among those the moments allow. Returns ``start``
    where no step improves on it.

    Shapes:
        ``start (n, n)``, ``design (M, n (n + 1) / 2)`` (columns: the
        upper-triangular entries ``iu``), ``target (M,)`` -> ``(n, n)``.
    """
    n = start.shape[0]
    m = iu.shape[1]
    d = start.diagonal().sqrt()
    # unknowns in units of the start's sizes (every entry of order one)
    a = design * (d[iu[0]] * d[iu[1]])
    basis = start.new_zeros(m, n, n)
    basis[torch.arange(m), iu[0], iu[1]] = 1.0
    basis[torch.arange(m), iu[1], iu[0]] = 1.0

    def objective(v: Tensor) -> float:
        c, info = torch.linalg.cholesky_ex(symmetric(v, iu, n))
        if int(info) != 0:
            return math.inf
        r = a @ v - target
        return float(r @ r) - ENTROPY_WEIGHT * 2 * float(c.diagonal().log().sum())

    v = (start / (d[:, None] * d[None, :]))[iu[0], iu[1]].clone()
    value = objective(v)
    if not math.isfinite(value):
        return start
    for _ in range(iterations):
        p = torch.linalg.inv(symmetric(v, iu, n))
        pe = p @ basis  # (m, n, n)
        grad = 2 * a.T @ (a @ v - target) - ENTROPY_WEIGHT * torch.einsum("aii->a", pe)
        hess = 2 * a.T @ a + ENTROPY_WEIGHT * torch.einsum("aij,bji->ab", pe, pe)
        step = torch.linalg.solve(hess, -grad)
        decrease = float(grad @ step)  # < 0
        if -decrease < 1e-14 * max(1.0, abs(value)):
            break
        t = 1.0
        for _half in range(40):
            trial = objective(v + t * step)
            if trial <= value + 1e-4 * t * decrease:
                break
            t /= 2
        else:
            break
        v, value = v + t * step, trial
    return symmetric(v, iu, n) * (d[:, None] * d[None, :])


def fit_gaussian(
    forward: ScreenForwardModel | Sequence[ScreenForwardModel],
    images: Tensor | Sequence[Tensor],
    settings: Tensor | Sequence[Tensor],
    maps: Sequence[Tensor] | None = None,
) -> GaussianGuess:
    """Fit the centroid and covariance of a beam to image moments of one or more scans.

    Linear optics: for each setting the affine map ``(R_k, c_k)`` comes from the
    forward model, the screen centroid is ``R_k mean + c_k`` and the screen second
    moments are ``R_k Sigma R_k^T``; the measured centroids, ``<x^2>``,
    ``<y^2>`` and ``<xy>`` of the images (minus the blur the forward model adds)
    give a linear least-squares problem for the centroid and covariance entries
    of the coordinates the scans see (x, px, y, py; z with a deflecting cavity,
    pz with dispersion). The result is projected onto a positive definite
    matrix; it is a starting point, not a reconstruction. Where z or pz is seen,
    the covariance is then refitted to the moments within the positive definite
    matrices, at the largest determinant along the directions the moments leave
    free (:func:`_max_entropy_fit`). Unseen coordinates get zero mean and zero
    (co)variance.

    Args:
        forward: Forward model of each scan (or one model).
        images: Sum-normalised images of each scan.
        settings: Settings of those images, one tensor per scan.
        maps: Affine maps ``(K_s, 7, 7)`` of each scan from
            :meth:`ScreenForwardModel.transfer_maps` when the caller has them
            already; computed here otherwise.

    Shapes:
        Scan ``s``: ``images (K_s, H_s, W_s)``, ``settings (K_s, P_s)``.

    Returns:
        A :class:`GaussianGuess` (float64, on the CPU).
    """
    forwards = list(forward) if isinstance(forward, list | tuple) else [forward]
    image_list = list(images) if isinstance(images, list | tuple) else [images]
    setting_list = list(settings) if isinstance(settings, list | tuple) else [settings]
    r_all, mx_all, my_all, vxx_all, vyy_all, vxy_all = ([] for _ in range(6))
    floors, drift = [], 0.0
    map_list = list(maps) if maps is not None else [None] * len(forwards)
    if not len(forwards) == len(image_list) == len(setting_list) == len(map_list):
        raise ValueError(
            f"one forward model, image stack and settings per scan; got "
            f"{len(forwards)}, {len(image_list)} and {len(setting_list)}"
            + ("" if maps is None else f" (and {len(map_list)} maps)")
            + "."
        )
    for fwd, imgs, sets, r in zip(
        forwards, image_list, setting_list, map_list, strict=True
    ):
        img = imgs.detach().to("cpu", torch.float64)
        if img.ndim != 3 or img.shape[0] != sets.shape[0]:
            raise ValueError(
                f"images {tuple(img.shape)} must be (K, H, W) with one image per "
                f"setting of settings {tuple(sets.shape)}."
            )
        if not bool(torch.isfinite(img).all()) or not bool(
            (img.sum((-2, -1)) > 0).all()
        ):
            raise ValueError("images must be finite and each sum to > 0.")
        img = img / img.sum((-2, -1), keepdim=True).clamp_min(1e-300)
        xs, ys = fwd.screen.pixel_centers(dtype=torch.float64)
        px = img.sum(-2)  # (K, W)
        py = img.sum(-1)  # (K, H)
        mx = (px * xs).sum(-1)
        my = (py * ys).sum(-1)
        blur_x, blur_y = (b**2 for b in fwd.blur_sigma())
        vxx_all.append((px * (xs - mx[:, None]) ** 2).sum(-1) - blur_x)
        vyy_all.append((py * (ys - my[:, None]) ** 2).sum(-1) - blur_y)
        dx = xs[None, None, :] - mx[:, None, None]
        dy = ys[None, :, None] - my[:, None, None]
        vxy_all.append((img * dx * dy).sum((-2, -1)))
        if r is None:
            r = fwd.transfer_maps(sets)
        r = r.to("cpu", torch.float64)  # (K, 7, 7) affine
        # centroids less the orbit offsets of misaligned elements
        mx_all.append(mx - r[:, 0, 6])
        my_all.append(my - r[:, 2, 6])
        r_all.append(r[:, :6, :6])
        floors.append(float(xs.diff().abs().mean()) * 0.5)
        drift = max(drift, float(fwd.drift_length()))
    rx, ry = (torch.cat([r[:, row] for r in r_all]) for row in (0, 2))
    seen = sorted(set(range(4)) | set(_observed(torch.cat([rx, ry]))))
    rx, ry = rx[:, seen], ry[:, seen]
    n = len(seen)
    # centroid: [mx; my] - offsets = [rx; ry] @ mean
    a = torch.cat([rx, ry], 0)
    b = torch.cat([torch.cat(mx_all), torch.cat(my_all)], 0)
    mean_seen = lstsq(a, b[:, None])[:, 0]
    # second moments: the moment design of the seen entries of Sigma (rows
    # <xx>, <xy>, <yy> of each setting; columns in the order of triu_indices)
    iu = torch.triu_indices(n, n)
    a2 = covariance_design(torch.cat(r_all), seen)
    b2 = torch.stack(
        [torch.cat(vxx_all), torch.cat(vxy_all), torch.cat(vyy_all)], -1
    ).reshape(-1)
    # scale unknowns for conditioning
    col = a2.abs().amax(0).clamp_min(1e-300)
    sol = lstsq(a2 / col, b2[:, None])[:, 0] / col
    s_seen = symmetric(sol, iu, n)
    s4 = s_seen[:4, :4].clone()
    floor = min(floors)
    for p, q in ((0, 1), (2, 3)):
        s00, s01, s11 = _psd_2x2(s4[p, p], s4[p, q], s4[q, q], floor)
        if s4[q, q] <= 0 or s4[p, p] <= 0:
            # quad scan did not resolve the divergence: use a beam waist guess
            s11 = s00 / drift**2
            s01 = torch.zeros_like(s01)
        s4[p, p], s4[p, q], s4[q, p], s4[q, q] = s00, s01, s01, s11
    if torch.linalg.eigvalsh(s4).min() <= 0:
        s4[:2, 2:] = 0.0
        s4[2:, :2] = 0.0
    s_seen[:4, :4] = s4
    if n > 4:
        # A seen longitudinal variance the least squares leaves <= 0 (pz behind a
        # dipole downstream of the quadrupole is nearly degenerate with the
        # px-pz covariance): a quarter of the largest variance the screen sizes
        # allow, uncorrelated; the training then sets it.
        v_all = torch.cat([torch.cat(vxx_all), torch.cat(vyy_all)]).clamp_min(0)
        r_all = torch.cat([rx, ry], 0)
        for i in range(4, n):
            if s_seen[i, i] <= 0:
                coef = r_all[:, i].square()
                ok = coef > 1e-6 * coef.max()
                s_seen[i, :] = 0.0
                s_seen[:, i] = 0.0
                s_seen[i, i] = 0.25 * float((v_all[ok] / coef[ok]).min())
        s_seen = _nearest_correlation(s_seen)
        # residuals in units of the mean screen variance (as the least
        # squares above weighs them; per-row relative units let the tight
        # waists, where the linear moments are least accurate, dominate)
        unit = float(torch.cat([torch.cat(vxx_all), torch.cat(vyy_all)]).abs().mean())
        s_seen = _max_entropy_fit(s_seen, a2 / unit, b2 / unit, iu)
    mean = torch.zeros(6, dtype=torch.float64)
    mean[seen] = mean_seen
    cov = torch.zeros(6, 6, dtype=torch.float64)
    cov[torch.tensor(seen)[:, None], torch.tensor(seen)[None, :]] = s_seen
    return GaussianGuess(mean=mean, cov=cov)
