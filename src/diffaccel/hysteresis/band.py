"""Predictive bands of a fitted Preisach model: a Laplace approximation over densities.

For exact relays the normalised output is linear in the hysteron weights:
``y_n(t) = c0 + c1 u_n(t) + sum_i v_i s_i(t)`` with ``v_i = scale * w_i / sum(w)``.
With a Gaussian prior on ``v`` (a smooth density on the Preisach plane: squared
exponential in the coordinates the mesh is regular in,
:meth:`PreisachModel.plane_coordinates`, symmetrised for a symmetric model) and flat
priors on ``c0``, ``c1`` and the mean density, the posterior of these
parameters given the training rows is Gaussian; its covariance is what a
Laplace approximation about any fit of the same linear model would give. The
prior scale, its length scale on the plane and the noise level are chosen by
maximising the marginal likelihood of the training rows (type-II maximum
likelihood), not by looking at held-out rows.

The predictive variance of row ``t`` is ``f_t^T Sigma f_t + noise^2`` for the
row's features ``f_t``; :class:`LaplaceBand` keeps the leading eigen-directions
of ``Sigma`` (scaled by the square roots of their eigenvalues), so that the
variance of a long history is a handful of weighted sums of hysteron states,
streamed with the model's own output
(:class:`~diffaccel.hysteresis.stream.StreamPredictor`). A calibration factor
(>= 1), measured on validation rows held out of the training rows, scales the
whole band. Beyond the input range the features are the saturated states and
the unclipped ``u_n`` of the model's linear term, so the band widens with the
uncertainty of the slope; it holds no doubt about the saturation itself (that
no hysteron lies beyond the range).

Building the band never fails for want of a positive-definite covariance: larger
jitter, then a coarser band (offset, slope and mean density only) are tried in
turn, and a :class:`BandFallbackWarning` says which (see :func:`laplace_band`).
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor, nn

from diffaccel.dynamics import as_real_tensor
from diffaccel.hysteresis.preisach import PreisachModel
from diffaccel.hysteresis.stream import StreamPredictor, StreamSpec

__all__ = ["LENGTH_SCALES", "BandFallbackWarning", "LaplaceBand", "laplace_band"]

# length scales [1] of the density prior on the normalised plane, tried in turn
LENGTH_SCALES = (0.05, 0.1, 0.2, 0.4)
# prior variance of offset, slope and mean density [normalised output ^ 2]:
# broad against outputs normalised to [0, 1]
_FLAT = 100.0
# eigen-directions kept: enough for this fraction of the posterior variance
_KEEP = 0.9999
_MAX_DIRECTIONS = 48
# noise-variance floors [normalised output ^ 2] tried in turn
_JITTERS = (1e-12, 1e-10, 1e-8, 1e-6)
# least noise std of the coarse fallback band [normalised output]
_COARSE_NOISE_FLOOR = 1e-6


class BandFallbackWarning(UserWarning):
    """The predictive band needed a larger jitter or its coarser fallback model."""


class LaplaceBand(nn.Module):
    """Predictive standard deviation of a fitted Preisach model's output.

    Args:
        directions: Scaled eigen-directions of the parameter posterior in
            normalised output units, shape ``(K, M + 3)`` (offset, slope, mean
            density, then one entry per hysteron).
        noise_std: Measurement noise [normalised output units], >= 0.
        calibration: Factor (>= 1) applied to the whole standard deviation,
            measured on validation rows.

    Shapes:
        ``directions``: ``(K, M + 3)``; standard deviations ``(T,)``.
    """

    def __init__(
        self, directions: Tensor, noise_std: float | Tensor, calibration: float = 1.0
    ) -> None:
        super().__init__()
        if directions.ndim != 2 or directions.shape[1] < 4:
            raise ValueError(
                "LaplaceBand directions need shape (K, M + 3); got "
                f"{tuple(directions.shape)}."
            )
        for name, value, least in (
            ("noise_std", noise_std, 0.0),
            ("calibration", calibration, 1.0),
        ):
            v = torch.as_tensor(value, dtype=torch.float64)
            if v.ndim != 0 or not (torch.isfinite(v) and v >= least):
                raise ValueError(
                    f"{name} must be a finite number >= {least:g}; got {v.tolist()}."
                )
        self.register_buffer("directions", directions.detach().clone())
        self.register_buffer(
            "noise_std", torch.as_tensor(noise_std, dtype=directions.dtype).clone()
        )
        self.register_buffer(
            "calibration", torch.as_tensor(calibration, dtype=directions.dtype).clone()
        )
        #: why the band is not the plain Laplace band (``None``: it is); not saved
        self.fallback: str | None = None

    @property
    def n_hysterons(self) -> int:
        """Number of hysterons ``M`` the band belongs to."""
        return self.directions.shape[1] - 3

    def hysteron_weights(self, model: PreisachModel) -> tuple[Tensor, Tensor]:
        """Per-direction affine part ``(K, 2)`` and hysteron weights ``(K, M)``.

        ``f_t . d_k = d_k0 + d_k1 u_n(t) + sum_i W_ki s_i(t)``.
        """
        d = self.directions.to(model.alpha)
        if self.n_hysterons != model.alpha.numel():
            raise ValueError(
                f"band has {self.n_hysterons} hysterons, the model "
                f"{model.alpha.numel()}."
            )
        a = model.area / model.area.sum()
        v = d[:, 3:]
        if model.symmetric:
            v = 0.5 * (v + v[:, model.mirror])
        return d[:, :2], a * (d[:, 2:3] + v)

    def stream_spec(
        self, model: PreisachModel, initial_state: str | Tensor | None = None
    ) -> StreamSpec:
        """:meth:`PreisachModel.stream_spec` with this band (numpy, float64)."""
        spec = model.stream_spec(initial_state)
        with torch.no_grad():
            affine, w = self.hysteron_weights(model)
            return dataclasses.replace(
                spec,
                band_affine=affine.detach().cpu().double().numpy(),
                band_weights=w.detach().cpu().double().numpy(),
                noise_std=float(self.noise_std),
                calibration=float(self.calibration),
            )

    def std(
        self,
        model: PreisachModel,
        u: Tensor,
        initial_state: str | Tensor | None = None,
    ) -> Tensor:
        """Predictive standard deviation [output units] along one history.

        Evaluated by the streaming code
        (:class:`~diffaccel.hysteresis.stream.StreamPredictor`, float64 sums),
        without a ``(T, M)`` state table; no gradients.

        Args:
            model: The fitted model the band belongs to.
            u: Inputs [input units], shape ``(T,)``.
            initial_state: See :meth:`PreisachModel.initial_states`.

        Returns:
            One standard deviation including measurement noise, shape ``(T,)``.

        Raises:
            ValueError: for inputs that are not one non-empty history, or NaN.
        """
        u = as_real_tensor(
            u, "inputs", dtype=model.alpha.dtype, device=model.alpha.device
        )
        if u.ndim != 1 or u.numel() == 0:
            raise ValueError(
                f"inputs need shape (T,) with T >= 1; got {tuple(u.shape)}."
            )
        predictor = StreamPredictor(
            self.stream_spec(model, initial_state), band_dtype=np.float64
        )
        _, std = predictor(u.detach().cpu().double().numpy())
        return torch.as_tensor(std, dtype=u.dtype, device=u.device)


def _features(model: PreisachModel, un: Tensor, initial_state) -> Tensor:
    """Rows ``f_t = (1, u_n, mean-density state, a_i s_i / sum(a))``, ``(T, M + 3)``.

    ``u_n`` unclipped, as in the model's linear term; the states saturate.
    """
    s = model._normalized_states(un, initial_state)
    a = model.area / model.area.sum()
    phi = s * a
    if model.symmetric:
        phi = 0.5 * (phi + phi[:, model.mirror])
    lin = torch.stack([torch.ones_like(un), un, phi.sum(1)], dim=1)
    return torch.cat([lin, phi], dim=1)


def _prior_covariance(model: PreisachModel, length: float, dtype) -> Tensor:
    """Squared-exponential prior of the density in the plane the mesh is regular in."""
    ta, tb = model.plane_coordinates()
    pts = torch.stack([ta, tb], dim=1).to(dtype)
    d2 = torch.cdist(pts, pts, compute_mode="donot_use_mm_for_euclid_dist") ** 2
    return torch.exp(-0.5 * d2 / length**2)


def _fit_hyper(g: Tensor, g_lin: Tensor, yn: Tensor, jitter: float) -> tuple:
    """Type-II maximum likelihood of (prior variance, noise variance) for one prior.

    The covariance of the training rows is ``sv2 g + g_lin + (sn2 + jitter) I``.
    Returns ``(nll, raw)``; raises ``RuntimeError`` / ``LinAlgError`` where a
    Cholesky factor fails.
    """
    eye = torch.eye(yn.numel(), dtype=yn.dtype, device=yn.device)
    raw = torch.tensor([-3.0, -6.0], dtype=yn.dtype, requires_grad=True)

    def nll() -> Tensor:
        sv2, sn2 = torch.exp(2 * raw)
        chol = torch.linalg.cholesky(sv2 * g + g_lin + (sn2 + jitter) * eye)
        alpha = torch.cholesky_solve(yn[:, None], chol)
        return 0.5 * (yn[:, None] * alpha).sum() + chol.diagonal().log().sum()

    opt = torch.optim.LBFGS(
        [raw], max_iter=60, line_search_fn="strong_wolfe", tolerance_change=1e-12
    )

    def closure() -> Tensor:
        opt.zero_grad()
        loss = nll()
        loss.backward()
        return loss

    opt.step(closure)
    with torch.no_grad():
        return float(nll()), raw.detach().clone()


def _directions(f: Tensor, prior: Tensor, noise_var: float) -> Tensor:
    """Scaled leading eigen-directions ``(K, M + 3)`` of the parameter posterior."""
    t = f.shape[0]
    eye = torch.eye(t, dtype=f.dtype, device=f.device)
    cross = f @ prior  # (T, M + 3)
    ky = cross @ f.T + noise_var * eye
    chol = torch.linalg.cholesky(ky)
    post = prior - cross.T @ torch.cholesky_solve(cross, chol)
    post = 0.5 * (post + post.T)
    evals, evecs = torch.linalg.eigh(post)
    evals, evecs = evals.flip(0).clamp(min=0.0), evecs.flip(1)
    if not bool(torch.isfinite(evals).all()):
        raise RuntimeError("non-finite posterior covariance")
    share = torch.cumsum(evals, 0) / evals.sum().clamp(min=1e-300)
    keep = int(torch.searchsorted(share, torch.tensor(_KEEP, dtype=f.dtype))) + 1
    keep = max(1, min(keep, _MAX_DIRECTIONS, evals.numel()))
    return (evecs[:, :keep] * evals[:keep].sqrt()).T


def laplace_band(
    model: PreisachModel,
    current: Tensor,
    field: Tensor,
    initial_state: str | Tensor | None = None,
    length_scales: Sequence[float] = LENGTH_SCALES,
    calibration: float = 1.0,
) -> LaplaceBand:
    """Laplace band of ``model`` from its training rows.

    The band never fails for lack of a positive-definite covariance. Each
    length scale is tried with a noise-variance floor (jitter) of ``1e-12``
    [normalised output^2] first, then ``1e-10``, ``1e-8`` and ``1e-6``; the
    first floor at which some length scale gives a positive-definite
    covariance is used. If none does, the band falls back to a coarser model:
    the posterior of offset, slope and mean density alone (no density prior),
    with the noise set to the fitted model's rms residual on the training rows.
    Either fallback raises one :class:`BandFallbackWarning` and is named by the
    band's ``fallback`` attribute (``None`` without one).

    Args:
        model: A model fitted to ``(current, field)`` (its output normalisation
            is used).
        current: Training inputs [input units], shape ``(T,)``.
        field: Training outputs [output units], shape ``(T,)``.
        initial_state: State before ``current[0]``; ``None`` is the model's own.
        length_scales: Candidate length scales of the density prior [1], in
            the plane the mesh is regular in (:meth:`PreisachModel.plane_coordinates`).
        calibration: Factor (>= 1) for the whole band.

    Returns:
        The band; ``std`` gives one standard deviation in output units.

    Raises:
        ValueError: for mismatched lengths.
    """
    dtype = torch.float64
    with torch.no_grad():
        un = model.normalize_input(current).to(dtype)
        y = torch.as_tensor(field, dtype=dtype, device=un.device)
        if y.shape != un.shape:
            raise ValueError(
                f"current and field lengths differ: {un.numel()} vs {y.numel()}."
            )
        yn = (y - model.output_loc.to(dtype)) / model.output_scale.to(dtype)
        f = _features(model, un, initial_state).to(dtype)
    lin, phi = f[:, :3], f[:, 3:]
    g_lin = _FLAT * (lin @ lin.T)
    m = phi.shape[1]
    directions = None
    fallback = None
    for jitter in _JITTERS:
        best = None
        for length in length_scales:
            k = _prior_covariance(model, float(length), dtype)
            g = phi @ k @ phi.T
            try:
                value, raw = _fit_hyper(g, g_lin, yn, jitter)
            except (RuntimeError, torch.linalg.LinAlgError):  # not positive definite
                continue
            if math.isfinite(value) and (best is None or value < best[0]):
                best = (value, k, raw)
        if best is None:
            continue
        _, k, raw = best
        sv2, sn2 = (float(v) for v in torch.exp(2 * raw))
        prior = torch.zeros(m + 3, m + 3, dtype=dtype, device=un.device)
        prior[:3, :3] = _FLAT * torch.eye(3, dtype=dtype)
        prior[3:, 3:] = sv2 * k
        try:
            directions = _directions(f, prior, sn2 + jitter)
        except (RuntimeError, torch.linalg.LinAlgError):
            continue
        noise_std = math.sqrt(sn2)
        if jitter != _JITTERS[0]:
            fallback = (
                f"predictive band: positive definite only with a noise-variance "
                f"floor (jitter) of {jitter:.0e} of the output range squared"
            )
        break
    if directions is None:
        with torch.no_grad():
            resid = (model(torch.as_tensor(current), initial_state) - y).to(dtype)
            r2 = float((resid / model.output_scale.to(dtype)).pow(2).mean())
        sn2 = max(r2, _COARSE_NOISE_FLOOR**2)
        prior = torch.zeros(m + 3, m + 3, dtype=dtype, device=un.device)
        prior[:3, :3] = _FLAT * torch.eye(3, dtype=dtype)
        directions = _directions(f, prior, sn2)
        noise_std = math.sqrt(sn2)
        fallback = (
            "predictive band: no length scale gave a positive-definite covariance; "
            "used the coarser band of offset, slope and mean density with the "
            "fit's rms residual as noise"
        )
    band = LaplaceBand(directions, noise_std, calibration=max(1.0, calibration))
    band.fallback = fallback
    if fallback is not None:
        warnings.warn(fallback + ".", BandFallbackWarning, stacklevel=2)
    return band.to(device=model.alpha.device)
