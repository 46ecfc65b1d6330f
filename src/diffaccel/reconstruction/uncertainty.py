"""Calibrated uncertainty of reconstructed beam moments (linear-Gaussian moment space).

The screen centroids and second moments are linear in the beam centroid ``mu`` and
covariance ``Sigma``: at setting ``k`` with first-order map ``R_k`` the screen
moments are ``(R_k Sigma R_k^T)`` restricted to (x, y), so
``<xx>_k = a_k Sigma a_k^T``, ``<xy>_k = a_k Sigma b_k^T``, ``<yy>_k = b_k Sigma
b_k^T`` with ``a_k, b_k`` the x and y rows of ``R_k``. Stacking every training
setting of every scan gives a linear operator ``A`` from the upper-triangular
elements ``theta`` of ``Sigma`` to the screen moments. With a Gaussian prior on
``theta`` (relative width ``prior_relative``: "the data alone set the value") and
Gaussian moment errors, the posterior covariance is
``(A^T W A + P^-1)^-1``: directions ``A`` sees shrink to the propagated
measurement error, directions it does not see keep the prior width.

The moment errors are estimated from the data themselves: the residuals between
the measured and the reconstruction's predicted image moments at the training
settings, scaled as ``r * <xx>_k`` (second moments; ``r * sqrt(<xx><yy>/2)`` for
``<xy>``) and ``r * sqrt(<xx>_k)`` (centroids), with ``r`` per scan from the
residual sum of squares left after the least-squares fit over its degrees of
freedom ``n - p_eff`` (``p_eff`` the trace of the hat matrix): shot noise, finite
counts and whatever no change of the beam's moments explains, so the error scale
is calibrated on the data rather than assumed. The part of the residuals that a
change of the beam *does* explain is the reconstruction's own bias (a training
that leaves every size 2 % large shows up as image moments 4 % above the
measured ones at every setting): the least-squares shift of ``theta`` that the
residuals ask for is added as a bias variance ``shift shift^T``. Image moments
are beam moments plus the variance of the point spread the image was formed
with; where the forward model's spread exceeds the data's (``psf_excess``, e.g.
cloud-in-cell 1/6 pixel^2 against histograms, 1/12) the excess is removed from
the predicted moments first, so it is not mistaken for a change of the beam.

Moment uncertainties (rms sizes, emittances, Twiss...) come from draws of
``(mu, Sigma)`` of this posterior, each moment computed from its own sub-block
(no projection of the full matrix, so an unconstrained z-x correlation cannot
disturb the transverse emittances).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor

from diffaccel.reconstruction.metrics import covariance_moments
from diffaccel.reconstruction.screen_moments import (
    centroid_design,
    covariance_design,
    pair_indices,
)

__all__ = [
    "MOMENT_WINDOW",
    "MomentUncertainty",
    "analyse_moments",
    "covariance_moments",
    "image_moments",
    "linear_posterior",
]

#: Moments whose draws :func:`covariance_moments` returns.
MOMENT_KEYS = (
    "centroid",
    "rms",
    "cov",
    "corr",
    "emit_x",
    "emit_y",
    "emit_z",
    "emit_4d",
    "emit_6d",
    "beta_x",
    "beta_y",
    "alpha_x",
    "alpha_y",
)


#: Half-width, in rms of the simulated image, of the box around its centroid in
#: which measured and simulated image moments are compared (the same box for
#: both). A whole frame's second moment weights each pixel's noise by its
#: squared distance from the centroid, so a camera's residual background and
#: read noise, zero on average, would dominate it; a box of 4 rms cuts a halo
#: 2.5 times wider than the core (12 % of the particles) at 2 of its rms, where
#: the windowed moments then measure the exact tail profile, not the beam's
#: second moments (such a beam's posterior emittance std: 5-6 % in a 4-rms box,
#: 3 % in a 6-rms box, 3 % on the whole frame).
MOMENT_WINDOW = 6.0


def image_moments(
    images: Tensor,
    xs: Tensor,
    ys: Tensor,
    window: Tensor | None = None,
    dtype: torch.dtype | None = torch.float64,
) -> Tensor:
    """Centroids and second central moments of screen images.

    Args:
        images: Images ``(K, H, W)`` (any normalisation, positive sums).
            Pixels are signed weights: the zero-mean negative noise of a
            background-subtracted image is kept, so that the moments stay
            linear in the image (unbiased by the noise); clipping it at 0 would
            leave a positive floor that widens the second moments.
        xs: Pixel-centre x [m] ``(W,)``; ``ys``: pixel-centre y [m] ``(H,)``.
        window: Optional 0/1 weights ``(K, H, W)``: only these pixels count
            (the same window for measured and predicted images keeps far-off
            background from dominating the second moments).
        dtype: Arithmetic dtype; None keeps the images' own (the training's
            moment term, differentiable on the device).

    Returns:
        ``(K, 5)``: ``<x>, <y>, <xx>, <xy>, <yy>`` [m, m, m^2...].
    """
    dtype = images.dtype if dtype is None else dtype
    w = images.to(dtype)
    if window is not None:
        w = w * window.to(dtype)
    total = w.sum((-2, -1)).clamp_min(torch.finfo(dtype).tiny)
    xs = xs.to(dtype)
    ys = ys.to(dtype)
    px = w.sum(-2) / total[:, None]  # (K, W)
    py = w.sum(-1) / total[:, None]  # (K, H)
    mx = (px * xs).sum(-1)
    my = (py * ys).sum(-1)
    dx = xs[None, :] - mx[:, None]  # (K, W)
    dy = ys[None, :] - my[:, None]  # (K, H)
    sxx = (px * dx * dx).sum(-1)
    syy = (py * dy * dy).sum(-1)
    sxy = (w * dy[:, :, None] * dx[:, None, :]).sum((-2, -1)) / total
    return torch.stack([mx, my, sxx, sxy, syy], -1)


def moment_window(images: Tensor, xs: Tensor, ys: Tensor, n_sigma: float) -> Tensor:
    """Box of ``n_sigma`` rms around each image's centroid, ``(K, H, W)`` 0/1."""
    m = image_moments(images, xs, ys)
    hx = n_sigma * m[:, 2].clamp_min(0).sqrt()
    hy = n_sigma * m[:, 4].clamp_min(0).sqrt()
    inx = (xs[None, :].double() - m[:, 0:1]).abs() <= hx[:, None]
    iny = (ys[None, :].double() - m[:, 1:2]).abs() <= hy[:, None]
    return (iny[:, :, None] & inx[:, None, :]).double()


def linear_posterior(
    design: Tensor,
    residual: Tensor,
    scale: Tensor,
    prior_std: Tensor,
    groups: Tensor | None = None,
    *,
    min_dof: float = 1.0,
    inflation: float = 1.0,
    fitted_residuals: bool = True,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Gaussian posterior of a linear model with error scales fitted to residuals.

    Model: ``residual = design @ delta + eps``, ``eps_m ~ N(0, (r_g scale_m)^2)``
    with one unknown ``r_g`` per group ``g`` of rows, prior
    ``delta ~ N(0, diag(prior_std^2))``. ``r_g^2 = RSS_g / (n_g - p_eff,g)`` with
    ``RSS_g`` the scaled residual sum of squares left after the fit (what
    ``design @ shift`` does not explain) and ``p_eff,g`` the group's share of
    the trace of the hat matrix (fixed-point iteration).

    Args:
        design: ``(M, P)``.
        residual: Observed minus predicted ``(M,)`` (the prediction at the
            current estimate, ``delta = 0``).
        scale: Relative error scale of each row ``(M,)`` (> 0).
        prior_std: Prior standard deviation of each parameter ``(P,)`` (> 0).
        groups: Integer group of each row ``(M,)``; default one group.
        min_dof: Lower bound of the degrees of freedom of each group.
        inflation: Factor on the fitted error scales ``r_g`` before the final
            posterior (widens what the data constrain, not the prior).
        fitted_residuals: Take ``RSS_g`` after the fit (default). ``False``
            takes it at ``delta = 0``: a systematic offset that a parameter
            shift explains then also counts as noise (the first version; on
            6D scans it made the error scale 10-100x too large, see
            ``docs/methods/uncertainty.md``).

    Returns:
        ``(cov (P, P), shift (P,), r (G,), dof (G,))``: posterior covariance, the
        posterior mean shift of the parameters, error scale and degrees of
        freedom per group.

    Example:
        >>> a = torch.tensor([[1.0, 0.0], [1.0, 0.0], [1.0, 0.0]], dtype=torch.float64)
        >>> cov, *_ = linear_posterior(a, torch.tensor([0.1, -0.1, 0.0]).double(),
        ...     torch.ones(3).double(), torch.tensor([10.0, 10.0]).double())
        >>> round(float(cov[1, 1].sqrt()), 6)  # unseen parameter keeps its prior
        10.0
    """
    a = design.to(torch.float64)
    e = residual.to(torch.float64)
    s = scale.to(torch.float64)
    p = prior_std.to(torch.float64)
    m = a.shape[0]
    g = torch.zeros(m, dtype=torch.long) if groups is None else groups.long()
    n_groups = int(g.max()) + 1
    aw = a * p[None, :] / s[:, None]  # whitened parameters, scaled rows
    ew = e / s
    n_g = torch.bincount(g, minlength=n_groups).to(torch.float64)
    rss_g = torch.zeros(n_groups, dtype=torch.float64).index_add_(0, g, ew**2)
    r2 = (rss_g / n_g.clamp_min(1)).clamp_min(1e-30)
    for _ in range(20):
        sw = r2[g].rsqrt()  # sqrt of the row weights
        _, hat, _, fitted = _whitened_posterior(aw * sw[:, None], ew * sw)
        # diagonal of the hat matrix, summed per group
        p_eff = torch.zeros(n_groups, dtype=torch.float64).index_add_(0, g, hat)
        if fitted_residuals:
            fit = fitted / sw  # what the fit leaves, in scaled units
            rss_g = torch.zeros(n_groups, dtype=torch.float64).index_add_(0, g, fit**2)
        dof = (n_g - p_eff).clamp_min(min_dof)
        new = (rss_g / dof).clamp_min(1e-30)
        if torch.allclose(new, r2, rtol=1e-6):
            r2 = new
            break
        r2 = new
    r2 = r2 * inflation**2
    sw = r2[g].rsqrt()
    cov_u, _, shift_u, _ = _whitened_posterior(aw * sw[:, None], ew * sw)
    cov = cov_u * p[:, None] * p[None, :]
    return cov, shift_u * p, r2.sqrt(), dof


def _whitened_posterior(b: Tensor, e: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Posterior of ``e = b @ u + noise``, ``u ~ N(0, I)``, unit noise.

    From the thin SVD ``b = U S V^T`` (``d = 1 / (1 + s^2)``), without forming
    ``I + b^T b``: covariance ``I - V V^T + V diag(d) V^T`` (exactly ``I`` on
    what ``b`` does not see, never above it), hat diagonal
    ``sum_k U_mk^2 s_k^2 d_k``, mean ``V diag(s d) U^T e`` and the residual
    left by it. Accurate however ill-conditioned: a group of rows fitted almost
    exactly gives weights ~1e17, where an LU inverse of ``I + b^T b`` failed
    with a zero pivot or returned variances above the prior.

    Shapes: ``b (M, P)``, ``e (M,)`` -> ``((P, P), (M,), (P,), (M,))``.
    """
    u, s, vh = torch.linalg.svd(b, full_matrices=False)
    v = vh.T
    d = 1.0 / (1.0 + s**2)
    eye = torch.eye(b.shape[1], dtype=b.dtype, device=b.device)
    cov = eye - v @ vh + (v * d) @ vh
    cov = 0.5 * (cov + cov.T)
    hat = (u**2 * (s**2 * d)).sum(-1)
    ue = u.T @ e
    shift = v @ (s * d * ue)
    fitted = e - u @ (s**2 * d * ue)
    return cov, hat, shift, fitted


@dataclass
class MomentUncertainty:
    """Posterior of the beam centroid and covariance from the moment-space analysis.

    Args:
        dims: Reconstructed coordinates (4 or 6).
        mean: Centroid of the reconstruction ``(6,)`` [Bmad units].
        cov: Covariance of the reconstruction ``(6, 6)``.
        theta_cov: Posterior covariance of the upper-triangular covariance
            elements ``(P, P)`` (order of :func:`pair_indices`).
        centroid_cov: Posterior covariance of the centroid ``(dims, dims)``.
        diagnostics: JSON extras (error scales, degrees of freedom, rank,
            constrained fraction of each parameter).
    """

    dims: int
    mean: Tensor
    cov: Tensor
    theta_cov: Tensor
    centroid_cov: Tensor
    diagnostics: dict = field(default_factory=dict)

    def draw(self, n: int, generator: torch.Generator | None = None) -> tuple:
        """Posterior draws ``(mu (n, 6), cov (n, 6, 6))`` (float64).

        Coordinates beyond ``dims`` keep the reconstruction's (zero) values.
        """
        d = self.dims
        pairs = pair_indices(d)
        lt = _safe_cholesky(self.theta_cov)
        lc = _safe_cholesky(self.centroid_cov)
        zt = torch.randn(n, lt.shape[0], generator=generator, dtype=torch.float64)
        zc = torch.randn(n, d, generator=generator, dtype=torch.float64)
        dtheta = zt @ lt.T
        dmu = zc @ lc.T
        cov = self.cov.to(torch.float64).expand(n, 6, 6).clone()
        for p, (i, j) in enumerate(pairs):
            cov[:, i, j] += dtheta[:, p]
            if i != j:
                cov[:, j, i] += dtheta[:, p]
        mu = self.mean.to(torch.float64).expand(n, 6).clone()
        mu[:, :d] += dmu
        return mu, cov

    def moment_std(self, n_draws: int = 2000, seed: int = 0) -> dict[str, Tensor]:
        """Posterior std of every moment of :func:`covariance_moments`."""
        g = torch.Generator().manual_seed(seed)
        mu, cov = self.draw(n_draws, g)
        moms = covariance_moments(mu, cov)
        return {k: v.std(0) for k, v in moms.items()}

    def to_dict(self) -> dict:
        """JSON-ready form (inverse of :meth:`from_dict`)."""
        return {
            "dims": self.dims,
            "mean": self.mean.tolist(),
            "cov": self.cov.tolist(),
            "theta_cov": self.theta_cov.tolist(),
            "centroid_cov": self.centroid_cov.tolist(),
            "diagnostics": self.diagnostics,
        }

    @classmethod
    def from_dict(cls, d: dict) -> MomentUncertainty:
        """Inverse of :meth:`to_dict`."""
        f64 = torch.float64
        return cls(
            dims=int(d["dims"]),
            mean=torch.tensor(d["mean"], dtype=f64),
            cov=torch.tensor(d["cov"], dtype=f64),
            theta_cov=torch.tensor(d["theta_cov"], dtype=f64),
            centroid_cov=torch.tensor(d["centroid_cov"], dtype=f64),
            diagnostics=dict(d.get("diagnostics", {})),
        )


def _safe_cholesky(c: Tensor) -> Tensor:
    c = 0.5 * (c + c.T)
    vals, vecs = torch.linalg.eigh(c)
    return vecs * vals.clamp_min(0).sqrt()[None, :]


def analyse_moments(
    maps: Sequence[Tensor],
    measured: Sequence[Tensor],
    predicted: Sequence[Tensor],
    pixel_axes: Sequence[tuple[Tensor, Tensor]],
    mean: Tensor,
    cov: Tensor,
    dims: int,
    *,
    prior_relative: float = 1.0,
    prior_correlation: float = 0.5,
    window_sigma: float = MOMENT_WINDOW,
    bias_term: bool = True,
    inflation: float = 1.0,
    floor_relative: float = 0.0,
    fitted_residuals: bool = True,
    psf_excess: Sequence[tuple[float, float]] | None = None,
) -> MomentUncertainty:
    """Moment-space posterior of a reconstruction from its training images.

    Args:
        maps: First-order transfer matrices of each scan's training settings
            ``(K_s, 6, 6)``.
        measured: Measured training images of each scan ``(K_s, H_s, W_s)``.
        predicted: The reconstruction's images at the same settings.
        pixel_axes: ``(xs (W_s,), ys (H_s,))`` pixel centres [m] of each scan.
        mean: Reconstructed centroid ``(6,)``; ``cov``: covariance ``(6, 6)``.
        dims: Reconstructed coordinates (4 or 6).
        prior_relative: Prior std of each variance relative to its
            reconstructed value (what an unconstrained direction keeps: 1.0 is
            "known to a factor of ~2 in rms").
        prior_correlation: Prior std of each correlation coefficient.
        window_sigma: Moments are computed in a box of this many predicted rms
            around the predicted centroid (same box for both images;
            :data:`MOMENT_WINDOW`).
        bias_term: Add the squared least-squares shift of the parameters that
            the residuals ask for (a data-driven bias floor).
        inflation: Factor on the posterior std of the data-constrained part
            (``1``: the residual-based error scale as it is).
        floor_relative: Model-error floor: every second moment gets an extra
            independent error of this fraction (variances ``2 f Sigma_ii``,
            covariances ``f sqrt(Sigma_ii Sigma_jj)``), centroids ``f`` rms.
        psf_excess: Per scan, the variance ``(x, y)`` [m^2] by which the point
            spread of the predicted images exceeds that of the measured ones
            (a known difference of the image formation, not of the beam: e.g.
            cloud-in-cell deposition, 1/6 pixel^2, against histogram data,
            1/12); subtracted from the predicted ``<xx>``, ``<yy>``.

    Returns:
        The :class:`MomentUncertainty`.
    """
    f64 = torch.float64
    cov = cov.to(f64)
    mean = mean.to(f64)
    sd = cov.diagonal()[:dims].clamp_min(1e-300).sqrt()
    pairs = pair_indices(dims)
    prior = torch.tensor(
        [
            prior_relative * float(sd[i] ** 2)
            if i == j
            else prior_correlation * float(sd[i] * sd[j])
            for i, j in pairs
        ],
        dtype=f64,
    )
    rows_c, res_c, sc_c, grp_c = [], [], [], []
    rows_m, res_m, sc_m, grp_m = [], [], [], []
    for s, (r, meas, pred, (xs, ys)) in enumerate(
        zip(maps, measured, predicted, pixel_axes, strict=True)
    ):
        r = r.to(f64)
        win = moment_window(pred, xs, ys, window_sigma)
        mm = image_moments(meas, xs, ys, win)
        pm = image_moments(pred, xs, ys, win)
        if psf_excess is not None:  # a point spread adds its variance
            pm[:, 2] -= psf_excess[s][0]
            pm[:, 4] -= psf_excess[s][1]
        k = r.shape[0]
        rows_c.append(centroid_design(r, dims))
        res_c.append((mm[:, :2] - pm[:, :2]).reshape(-1))
        sc_c.append(pm[:, [2, 4]].clamp_min(1e-300).sqrt().reshape(-1))
        grp_c.append(torch.full((2 * k,), s))
        rows_m.append(covariance_design(r, dims))
        res_m.append((mm[:, 2:] - pm[:, 2:]).reshape(-1))
        sxy = (pm[:, 2] * pm[:, 4]).clamp_min(1e-300).sqrt() / math.sqrt(2.0)
        sc_m.append(torch.stack([pm[:, 2], sxy, pm[:, 4]], -1).reshape(-1))
        grp_m.append(torch.full((3 * k,), s))
    theta_cov, shift, r_m, dof_m = linear_posterior(
        torch.cat(rows_m),
        torch.cat(res_m),
        torch.cat(sc_m),
        prior,
        torch.cat(grp_m),
        inflation=inflation,
        fitted_residuals=fitted_residuals,
    )
    cen_prior = sd.clone()  # a centroid off by one rms is plausible a priori
    cen_cov, cen_shift, r_c, dof_c = linear_posterior(
        torch.cat(rows_c),
        torch.cat(res_c),
        torch.cat(sc_c),
        cen_prior,
        torch.cat(grp_c),
        inflation=inflation,
        fitted_residuals=fitted_residuals,
    )
    if bias_term:
        theta_cov = theta_cov + torch.outer(shift, shift)
        cen_cov = cen_cov + torch.outer(cen_shift, cen_shift)
    if floor_relative > 0:
        floor = torch.tensor(
            [
                (2.0 if i == j else 1.0) * floor_relative * float(sd[i] * sd[j])
                for i, j in pairs
            ],
            dtype=f64,
        )
        theta_cov = theta_cov + torch.diag(floor**2)
        cen_cov = cen_cov + torch.diag((floor_relative * sd) ** 2)
    post_sd = theta_cov.diagonal().clamp_min(0).sqrt()
    names = ("x", "px", "y", "py", "z", "pz")
    constrained = {
        f"{names[i]}.{names[j]}": float(1.0 - post_sd[p] / prior[p])
        for p, (i, j) in enumerate(pairs)
    }
    diagnostics = {
        "method": "moment-space linear-Gaussian posterior",
        "error_scale_second_moments": r_m.tolist(),
        "dof_second_moments": dof_m.tolist(),
        "error_scale_centroids": r_c.tolist(),
        "dof_centroids": dof_c.tolist(),
        "prior_relative": prior_relative,
        "prior_correlation": prior_correlation,
        "bias_term": bias_term,
        "inflation": inflation,
        "floor_relative": floor_relative,
        "constrained_fraction": constrained,
    }
    return MomentUncertainty(dims, mean, cov, theta_cov, cen_cov, diagnostics)
