"""Joint hysteresis-Gaussian-process model (H-GP) of a beam response.

The beam responds to the *magnetic state* of hysteretic magnets, not to their
currents. :class:`HysteresisGP` feeds each hysteretic input column through a
Preisach model of the current history and models the beam response as an exact
Gaussian process of the resulting normalised magnetisations (plain columns are
ordinary GP inputs). The Preisach densities and the GP hyperparameters are fitted
together on the exact marginal log likelihood by :func:`fit_hysteresis_gp`.

Time order matters: row ``t`` of ``train_X`` is the setting applied at step ``t``
and ``posterior(X)`` means "apply the ``q`` settings of ``X`` in order, starting
from the magnetic state left by the training history".
"""

from __future__ import annotations

import copy
import logging
import math
import time
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import torch
from botorch.models.model import Model
from botorch.models.transforms.outcome import OutcomeTransform, Standardize
from botorch.models.utils.gpytorch_modules import (
    get_covar_module_with_dim_scaled_prior,
    get_gaussian_likelihood_with_lognormal_prior,
)
from botorch.optim.closures import ForwardBackwardClosure
from botorch.optim.fit import fit_gpytorch_mll_scipy
from botorch.optim.utils import get_parameters_and_bounds
from botorch.posteriors.gpytorch import GPyTorchPosterior
from botorch.posteriors.transformed import TransformedPosterior
from gpytorch.distributions import MultivariateNormal
from gpytorch.kernels import Kernel
from gpytorch.likelihoods import Likelihood
from gpytorch.means import ConstantMean, Mean
from gpytorch.mlls import ExactMarginalLogLikelihood
from gpytorch.models import ExactGP
from gpytorch.utils.warnings import GPInputWarning
from torch import Tensor, nn

from diffaccel.hysteresis.preisach import PreisachModel
from diffaccel.hysteresis.states import exact_states, smooth_states

__all__ = [
    "HGPFitResult",
    "HysteresisGP",
    "fit_hysteresis_gp",
    "magnetisation_feature",
]

logger = logging.getLogger(__name__)

_MIN_POINTS = 3


class _FeatureGP(ExactGP):
    """Exact GP on state features in ``[0, 1]^d`` (mean, kernel, likelihood only)."""

    def __init__(
        self,
        features: Tensor,
        targets: Tensor,
        likelihood: Likelihood,
        mean_module: Mean,
        covar_module: Kernel,
    ) -> None:
        super().__init__(features, targets, likelihood)
        self.mean_module = mean_module
        self.covar_module = covar_module

    def forward(self, x: Tensor) -> MultivariateNormal:
        return MultivariateNormal(self.mean_module(x), self.covar_module(x))


def magnetisation_feature(states: Tensor, weights: Tensor) -> Tensor:
    """GP input of a hysteretic magnet: its normalised magnetisation in ``[0, 1]``.

    ``(m + 1) / 2`` with ``m = sum(w * s) / sum(w)``: only the shape of the
    density matters (field scale and offset are not identifiable from beam data).

    Args:
        states: Hysteron states in ``[-1, 1]``, shape ``(*B, M)``.
        weights: Hysteron weights ``area * density`` (non-negative), shape ``(M,)``.

    Returns:
        Feature in ``[0, 1]``, shape ``(*B,)``.
    """
    return 0.5 * (states @ weights / weights.sum() + 1.0)


class HysteresisGP(Model):
    """Gaussian-process model of a beam response to the state of hysteretic magnets.

    The training inputs are a *history*: row ``t`` of ``train_X`` is the setting
    applied at step ``t`` (in order) and ``train_Y[t]`` the response measured after
    it. Each hysteretic column ``c`` (a key of ``hysteresis``) is a magnet current
    fed through a copy of its Preisach model; the GP input for that column is the
    normalised magnetisation ``(m + 1) / 2`` in ``[0, 1]``, where
    ``m = sum(w * s) / sum(w)``, ``w = density * area``. Field scale and offset are
    not identifiable from beam data, so only the density *shape* enters. Plain
    columns are scaled to ``[0, 1]`` with ``bounds``. The GP itself is built as
    BoTorch's ``SingleTaskGP`` builds its modules (RBF kernel with the
    dimension-scaled lengthscale prior, constant mean, Gaussian likelihood with a
    LogNormal noise prior, ``Standardize`` outcome transform), so with no
    hysteretic columns it is the same model.

    ``posterior(X)`` with ``X`` of shape ``batch x q x d`` means: *starting from the
    magnetic state at the end of the training history, apply the q settings of
    each batch in order*; candidate ``j`` sees the state left by candidates
    ``1..j-1``. A batch of one-step candidates is ``batch x 1 x d``; a future
    sequence is ``1 x T x d``. The candidates' hysterons follow smooth relays
    (``candidate_smoothing``) so that acquisition optimisers get gradients;
    ``posterior_sequence(X)`` predicts the same scenario with exact relays and
    ``posterior_on_history()`` gives the model at the training points.

    Args:
        train_X: Settings in the order they were applied, shape ``(n, d)``;
            hysteretic columns in the units of their Preisach model's
            ``input_range`` (e.g. current [A]).
        train_Y: Measured responses, shape ``(n, 1)``.
        hysteresis: Map from input column to its Preisach model (copied; the
            copies live in ``hysteresis_models``). Empty for a plain GP. The
            state before the first row is the model's initial state, held fixed
            (a ``"learned"`` initial state is used as it is, not refitted).
        bounds: Lower and upper bounds of every input column, shape ``(2, d)``,
            used to scale plain columns to ``[0, 1]``; the data range if omitted.
        likelihood: Replaces the default Gaussian likelihood.
        covar_module: Replaces the default kernel (acts on the ``d`` features).
        mean_module: Replaces the default constant mean.
        outcome_transform: Transform of ``train_Y``; ``Standardize`` by default,
            ``None`` for none.
        candidate_smoothing: Width of the smooth, rate-independent relays used
            for the settings given to ``posterior`` (normalised Preisach input
            units; see ``diffaccel.hysteresis.states.smooth_states``). They start
            exactly at the state and input left by the history, tend to exact
            relays as the width goes to 0, and make the posterior a smooth
            function of the candidate currents, which gradient-based acquisition
            optimisers need (exact relays are piecewise constant). ``None``: a quarter
            of the mesh spacing, ``0.25 / sqrt(2 M)``; ``0``: exact relays.

    Shapes:
        ``posterior(X)`` maps ``(*b, q, d)`` to a posterior over ``(*b, q, 1)``.

    Raises:
        ValueError: for shapes, NaN or infinite values, fewer than 3 points,
            constant outputs, or a hysteretic column outside ``0..d-1``.

    Example:
        >>> import torch
        >>> from diffaccel.hysteresis import PreisachMesh, PreisachModel
        >>> u = torch.cat([torch.linspace(0, 1, 15), torch.linspace(1, 0, 15)])
        >>> X = u.double().unsqueeze(-1)
        >>> Y = torch.sin(3 * X)
        >>> pm = PreisachModel(mesh=PreisachMesh.triangular(n=10), input_range=(0, 1))
        >>> model = HysteresisGP(X, Y, hysteresis={0: pm})
        >>> model.posterior(torch.rand(4, 2, 1, dtype=torch.float64)).mean.shape
        torch.Size([4, 2, 1])
    """

    def __init__(
        self,
        train_X: Tensor,
        train_Y: Tensor,
        hysteresis: Mapping[int, PreisachModel],
        bounds: Tensor | None = None,
        likelihood: Likelihood | None = None,
        covar_module: Kernel | None = None,
        mean_module: Mean | None = None,
        outcome_transform: OutcomeTransform | str | None = "default",
        candidate_smoothing: float | None = None,
    ) -> None:
        super().__init__()
        # 1. validate
        _validate_training_data(train_X, train_Y)
        d = train_X.shape[-1]
        dims = sorted(int(c) for c in hysteresis)
        for c in dims:
            if not 0 <= c < d:
                raise ValueError(
                    f"hysteretic column {c} does not exist: train_X has d={d} columns "
                    f"(0..{d - 1})."
                )
        if bounds is None:
            bounds = torch.stack([train_X.min(dim=0).values, train_X.max(dim=0).values])
        bounds = torch.as_tensor(bounds, dtype=train_X.dtype, device=train_X.device)
        if bounds.shape != (2, d):
            raise ValueError(
                f"bounds must have shape (2, d) = (2, {d}); got {tuple(bounds.shape)}."
            )
        if candidate_smoothing is not None and not candidate_smoothing >= 0:
            raise ValueError(
                f"candidate_smoothing must be >= 0 or None; got {candidate_smoothing}."
            )
        self.hysteretic_dims: tuple[int, ...] = tuple(dims)
        self.plain_dims: tuple[int, ...] = tuple(i for i in range(d) if i not in dims)
        self.candidate_smoothing = candidate_smoothing
        width = bounds[1] - bounds[0]
        self.register_buffer("bounds", bounds.clone())
        self.register_buffer("_plain_width", torch.where(width > 0, width, 1.0))
        self.register_buffer("train_X", train_X.detach().clone())
        self.register_buffer("train_Y", train_Y.detach().clone())

        # 2. transform
        models = [copy.deepcopy(hysteresis[c]).to(train_X) for c in dims]
        self.hysteresis_models = nn.ModuleList(models)
        # exact hysteron states along the history do not depend on the density
        for i, (c, pm) in enumerate(zip(dims, models, strict=True)):
            pm.check_input_range(train_X[:, c], f"training inputs of column {c}")
            with torch.no_grad():
                states = pm.states(train_X[:, c])
            self.register_buffer(f"_history_states_{i}", states.to(train_X))
        if outcome_transform == "default":
            outcome_transform = Standardize(m=1)
        y = train_Y
        if outcome_transform is not None:
            outcome_transform.train()
            y, _ = outcome_transform(train_Y)
            self.outcome_transform = outcome_transform
        self.register_buffer("_train_targets", y.squeeze(-1).detach().clone())

        # 3. build modules
        if likelihood is None:
            likelihood = get_gaussian_likelihood_with_lognormal_prior()
        if covar_module is None:
            covar_module = get_covar_module_with_dim_scaled_prior(ard_num_dims=d)
        if mean_module is None:
            mean_module = ConstantMean()
        with torch.no_grad():
            features = self.train_features()
        self.gp = _FeatureGP(
            features, self._train_targets, likelihood, mean_module, covar_module
        )
        # 4. move to train_X
        self.to(train_X)

    # ------------------------------------------------------------------ shapes
    @property
    def num_outputs(self) -> int:
        """Number of modelled outputs (always 1)."""
        return 1

    @property
    def batch_shape(self) -> torch.Size:
        """Model batch shape (always empty: one history, one output)."""
        return torch.Size([])

    @property
    def likelihood(self) -> Likelihood:
        """The Gaussian likelihood of the inner GP (noise in standardised units)."""
        return self.gp.likelihood

    @property
    def noise_sigma(self) -> Tensor:
        """Fitted observation-noise standard deviation in units of ``train_Y``."""
        noise = self.gp.likelihood.noise.squeeze()
        scale = self._outcome_scale()
        return noise.sqrt() * scale

    def _outcome_scale(self) -> Tensor:
        ot = getattr(self, "outcome_transform", None)
        if isinstance(ot, Standardize):
            return ot.stdvs.squeeze()
        return torch.ones((), dtype=self.train_X.dtype, device=self.train_X.device)

    # ---------------------------------------------------------------- features
    def _weights(self, i: int) -> Tensor:
        return self.hysteresis_models[i].weights

    def _normalised(self, i: int, u: Tensor) -> Tensor:
        # settings beyond the Preisach input range saturate every hysteron alike
        lo, hi = self.hysteresis_models[i].input_range
        return ((u - lo) / (hi - lo)).clamp(0.0, 1.0)

    def _plain_features(self, X: Tensor) -> Tensor:
        idx = list(self.plain_dims)
        return (X[..., idx] - self.bounds[0, idx]) / self._plain_width[idx]

    def _assemble(self, X: Tensor, hyst: list[Tensor]) -> Tensor:
        cols: list[Tensor | None] = [None] * X.shape[-1]
        plain = self._plain_features(X)
        for k, c in enumerate(self.plain_dims):
            cols[c] = plain[..., k]
        for k, c in enumerate(self.hysteretic_dims):
            cols[c] = hyst[k]
        return torch.stack(cols, dim=-1)  # type: ignore[arg-type]

    def history_states(self, i: int) -> Tensor:
        """Exact hysteron states of hysteretic input ``i`` along the training history.

        Args:
            i: Position of the column in ``hysteretic_dims``.

        Returns:
            States in ``{-1, +1}``, shape ``(n, M)``.
        """
        return getattr(self, f"_history_states_{i}")

    def current_states(self) -> list[Tensor]:
        """Hysteron states at the end of the training history, one ``(M,)`` each."""
        return [self.history_states(i)[-1] for i in range(len(self.hysteretic_dims))]

    def _magnetisation_feature(self, i: int, states: Tensor) -> Tensor:
        return magnetisation_feature(states, self._weights(i))

    def train_features(self) -> Tensor:
        """GP inputs along the training history (differentiable in the densities).

        Returns:
            Features in ``[0, 1]``, shape ``(n, d)``.
        """
        hyst = [
            self._magnetisation_feature(i, self.history_states(i))
            for i in range(len(self.hysteretic_dims))
        ]
        return self._assemble(self.train_X, hyst)

    def smoothing_width(self, i: int) -> float:
        """Candidate relay width of hysteretic input ``i`` (normalised units)."""
        if self.candidate_smoothing is not None:
            return float(self.candidate_smoothing)
        return 0.25 / math.sqrt(2.0 * self.hysteresis_models[i].alpha.numel())

    def features(self, X: Tensor, exact: bool = False) -> Tensor:
        """GP inputs for settings applied in order after the training history.

        Hysteretic columns start from the exact state and input at the end of
        the history and follow smooth relays of width :meth:`smoothing_width`
        (exact relays if it is 0 or ``exact`` is True).

        Args:
            X: Settings, shape ``(*b, q, d)``; along ``q`` they are applied in order
                starting from the state at the end of the training history.
            exact: Use exact relays whatever the smoothing width.

        Returns:
            Features, shape ``(*b, q, d)``.
        """
        hyst = []
        for i, c in enumerate(self.hysteretic_dims):
            pm = self.hysteresis_models[i]
            x = self._normalised(i, X[..., c])
            s_end = self.history_states(i)[-1].to(X)
            alpha, beta = pm.alpha.to(X), pm.beta.to(X)
            width = 0.0 if exact else self.smoothing_width(i)
            if width > 0:
                x_end = self._normalised(i, self.train_X[-1, c]).to(X)
                states = smooth_states(x, alpha, beta, s_end, width, start=x_end)
            else:
                states = exact_states(x, alpha, beta, s_end)
            hyst.append(self._magnetisation_feature(i, states))
        return self._assemble(X, hyst)

    def _sync_train_data(self) -> None:
        with torch.no_grad():
            feats = self.train_features()
        old = self.gp.train_inputs[0]
        if old.shape != feats.shape or not torch.equal(old, feats):
            self.gp.set_train_data(feats, self._train_targets, strict=False)

    # --------------------------------------------------------------- posterior
    def _check_X(self, X: Tensor) -> None:
        d = self.train_X.shape[-1]
        if X.dim() < 2 or X.shape[-1] != d:
            raise ValueError(
                f"X must have shape (*batch, q, d) with d={d}; got {tuple(X.shape)}."
            )
        if not torch.isfinite(X).all():
            raise ValueError("X contains NaN or infinite values.")

    def _wrap(
        self,
        mvn: MultivariateNormal,
        features: Tensor,
        X: Tensor,
        observation_noise: bool | Tensor,
        posterior_transform: Callable | None,
    ) -> GPyTorchPosterior | TransformedPosterior:
        if observation_noise is not False:
            mvn = self.gp.likelihood(mvn, features)
        posterior = GPyTorchPosterior(distribution=mvn)
        ot = getattr(self, "outcome_transform", None)
        if ot is not None:
            posterior = ot.untransform_posterior(posterior, X=X)
        if posterior_transform is not None:
            posterior = posterior_transform(posterior)
        return posterior

    def posterior(
        self,
        X: Tensor,
        output_indices: list[int] | None = None,
        observation_noise: bool | Tensor = False,
        posterior_transform: Callable | None = None,
    ) -> GPyTorchPosterior | TransformedPosterior:
        """Joint posterior of the responses to settings applied after the history.

        Args:
            X: Settings, shape ``batch x q x d`` (or ``q x d``): each batch is an
                independent scenario in which its ``q`` settings are applied in
                order, starting from the magnetic state at the end of the
                training history.
            output_indices: Must be ``None`` or ``[0]`` (single output).
            observation_noise: If True, add the fitted observation noise.
            posterior_transform: Optional BoTorch posterior transform.

        Returns:
            Posterior over responses of shape ``batch x q x 1`` (units of
            ``train_Y``).

        Raises:
            ValueError: if ``X`` has the wrong last dimension or holds NaN.
        """
        if output_indices not in (None, [0]):
            raise ValueError(f"HysteresisGP has one output; got {output_indices}.")
        self._check_X(X)
        self.eval()
        self._sync_train_data()
        feats = self.features(X)
        mvn = self.gp(feats)
        return self._wrap(mvn, feats, X, observation_noise, posterior_transform)

    def posterior_on_history(
        self, observation_noise: bool = False
    ) -> GPyTorchPosterior | TransformedPosterior:
        """Posterior of the responses at the training history itself.

        Args:
            observation_noise: If True, add the fitted observation noise.

        Returns:
            Posterior over shape ``(n, 1)`` (units of ``train_Y``).
        """
        self.eval()
        self._sync_train_data()
        feats = self.gp.train_inputs[0]
        with warnings.catch_warnings():  # predicting at the training inputs is meant
            warnings.simplefilter("ignore", GPInputWarning)
            mvn = self.gp(feats)
        return self._wrap(mvn, feats, self.train_X, observation_noise, None)

    def posterior_sequence(
        self, X: Tensor, observation_noise: bool = False
    ) -> GPyTorchPosterior | TransformedPosterior:
        """Joint posterior along a future sequence, with exact hysteron states.

        Same meaning of ``X`` as :meth:`posterior` (settings applied in order
        from the end of the history), but the states follow exact relays, so the
        prediction is exactly consistent with the Preisach model (no smoothing).
        Use it to predict; :meth:`posterior` (smooth in ``X``) is for
        acquisition optimisation.

        Args:
            X: Future settings, shape ``(T, d)`` or ``(*b, T, d)``.
            observation_noise: If True, add the fitted observation noise.

        Returns:
            Posterior over ``(T, 1)`` or ``(*b, T, 1)`` (units of ``train_Y``).

        Raises:
            ValueError: if ``X`` has the wrong last dimension or holds NaN.
        """
        self._check_X(X)
        self.eval()
        self._sync_train_data()
        feats = self.features(X, exact=True)
        mvn = self.gp(feats)
        return self._wrap(mvn, feats, X, observation_noise, None)

    def condition_on_observations(
        self, X: Tensor, Y: Tensor, **kwargs: object
    ) -> HysteresisGP:
        """A new model whose history continues with ``X`` and measurements ``Y``.

        The hyperparameters and densities are copied, not refitted; call
        :func:`fit_hysteresis_gp` on the result to refit.

        Args:
            X: Settings applied after the history, in order, shape ``(n', d)``.
            Y: Responses measured after each, shape ``(n', 1)``.
            **kwargs: Not supported; must be empty.

        Returns:
            A new :class:`HysteresisGP` on the extended history.
        """
        if kwargs:
            raise ValueError(f"unsupported arguments: {sorted(kwargs)}.")
        if X.dim() != 2 or Y.dim() != 2:
            raise ValueError(
                "condition_on_observations takes one continued history: X (n', d), "
                f"Y (n', 1); got X {tuple(X.shape)}, Y {tuple(Y.shape)}."
            )
        return self.extended(X, Y)

    def extended(self, X: Tensor, Y: Tensor) -> HysteresisGP:
        """Same model (densities, hyperparameters) on the history continued by X, Y.

        Args:
            X: Settings applied after the history, in order, shape ``(n', d)``.
            Y: Responses measured after each, shape ``(n', 1)``.

        Returns:
            A new :class:`HysteresisGP`; the outcome transform is re-fitted to the
            extended data.
        """
        new_X = torch.cat([self.train_X, X.to(self.train_X)])
        new_Y = torch.cat([self.train_Y, Y.to(self.train_Y)])
        hyst = {
            c: pm
            for c, pm in zip(self.hysteretic_dims, self.hysteresis_models, strict=True)
        }
        ot = getattr(self, "outcome_transform", None)
        new = HysteresisGP(
            new_X,
            new_Y,
            hysteresis=hyst,
            bounds=self.bounds,
            likelihood=copy.deepcopy(self.gp.likelihood),
            covar_module=copy.deepcopy(self.gp.covar_module),
            mean_module=copy.deepcopy(self.gp.mean_module),
            outcome_transform=None if ot is None else Standardize(m=1),
            candidate_smoothing=self.candidate_smoothing,
        )
        return new


def _validate_training_data(train_X: Tensor, train_Y: Tensor) -> None:
    if not isinstance(train_X, Tensor) or not isinstance(train_Y, Tensor):
        raise TypeError("train_X and train_Y must be torch tensors.")
    if train_X.dim() != 2:
        raise ValueError(
            f"train_X must have shape (n, d) (one history in time order); got "
            f"{tuple(train_X.shape)}."
        )
    if train_Y.shape != (train_X.shape[0], 1):
        raise ValueError(
            f"train_Y must have shape (n, 1) = ({train_X.shape[0]}, 1); got "
            f"{tuple(train_Y.shape)}."
        )
    if not train_X.is_floating_point() or train_X.dtype != train_Y.dtype:
        raise ValueError(
            f"train_X and train_Y must share a floating dtype; got {train_X.dtype} "
            f"and {train_Y.dtype} (float64 recommended)."
        )
    if not torch.isfinite(train_X).all():
        raise ValueError("train_X contains NaN or infinite values.")
    if not torch.isfinite(train_Y).all():
        raise ValueError(
            "train_Y contains NaN or infinite values; drop failed measurements "
            "from the outputs only if you keep their settings in the history."
        )
    n = train_X.shape[0]
    if n < _MIN_POINTS:
        raise ValueError(
            f"too few points to fit a GP: got n={n}, need at least {_MIN_POINTS}."
        )
    if bool((train_Y == train_Y[0]).all()):
        raise ValueError(
            f"train_Y is constant ({float(train_Y[0, 0])}): a GP cannot learn a "
            "response from outputs that never change."
        )


@dataclass(frozen=True)
class HGPFitResult:
    """Outcome of a joint H-GP fit.

    Args:
        mll: Best exact marginal log likelihood per point (with priors).
        noise_sigma: Fitted noise standard deviation [units of ``train_Y``].
        restart_mlls: Final ``mll`` of every restart, in order.
        best_restart: Index of the restart kept.
        fit_s: Wall-clock time of the fit [s].
    """

    mll: float
    noise_sigma: float
    restart_mlls: tuple[float, ...]
    best_restart: int
    fit_s: float


def _joint_loss(model: HysteresisGP, mll: ExactMarginalLogLikelihood) -> Tensor:
    """Negative exact MLL per point, with priors, as GPyTorch's ExactMLL defines it.

    Computed with one dense Cholesky factorisation (no lazy-tensor machinery), which
    is several times faster for the few hundred points of a magnet history.
    """
    gp = model.gp
    feats = model.train_features()
    y = model._train_targets
    n = y.shape[-1]
    noise = gp.likelihood.noise.reshape(())
    cov = gp.covar_module(feats).to_dense()
    cov = cov + noise * torch.eye(n, dtype=cov.dtype, device=cov.device)
    chol, info = torch.linalg.cholesky_ex(cov)
    if bool(info):
        jitter = 1e-6 * cov.diagonal().mean().detach()
        cov = cov + jitter * torch.eye(n, dtype=cov.dtype, device=cov.device)
        chol = torch.linalg.cholesky(cov)
    resid = (y - gp.mean_module(feats)).unsqueeze(-1)
    alpha = torch.cholesky_solve(resid, chol)
    value = -0.5 * (resid * alpha).sum() - chol.diagonal().log().sum()
    value = value - 0.5 * n * math.log(2.0 * math.pi)
    for _, module, prior, closure, _ in gp.named_priors():
        value = value + prior.log_prob(closure(module)).sum()
    return -value / n


def _randomise(model: HysteresisGP, generator: torch.Generator) -> None:
    """Random start: log-normal density jitter, random lengthscales and noise."""
    dtype, device = model.train_X.dtype, model.train_X.device
    with torch.no_grad():
        for pm in model.hysteresis_models:
            raw = pm.raw_density
            noise = torch.randn(raw.shape, generator=generator, dtype=dtype)
            pm.raw_density.copy_(raw + noise.to(device=device, dtype=raw.dtype))
        kern = model.gp.covar_module
        if hasattr(kern, "lengthscale"):
            ls = kern.lengthscale
            factor = torch.exp(0.7 * torch.randn(ls.shape, generator=generator))
            kern.lengthscale = (ls * factor.to(ls)).clamp_min(0.05)
        lik = model.gp.likelihood
        if hasattr(lik, "noise"):
            log_noise = -6.0 + 2.0 * torch.rand((), generator=generator)
            lik.noise = torch.full_like(lik.noise, math.exp(float(log_noise)))


def fit_hysteresis_gp(
    model: HysteresisGP,
    restarts: int = 3,
    max_iter: int = 200,
    fit_density: bool = True,
    density_prior_scale: float | None = None,
    seed: int = 0,
    callback: Callable[[int, float], None] | None = None,
) -> HGPFitResult:
    """Fit Preisach densities and GP hyperparameters jointly on the exact MLL.

    L-BFGS-B (BoTorch's scipy fitting routine) maximises the exact marginal log
    likelihood plus the GP priors (the LogNormal noise prior keeps the model from
    explaining everything as noise). Restart 0 starts from the model as given;
    further restarts jitter the densities, lengthscales and noise at random; the
    best restart is kept. Only density *shapes* are fitted (features use
    normalised magnetisations), never field scale or offset.

    Args:
        model: The model to fit in place.
        restarts: Number of optimisations (``>= 1``).
        max_iter: L-BFGS-B iterations per restart.
        fit_density: If False, keep the Preisach densities fixed (e.g. measured).
        density_prior_scale: If set, a Gaussian prior of this standard deviation
            on each raw (softplus-inverse) density about its value when the fit
            starts, i.e. the given density is a prior guess. It matters when few
            points must constrain many hysterons (e.g. early in optimisation)
            and fades as data accumulate. ``None``: no density prior.
        seed: Seed of the random restarts.
        callback: Called after each restart with ``(restart, mll)``.

    Returns:
        A :class:`HGPFitResult`; ``model`` holds the best parameters, in eval mode.

    Raises:
        ValueError: if ``restarts < 1`` or ``max_iter < 1``.
    """
    if restarts < 1 or max_iter < 1:
        raise ValueError(
            f"restarts and max_iter must be >= 1; got {restarts} and {max_iter}."
        )
    if density_prior_scale is not None and not density_prior_scale > 0:
        raise ValueError(
            f"density_prior_scale must be > 0 or None; got {density_prior_scale}."
        )
    t0 = time.perf_counter()
    generator = torch.Generator().manual_seed(seed)
    mll = ExactMarginalLogLikelihood(model.gp.likelihood, model.gp)
    gp_params, _ = get_parameters_and_bounds(mll)
    params = {n: p for n, p in gp_params.items() if p.requires_grad}
    if fit_density:
        for i, pm in enumerate(model.hysteresis_models):
            params[f"hysteresis_models.{i}.raw_density"] = pm.raw_density
    start = copy.deepcopy(model.state_dict())
    raw0 = [pm.raw_density.detach().clone() for pm in model.hysteresis_models]

    def loss() -> Tensor:
        value = _joint_loss(model, mll)
        if fit_density and density_prior_scale is not None:
            n = model._train_targets.shape[-1]
            for pm, r0 in zip(model.hysteresis_models, raw0, strict=True):
                dev = (pm.raw_density - r0) / density_prior_scale
                value = value + 0.5 * dev.pow(2).sum() / n
        return value

    best_state, best_value, best_index = None, -math.inf, 0
    values: list[float] = []
    for r in range(restarts):
        model.load_state_dict(start)
        if r > 0:
            _randomise(model, generator)
        model.train()
        closure = ForwardBackwardClosure(forward=loss, parameters=params)
        try:
            fit_gpytorch_mll_scipy(
                mll, parameters=params, closure=closure, options={"maxiter": max_iter}
            )
            with torch.no_grad():
                value = -float(loss())
        except (RuntimeError, ValueError) as err:  # numerical failure of one start
            logger.warning("H-GP restart %d failed: %s", r, err)
            value = -math.inf
        values.append(value)
        if callback is not None:
            callback(r, value)
        if value > best_value:
            best_value, best_index = value, r
            best_state = copy.deepcopy(model.state_dict())
    if best_state is None:
        raise RuntimeError("every H-GP restart failed; check the data for outliers.")
    model.load_state_dict(best_state)
    model.eval()
    model._sync_train_data()
    return HGPFitResult(
        mll=best_value,
        noise_sigma=float(model.noise_sigma.detach()),
        restart_mlls=tuple(values),
        best_restart=best_index,
        fit_s=time.perf_counter() - t0,
    )
