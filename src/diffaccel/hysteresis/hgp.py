"""Joint hysteresis-Gaussian-process model (H-GP) of a beam response.

The beam responds to the *magnetic state* of hysteretic magnets, not to their
currents. :class:`HysteresisGP` feeds each hysteretic input column through a
Preisach model of the current history and models the beam response as an exact
Gaussian process of the resulting normalised magnetisations (plain columns are
ordinary GP inputs). The inner GPyTorch ``ExactGP`` takes the hysteron *states*
as its inputs (they do not depend on the density) and maps them to
magnetisations with the Preisach densities, which are constrained raw
parameters of the model, GPyTorch style. :func:`fit_hysteresis_gp` fits them
together with the GP hyperparameters on GPyTorch's
``ExactMarginalLogLikelihood`` with BoTorch's ``fit_gpytorch_mll``.

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
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import torch
from botorch.exceptions.errors import ModelFittingError
from botorch.fit import fit_gpytorch_mll
from botorch.models.model import Model
from botorch.models.transforms.input import Normalize
from botorch.models.transforms.outcome import OutcomeTransform, Standardize
from botorch.models.utils.gpytorch_modules import (
    get_covar_module_with_dim_scaled_prior,
    get_gaussian_likelihood_with_lognormal_prior,
)
from botorch.optim.fit import fit_gpytorch_mll_scipy
from botorch.posteriors.gpytorch import GPyTorchPosterior
from botorch.posteriors.transformed import TransformedPosterior
from botorch.utils.types import DEFAULT, _DefaultType
from gpytorch.constraints import GreaterThan, Positive
from gpytorch.distributions import MultivariateNormal
from gpytorch.kernels import Kernel
from gpytorch.likelihoods import (
    FixedNoiseGaussianLikelihood,
    GaussianLikelihood,
    Likelihood,
)
from gpytorch.likelihoods.gaussian_likelihood import _GaussianLikelihoodBase
from gpytorch.likelihoods.noise_models import HomoskedasticNoise
from gpytorch.means import ConstantMean, Mean
from gpytorch.mlls import ExactMarginalLogLikelihood
from gpytorch.models import ExactGP
from gpytorch.module import Module as GPyTorchModule
from gpytorch.priors import LogNormalPrior, NormalPrior
from gpytorch.utils.warnings import GPInputWarning
from torch import Tensor, nn

from diffaccel.dynamics import is_integer
from diffaccel.hysteresis.fit import MAX_MAGNITUDE, fit_preisach
from diffaccel.hysteresis.preisach import PreisachModel
from diffaccel.hysteresis.states import exact_states, smooth_states

__all__ = [
    "HGPFitResult",
    "HysteresisGP",
    "JointStart",
    "fit_hysteresis_gp",
    "joint_gp_from_preisach",
    "magnetization_feature",
    "noise_likelihood",
]

logger = logging.getLogger(__name__)

_MIN_POINTS = 3


def _standardize() -> Standardize:
    """The default outcome transform: ``Standardize`` whatever the output's units.

    BoTorch's ``Standardize`` only de-means outputs whose standard deviation is
    below ``min_stdv`` (1e-8 by default), which would leave a beam size in
    metres (or any output in small units) unscaled against a noise prior and
    noise floor meant for unit-variance data. Constant outputs are refused
    before, so every standard deviation here is positive.
    """
    return Standardize(m=1, min_stdv=0.0)


class _RescaledPosterior(GPyTorchPosterior):
    """Posterior in units of ``train_Y``, variance and samples scaled from model units.

    GPyTorch rounds variances below an absolute floor (1e-10 in float64) up to
    it, with a "Negative variance values detected" warning, and adds an
    absolute jitter (1e-8 in float64) to a covariance whose Cholesky factor
    fails (nearly singular: many close settings, the training history); after
    the standardisation is undone both would swamp an output in small units
    (a beam size of 1e-4 m has variances near 1e-13 m^2). The variance and the
    samples (:meth:`rsample`, :meth:`rsample_from_base_samples`, and
    ``sample``, which BoTorch's samplers and Monte-Carlo acquisition
    functions use) are therefore taken in standardised units and mapped
    affinely: ``mean + scale * (s - mean_std)``, variance ``scale^2 var_std``.
    ``distribution`` itself is BoTorch's un-standardised one (its
    ``variance`` and samples drawn from it directly keep GPyTorch's floors).

    Args:
        distribution: The posterior distribution in units of ``train_Y``.
        standardised: The same posterior in model (standardised) units.
        scale: Output scale [units of ``train_Y``], a scalar tensor.
    """

    def __init__(
        self,
        distribution: MultivariateNormal,
        standardised: GPyTorchPosterior,
        scale: Tensor,
    ) -> None:
        super().__init__(distribution=distribution)
        self._standardised = standardised
        self._scale = scale

    @property
    def variance(self) -> Tensor:
        """Marginal variances [units of ``train_Y`` squared], shape ``(*b, q, 1)``."""
        return self._standardised.variance * self._scale.square()

    def _rescale(self, samples: Tensor) -> Tensor:
        return self.mean + self._scale * (samples - self._standardised.mean)

    def rsample(self, sample_shape: torch.Size | None = None) -> Tensor:
        """Samples [units of ``train_Y``], shape ``(*sample_shape, *b, q, 1)``."""
        return self._rescale(self._standardised.rsample(sample_shape))

    def rsample_from_base_samples(
        self, sample_shape: torch.Size, base_samples: Tensor
    ) -> Tensor:
        """Samples [units of ``train_Y``] from ``N(0, I)`` base samples.

        Args:
            sample_shape: Leading shape of the samples.
            base_samples: Shape ``(*sample_shape, *base_sample_shape)``.

        Returns:
            Samples, shape ``(*sample_shape, *b, q, 1)``.
        """
        return self._rescale(
            self._standardised.rsample_from_base_samples(sample_shape, base_samples)
        )


def magnetization_feature(states: Tensor, weights: Tensor) -> Tensor:
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


class _MagnetFeature(GPyTorchModule):
    """Normalised magnetisation of one hysteretic magnet from its hysteron states.

    Holds the magnet's mesh (buffers) and its Preisach density as the
    constrained raw parameter ``raw_density`` (``density = softplus(raw)``,
    GPyTorch's ``Positive`` constraint, the same map as ``PreisachModel``),
    averaged with its mirror image when the Preisach model is symmetric. With
    ``prior_scale`` a ``NormalPrior`` of that width on ``raw_density`` about its
    starting value is registered as ``density_prior``.
    """

    def __init__(self, preisach: PreisachModel, prior_scale: float | None) -> None:
        super().__init__()
        m = preisach.alpha.numel()
        self.register_buffer("alpha", preisach.alpha.detach().clone())
        self.register_buffer("beta", preisach.beta.detach().clone())
        self.register_buffer("area", preisach.area.detach().clone())
        mirror = preisach.mesh.mirror_index() if preisach.symmetric else None
        self.register_buffer(
            "mirror", torch.arange(m) if mirror is None else mirror.cpu().clone()
        )
        raw = preisach.raw_density.detach().clone()
        self.register_parameter("raw_density", nn.Parameter(raw))
        self.register_constraint("raw_density", Positive())
        if prior_scale is not None:
            self.register_prior(
                "density_prior",
                NormalPrior(raw.clone(), torch.full_like(raw, prior_scale)),
                "raw_density",
            )

    @property
    def density(self) -> Tensor:
        """Non-negative hysteron density [1], shape ``(M,)``."""
        d = self.raw_density_constraint.transform(self.raw_density)
        return 0.5 * (d + d[self.mirror])

    @property
    def weights(self) -> Tensor:
        """Hysteron weights ``area * density``, shape ``(M,)``."""
        return self.area * self.density

    def forward(self, states: Tensor) -> Tensor:
        return magnetization_feature(states, self.weights)


class _StateFeatures(GPyTorchModule):
    """GP features from encoded inputs ``[plain (p), states_0 (M_0), ...]``.

    With ``currents`` the encoded inputs end with one normalised input per
    hysteretic column, passed on as extra features after the ``d`` columns.
    """

    def __init__(
        self,
        d: int,
        hysteretic_dims: tuple[int, ...],
        magnets: list[_MagnetFeature],
        currents: bool = False,
    ) -> None:
        super().__init__()
        self.d = d
        self.hysteretic_dims = hysteretic_dims
        self.plain_dims = tuple(i for i in range(d) if i not in hysteretic_dims)
        self.magnets = nn.ModuleList(magnets)
        self.currents = bool(currents)

    def forward(self, z: Tensor) -> Tensor:
        cols: list[Tensor | None] = [None] * self.d
        for k, c in enumerate(self.plain_dims):
            cols[c] = z[..., k]
        offset = len(self.plain_dims)
        for c, magnet in zip(self.hysteretic_dims, self.magnets, strict=True):
            m = magnet.alpha.numel()
            cols[c] = magnet(z[..., offset : offset + m])
            offset += m
        if self.currents:
            cols.extend(z[..., offset + k] for k in range(len(self.magnets)))
        return torch.stack(cols, dim=-1)  # type: ignore[arg-type]


class _StateGP(ExactGP):
    """Exact GP on hysteron states: features (densities), mean, kernel, likelihood."""

    def __init__(
        self,
        inputs: Tensor,
        targets: Tensor,
        likelihood: Likelihood,
        features: _StateFeatures,
        mean_module: Mean,
        covar_module: Kernel,
    ) -> None:
        super().__init__(inputs, targets, likelihood)
        self.features = features
        self.mean_module = mean_module
        self.covar_module = covar_module

    def transform_inputs(self, X: Tensor) -> Tensor:
        """Identity: the states are already this GP's inputs.

        BoTorch's exact-MLL loss closure calls it on ``train_inputs``.
        """
        return X

    def forward(self, z: Tensor) -> MultivariateNormal:
        x = self.features(z)
        return MultivariateNormal(self.mean_module(x), self.covar_module(x))


def _check_likelihood(likelihood: Likelihood) -> None:
    """Accept the likelihoods whose exact marginal likelihood the H-GP supports."""
    if isinstance(likelihood, FixedNoiseGaussianLikelihood):
        raise ValueError(
            "pass measured noise variances as train_Yvar (units of train_Y squared) "
            "instead of a FixedNoiseGaussianLikelihood: the H-GP standardises them "
            "with train_Y and builds the likelihood itself."
        )
    if not isinstance(likelihood, _GaussianLikelihoodBase):
        raise ValueError(
            "HysteresisGP fits the exact marginal likelihood, which needs a Gaussian "
            f"likelihood; got {type(likelihood).__name__}."
        )
    if not (
        isinstance(likelihood, GaussianLikelihood)
        and type(likelihood.noise_covar) is HomoskedasticNoise
        and likelihood.noise.numel() == 1
    ):
        raise ValueError(
            "HysteresisGP supports one homoskedastic noise level (GaussianLikelihood) "
            "or per-point variances given as train_Yvar; got "
            f"{type(likelihood).__name__} with noise model "
            f"{type(getattr(likelihood, 'noise_covar', None)).__name__}."
        )


class HysteresisGP(Model):
    """Gaussian-process model of a beam response to the state of hysteretic magnets.

    The training inputs are a *history*: row ``t`` of ``train_X`` is the setting
    applied at step ``t`` (in order) and ``train_Y[t]`` the response measured after
    it. Each hysteretic column ``c`` (a key of ``hysteresis``) is a magnet current
    whose exact hysteron states along the history come from its Preisach model;
    the GP input for that column is the normalised magnetisation ``(m + 1) / 2``
    in ``[0, 1]``, where ``m = sum(w * s) / sum(w)``, ``w = density * area``. Field
    scale and offset are not identifiable from beam data, so only the density
    *shape* enters. The densities are parameters of this model
    (``gp.features.magnets[i].raw_density``, positive through GPyTorch's
    ``Positive`` constraint); ``hysteresis_models`` returns Preisach models
    carrying them. Plain columns are scaled to ``[0, 1]`` with BoTorch's
    ``Normalize`` and ``bounds``. The GP itself is built as BoTorch's
    ``SingleTaskGP`` builds its modules (RBF kernel with the dimension-scaled
    lengthscale prior, constant mean, Gaussian likelihood with a LogNormal noise
    prior or, with ``train_Yvar``, a ``FixedNoiseGaussianLikelihood``,
    ``Standardize`` outcome transform), so with no hysteretic columns it is the
    same model.

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
        hysteresis: Map from input column to its Preisach model (copied; its
            density is the starting point of the fit). Empty for a plain GP.
            The state before the first row is the model's initial state, held
            fixed (a ``"learned"`` initial state is used as it is, not refitted).
        bounds: Lower and upper bounds of every input column, shape ``(2, d)``,
            used to scale plain columns to ``[0, 1]``; the data range if omitted.
            Finite, with lower <= upper (equal bounds: a constant column).
        train_Yvar: Measured noise variances of ``train_Y`` [units of ``train_Y``
            squared], shape ``(n, 1)``; a ``FixedNoiseGaussianLikelihood`` then
            replaces the fitted noise level.
        likelihood: Replaces the default Gaussian likelihood; must be a
            homoskedastic ``GaussianLikelihood`` (other likelihoods are rejected).
        covar_module: Replaces the default kernel (acts on the ``d`` features).
        mean_module: Replaces the default constant mean.
        outcome_transform: Transform of ``train_Y``; by default (BoTorch's
            ``DEFAULT``) ``Standardize`` with no lower limit on the standard
            deviation, so that results do not depend on the output's units;
            ``None`` for none.
        candidate_smoothing: Width of the smooth, rate-independent relays used
            for the settings given to ``posterior`` (normalised Preisach input
            units; see ``diffaccel.hysteresis.states.smooth_states``). They start
            exactly at the state and input left by the history, tend to exact
            relays as the width goes to 0, and make the posterior a smooth
            function of the candidate currents, which gradient-based acquisition
            optimisers need (exact relays are piecewise constant). ``None``: a quarter
            of the mesh spacing, ``0.25 / sqrt(2 M)``; ``0``: exact relays.
        density_prior_scale: If set, a ``NormalPrior`` of this standard deviation
            on each raw (softplus-inverse) density about its given value is
            registered (``density_prior``): the given density is a prior guess.
            It matters when few points must constrain many hysterons (e.g. early
            in optimisation) and fades as data accumulate; the fit's restarts
            sample it. ``None``: no density prior.
        current_feature: Also give the GP, for each hysteretic column, its
            input normalised to the Preisach input range (``(u - lo) / (hi -
            lo)``, an extra feature after the ``d`` columns: ``features``
            returns ``d + len(hysteresis)`` columns). The magnetisation of
            exact relays is a staircase along a sweep (one step per mesh row
            crossed); a response that also follows the input continuously
            (the reversible part of a magnet's field: the linear term of
            :class:`PreisachModel`) needs the input itself, and with it the
            model contains the plain GP (a long magnetisation lengthscale).

    Shapes:
        ``posterior(X)`` maps ``(*b, q, d)`` to a posterior over ``(*b, q, 1)``.

    Raises:
        ValueError: for shapes, NaN or infinite values, magnitudes beyond
            1e100 (a unit or parsing error), fewer than 3 points,
            constant outputs, a hysteretic column outside ``0..d-1``, training
            currents outside a Preisach model's ``input_range``, negative
            ``train_Yvar`` or an unsupported likelihood.

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
        train_Yvar: Tensor | None = None,
        likelihood: Likelihood | None = None,
        covar_module: Kernel | None = None,
        mean_module: Mean | None = None,
        outcome_transform: OutcomeTransform | _DefaultType | None = DEFAULT,
        candidate_smoothing: float | None = None,
        density_prior_scale: float | None = None,
        current_feature: bool = False,
    ) -> None:
        super().__init__()
        # 1. validate
        _validate_training_data(train_X, train_Y, train_Yvar)
        if likelihood is not None:
            if train_Yvar is not None:
                raise ValueError(
                    "give either train_Yvar (fixed noise) or a likelihood, not both."
                )
            _check_likelihood(likelihood)
        d = train_X.shape[-1]
        for c in hysteresis:
            if not is_integer(c):
                raise ValueError(
                    f"hysteresis keys must be int column indices of train_X; got "
                    f"{c!r} ({type(c).__name__})."
                )
            if not isinstance(hysteresis[c], PreisachModel):
                raise ValueError(
                    f"hysteresis[{c}] must be a PreisachModel; got "
                    f"{type(hysteresis[c]).__name__}."
                )
        hysteresis = {int(c): pm for c, pm in hysteresis.items()}
        dims = sorted(hysteresis)
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
        if not torch.isfinite(bounds).all():
            raise ValueError(
                f"bounds contain NaN or infinite values; got {bounds.tolist()}."
            )
        if (bounds[0] > bounds[1]).any():
            raise ValueError(
                f"bounds need lower <= upper in every column; got {bounds.tolist()}."
            )
        if candidate_smoothing is not None and not candidate_smoothing >= 0:
            raise ValueError(
                f"candidate_smoothing must be >= 0 or None; got {candidate_smoothing}."
            )
        if density_prior_scale is not None and not density_prior_scale > 0:
            raise ValueError(
                f"density_prior_scale must be > 0 or None; got {density_prior_scale}."
            )
        self.hysteretic_dims: tuple[int, ...] = tuple(dims)
        self.plain_dims: tuple[int, ...] = tuple(i for i in range(d) if i not in dims)
        self.candidate_smoothing = candidate_smoothing
        self.density_prior_scale = density_prior_scale
        self.current_feature = bool(current_feature)
        self.register_buffer("bounds", bounds.clone())
        self.register_buffer("train_X", train_X.detach().clone())
        self.register_buffer("train_Y", train_Y.detach().clone())
        yvar_buffer = None if train_Yvar is None else train_Yvar.detach().clone()
        self.register_buffer("train_Yvar", yvar_buffer)

        # 2. transform: plain columns -> [0, 1]; hysteretic columns -> exact states
        # along the history (they do not depend on the density)
        if self.plain_dims:
            idx = list(self.plain_dims)
            lo, hi = bounds[0, idx], bounds[1, idx]
            hi = torch.where(hi > lo, hi, lo + 1.0)  # constant column: shift only
            self.plain_transform = Normalize(
                d=len(idx), bounds=torch.stack([lo, hi])
            ).to(train_X)
        given = [copy.deepcopy(hysteresis[c]).to(train_X) for c in dims]
        self._given = given  # plain list: templates for ``hysteresis_models``
        blocks = [self._plain_features(train_X)]
        for c, pm in zip(dims, given, strict=True):
            pm.check_input_range(train_X[:, c], f"training inputs of column {c}")
            with torch.no_grad():
                blocks.append(pm.states(train_X[:, c]).to(train_X))
        if self.current_feature:
            blocks.append(self._currents(train_X))
        train_inputs = torch.cat(blocks, dim=-1)
        if outcome_transform is DEFAULT:
            outcome_transform = _standardize()
        y, yvar = train_Y, train_Yvar
        if outcome_transform is not None:
            outcome_transform.train()
            y, yvar = outcome_transform(train_Y, train_Yvar)
            self.outcome_transform = outcome_transform

        # 3. build modules
        if likelihood is None:
            if yvar is None:
                likelihood = get_gaussian_likelihood_with_lognormal_prior()
            else:
                likelihood = FixedNoiseGaussianLikelihood(noise=yvar.squeeze(-1))
        if covar_module is None:
            n_features = d + (len(dims) if self.current_feature else 0)
            covar_module = get_covar_module_with_dim_scaled_prior(
                ard_num_dims=n_features
            )
        if mean_module is None:
            mean_module = ConstantMean()
        magnets = [_MagnetFeature(pm, density_prior_scale) for pm in given]
        features = _StateFeatures(
            d, self.hysteretic_dims, magnets, currents=self.current_feature
        )
        self.gp = _StateGP(
            train_inputs,
            y.squeeze(-1).detach(),
            likelihood,
            features,
            mean_module,
            covar_module,
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
        """Observation-noise standard deviation in units of ``train_Y``.

        The fitted level, or with ``train_Yvar`` the root mean given variance.
        """
        noise = self.gp.likelihood.noise.mean()
        return noise.sqrt() * self._outcome_scale()

    def _outcome_scale(self) -> Tensor:
        ot = getattr(self, "outcome_transform", None)
        if isinstance(ot, Standardize):
            return ot.stdvs.squeeze()
        return torch.ones((), dtype=self.train_X.dtype, device=self.train_X.device)

    def marginal_log_likelihood(self) -> ExactMarginalLogLikelihood:
        """GPyTorch's exact marginal log likelihood of the inner GP.

        Its value on the training data (per point, with every registered prior:
        noise, lengthscales, densities) is what :func:`fit_hysteresis_gp`
        maximises over the GP hyperparameters and the Preisach densities.
        """
        return ExactMarginalLogLikelihood(self.gp.likelihood, self.gp)

    # ---------------------------------------------------------------- features
    @property
    def hysteresis_models(self) -> list[PreisachModel]:
        """Preisach models of the hysteretic columns carrying the current densities.

        New copies on every call (changing them does not change this model).
        """
        out = []
        for pm, magnet in zip(self._given, self.gp.features.magnets, strict=True):
            pm = copy.deepcopy(pm).to(self.train_X)
            with torch.no_grad():
                pm.raw_density.copy_(magnet.raw_density)
            out.append(pm)
        return out

    def _plain_features(self, X: Tensor) -> Tensor:
        if not self.plain_dims:
            return X[..., :0]
        return self.plain_transform(X[..., list(self.plain_dims)])

    def _currents(self, X: Tensor) -> Tensor:
        """Hysteretic inputs normalised to their Preisach ranges, ``(*b, q, H)``."""
        cols = []
        for c, pm in zip(self.hysteretic_dims, self._given, strict=True):
            lo, hi = pm.input_range
            cols.append((X[..., c] - lo) / (hi - lo))
        return torch.stack(cols, dim=-1)

    def _normalised(self, i: int, u: Tensor) -> Tensor:
        # settings beyond the Preisach input range saturate every hysteron alike
        lo, hi = self._given[i].input_range
        return ((u - lo) / (hi - lo)).clamp(0.0, 1.0)

    def history_states(self, i: int) -> Tensor:
        """Exact hysteron states of hysteretic input ``i`` along the training history.

        Args:
            i: Position of the column in ``hysteretic_dims``.

        Returns:
            States in ``{-1, +1}``, shape ``(n, M)``.
        """
        start = len(self.plain_dims)
        for magnet in self.gp.features.magnets[:i]:
            start += magnet.alpha.numel()
        m = self.gp.features.magnets[i].alpha.numel()
        return self.gp.train_inputs[0][:, start : start + m]

    def train_features(self) -> Tensor:
        """GP inputs along the training history (differentiable in the densities).

        Returns:
            Features in ``[0, 1]``, shape ``(n, d)`` (``(n, d + H)`` with
            ``current_feature``: the ``H`` normalised hysteretic inputs last).
        """
        return self.gp.features(self.gp.train_inputs[0])

    def smoothing_width(self, i: int) -> float:
        """Candidate relay width of hysteretic input ``i`` (normalised units)."""
        if self.candidate_smoothing is not None:
            return float(self.candidate_smoothing)
        return 0.25 / math.sqrt(2.0 * self.gp.features.magnets[i].alpha.numel())

    def encode(self, X: Tensor, exact: bool = False) -> Tensor:
        """Inputs of the inner GP for settings applied in order after the history.

        Plain columns scaled to ``[0, 1]``, then the hysteron states of each
        hysteretic column. These start from the exact state and input at the end
        of the history and follow smooth relays of width :meth:`smoothing_width`
        (exact relays if it is 0 or ``exact`` is True).

        Args:
            X: Settings, shape ``(*b, q, d)``; along ``q`` they are applied in order
                starting from the state at the end of the training history.
            exact: Use exact relays whatever the smoothing width.

        Returns:
            Encoded inputs, shape ``(*b, q, p + M_1 + ...)`` with ``p`` plain
            columns and ``M_i`` hysterons of hysteretic column ``i`` (with
            ``current_feature``, then the ``H`` normalised hysteretic inputs).
        """
        blocks = [self._plain_features(X)]
        for i, (c, magnet) in enumerate(
            zip(self.hysteretic_dims, self.gp.features.magnets, strict=True)
        ):
            x = self._normalised(i, X[..., c])
            s_end = self.history_states(i)[-1].to(X)
            alpha, beta = magnet.alpha.to(X), magnet.beta.to(X)
            width = 0.0 if exact else self.smoothing_width(i)
            if width > 0:
                x_end = self._normalised(i, self.train_X[-1, c]).to(X)
                states = smooth_states(x, alpha, beta, s_end, width, start=x_end)
            else:
                states = exact_states(x, alpha, beta, s_end)
            blocks.append(states)
        if self.current_feature:
            blocks.append(self._currents(X))
        return torch.cat(blocks, dim=-1)

    def features(self, X: Tensor, exact: bool = False) -> Tensor:
        """GP features (normalised magnetisations, scaled plain columns) of ``X``.

        Args:
            X: Settings, shape ``(*b, q, d)``, applied in order after the history
                (see :meth:`encode`).
            exact: Use exact relays whatever the smoothing width.

        Returns:
            Features in ``[0, 1]``, shape ``(*b, q, d)`` (``(*b, q, d + H)``
            with ``current_feature``).
        """
        return self.gp.features(self.encode(X, exact=exact))

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
        inputs: Tensor,
        X: Tensor,
        observation_noise: bool | Tensor,
        posterior_transform: Callable | None,
        at_history: bool = False,
    ) -> GPyTorchPosterior | TransformedPosterior:
        lik = self.gp.likelihood
        shape = mvn.batch_shape + mvn.event_shape
        if isinstance(observation_noise, Tensor):  # as BoTorch: model units, (..., 1)
            mvn = lik(mvn, inputs, noise=observation_noise.squeeze(-1).expand(shape))
        elif observation_noise and isinstance(lik, FixedNoiseGaussianLikelihood):
            # training points keep their own variances; new points get the mean
            noise = lik.noise if at_history else lik.noise.mean(-1, keepdim=True)
            mvn = lik(mvn, inputs, noise=noise.expand(shape))
        elif observation_noise:
            mvn = lik(mvn, inputs)
        posterior = GPyTorchPosterior(distribution=mvn)
        ot = getattr(self, "outcome_transform", None)
        if ot is not None:
            standardised = posterior  # model units: GPyTorch's floors are relative
            posterior = ot.untransform_posterior(posterior, X=X)
            if isinstance(ot, Standardize) and type(posterior) is GPyTorchPosterior:
                posterior = _RescaledPosterior(
                    posterior.distribution, standardised, self._outcome_scale()
                )
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
            observation_noise: If True, add the observation noise (fitted, or
                the mean of ``train_Yvar``); a tensor ``batch x q x 1`` is used as
                the noise variance in model (standardised) units, as in BoTorch.
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
        inputs = self.encode(X)
        mvn = self.gp(inputs)
        return self._wrap(mvn, inputs, X, observation_noise, posterior_transform)

    def posterior_on_history(
        self, observation_noise: bool = False
    ) -> GPyTorchPosterior | TransformedPosterior:
        """Posterior of the responses at the training history itself.

        Args:
            observation_noise: If True, add the observation noise (with
                ``train_Yvar``: each point's own variance).

        Returns:
            Posterior over shape ``(n, 1)`` (units of ``train_Y``).
        """
        self.eval()
        inputs = self.gp.train_inputs[0]
        with warnings.catch_warnings():  # predicting at the training inputs is meant
            warnings.simplefilter("ignore", GPInputWarning)
            mvn = self.gp(inputs)
        return self._wrap(
            mvn, inputs, self.train_X, observation_noise, None, at_history=True
        )

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
            observation_noise: If True, add the observation noise (fitted, or
                the mean of ``train_Yvar``).

        Returns:
            Posterior over ``(T, 1)`` or ``(*b, T, 1)`` (units of ``train_Y``).

        Raises:
            ValueError: if ``X`` has the wrong last dimension or holds NaN.
        """
        self._check_X(X)
        self.eval()
        inputs = self.encode(X, exact=True)
        mvn = self.gp(inputs)
        return self._wrap(mvn, inputs, X, observation_noise, None)

    def condition_on_observations(
        self, X: Tensor, Y: Tensor, noise: Tensor | None = None, **kwargs: object
    ) -> HysteresisGP:
        """A new model whose history continues with ``X`` and measurements ``Y``.

        The hyperparameters and densities are copied, not refitted; call
        :func:`fit_hysteresis_gp` on the result to refit. BoTorch's spelling of
        :meth:`extended` (``noise`` is its ``Yvar``).

        Args:
            X: As ``X`` of :meth:`extended`.
            Y: As ``Y`` of :meth:`extended`.
            noise: As ``Yvar`` of :meth:`extended`.
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
        return self.extended(X, Y, Yvar=noise)

    def extended(
        self, X: Tensor, Y: Tensor, Yvar: Tensor | None = None
    ) -> HysteresisGP:
        """Same model (densities, priors, hyperparameters) on the history continued.

        Args:
            X: Settings applied after the history, in order, shape ``(n', d)``.
            Y: Responses measured after each, shape ``(n', 1)``.
            Yvar: Their noise variances ``(n', 1)``; required exactly when the
                model was built with ``train_Yvar``.

        Returns:
            A new :class:`HysteresisGP`; the outcome transform is re-fitted to the
            extended data.

        Raises:
            ValueError: if ``Yvar`` is missing for a fixed-noise model or given
                for a fitted-noise one.
        """
        if (Yvar is None) != (self.train_Yvar is None):
            raise ValueError(
                "Yvar is required exactly when the model was built with train_Yvar; "
                f"model has train_Yvar: {self.train_Yvar is not None}, got Yvar: "
                f"{Yvar is not None}."
            )
        new_X = torch.cat([self.train_X, X.to(self.train_X)])
        new_Y = torch.cat([self.train_Y, Y.to(self.train_Y)])
        modules: dict[str, object] = {}
        new_Yvar = None
        if self.train_Yvar is None:
            modules["likelihood"] = copy.deepcopy(self.gp.likelihood)
        else:
            new_Yvar = torch.cat([self.train_Yvar, Yvar.to(self.train_Yvar)])
        ot = getattr(self, "outcome_transform", None)
        new = HysteresisGP(
            new_X,
            new_Y,
            hysteresis=dict(zip(self.hysteretic_dims, self._given, strict=True)),
            bounds=self.bounds,
            train_Yvar=new_Yvar,
            covar_module=copy.deepcopy(self.gp.covar_module),
            mean_module=copy.deepcopy(self.gp.mean_module),
            outcome_transform=None if ot is None else _standardize(),
            candidate_smoothing=self.candidate_smoothing,
            density_prior_scale=self.density_prior_scale,
            current_feature=self.current_feature,
            **modules,
        )
        with torch.no_grad():  # the fitted densities; the priors stay the given ones
            for old, mag in zip(
                self.gp.features.magnets, new.gp.features.magnets, strict=True
            ):
                mag.raw_density.copy_(old.raw_density)
        return new


def _validate_training_data(
    train_X: Tensor, train_Y: Tensor, train_Yvar: Tensor | None
) -> None:
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
    for name, v in (("train_X", train_X), ("train_Y", train_Y)):
        big = v.abs() > MAX_MAGNITUDE
        if big.any():
            i, c = (int(k) for k in big.nonzero()[0])
            raise ValueError(
                f"{name} row {i}, column {c} is {float(v[i, c]):.6g}: beyond "
                f"{MAX_MAGNITUDE:.0e} in magnitude, not a measurement (a unit or "
                "parsing error?)."
            )
    if train_Yvar is not None:
        if not isinstance(train_Yvar, Tensor) or train_Yvar.shape != train_Y.shape:
            raise ValueError(
                f"train_Yvar must be a tensor of shape (n, 1) = "
                f"({train_X.shape[0]}, 1); got "
                f"{getattr(train_Yvar, 'shape', type(train_Yvar).__name__)}."
            )
        if not (torch.isfinite(train_Yvar).all() and (train_Yvar >= 0).all()):
            raise ValueError(
                "train_Yvar holds negative, NaN or infinite noise variances."
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
        mll: Exact marginal log likelihood per point (with priors) of the kept
            parameters.
        noise_sigma: Noise standard deviation [units of ``train_Y``].
        restart_mlls: Final ``mll`` of every restart, in order (``-inf`` for a
            restart that failed numerically).
        best_restart: Index of the restart kept.
        fit_s: Wall-clock time of the fit [s].
    """

    mll: float
    noise_sigma: float
    restart_mlls: tuple[float, ...]
    best_restart: int
    fit_s: float


def _accept_optimizer_warning(w: warnings.WarningMessage) -> bool:
    """Every restart's end point competes: a stop at the iteration limit or an
    abnormal line search still leaves a point at least as good as its start."""
    logger.debug("H-GP fit: %s", w.message)
    return True


def fit_hysteresis_gp(
    model: HysteresisGP,
    restarts: int = 3,
    max_iter: int = 200,
    fit_density: bool = True,
    seed: int = 0,
    callback: Callable[[int, float], None] | None = None,
    density_starts: Sequence[Sequence[Tensor]] | None = None,
) -> HGPFitResult:
    """Fit Preisach densities and GP hyperparameters jointly on the exact MLL.

    BoTorch's ``fit_gpytorch_mll`` maximises GPyTorch's
    ``ExactMarginalLogLikelihood`` of ``model.gp``, as returned by
    ``model.marginal_log_likelihood()`` (data term plus every registered prior,
    e.g. the LogNormal noise prior that keeps the model from explaining
    everything as noise, and the density prior if the model has one) with
    scipy's L-BFGS-B
    over all its free parameters, the raw densities included. Restarts go
    through BoTorch's fallback (``pick_best_of_all_attempts``): restart 0 starts
    from the model as given, later ones from values drawn by
    ``sample_all_priors``; restarts failing with ``NotPSDError`` are discarded
    and the best restart is kept. Only density *shapes* are fitted (features
    use normalised magnetisations), never field scale or offset.

    With ``density_starts`` each start's densities begin their own
    optimisation from the model's hyperparameters as given (the first start
    also takes the prior-sampled restarts): ``max(restarts, len(starts))``
    optimisations in all, the one of highest marginal likelihood kept.

    Args:
        model: The model to fit in place.
        restarts: Number of optimisations (``>= 1``).
        max_iter: L-BFGS-B iterations per restart.
        fit_density: If False, keep the Preisach densities fixed (e.g. measured).
        seed: Seed of the random restarts (torch's global generator is forked,
            so the caller's random state is left unchanged).
        callback: Called after each restart with ``(restart, mll)``.
        density_starts: Starting raw densities (``raw_density`` of each
            hysteretic column, in order) of the first optimisations, e.g.
            those of :class:`JointStart`; ``None``: the model's own.

    Returns:
        A :class:`HGPFitResult`; ``model`` holds the best parameters, in eval mode.

    Raises:
        ValueError: if ``restarts < 1`` or ``max_iter < 1``, or a density start
            does not match the model's magnets.
        RuntimeError: if every restart failed numerically.
    """
    if not density_starts:
        return _fit_restarts(model, restarts, max_iter, fit_density, seed, callback)
    magnets = model.gp.features.magnets
    for start in density_starts:
        shapes = [tuple(torch.as_tensor(r).shape) for r in start]
        if shapes != [tuple(m.raw_density.shape) for m in magnets]:
            raise ValueError(
                f"density start shapes {shapes} do not match the model's "
                f"{[tuple(m.raw_density.shape) for m in magnets]}."
            )
    t0 = time.perf_counter()
    given = copy.deepcopy(model.state_dict())
    runs: list[tuple[HGPFitResult, dict]] = []
    values: list[float] = []
    for i, start in enumerate(density_starts):
        model.load_state_dict(given)
        with torch.no_grad():
            for mag, raw in zip(magnets, start, strict=True):
                mag.raw_density.copy_(torch.as_tensor(raw).to(mag.raw_density))
        n = max(1, restarts - len(density_starts) + 1) if i == 0 else 1
        offset = len(values)

        def relay(r: int, v: float, offset: int = offset) -> None:
            if callback is not None:
                callback(offset + r, v)

        try:
            res = _fit_restarts(model, n, max_iter, fit_density, seed + i, relay)
        except RuntimeError:
            values.extend([-math.inf] * n)
            continue
        values.extend(res.restart_mlls)
        runs.append((res, copy.deepcopy(model.state_dict())))
    if not runs:
        raise RuntimeError(
            f"every one of the {len(values)} H-GP fit restarts failed numerically "
            "(covariance not positive definite); check the data for outliers or "
            "duplicated rows with different responses."
        )
    best_res, best_state = max(runs, key=lambda r: r[0].mll)
    model.load_state_dict(best_state)
    model.eval()
    return HGPFitResult(
        mll=best_res.mll,
        noise_sigma=float(model.noise_sigma.detach()),
        restart_mlls=tuple(values),
        best_restart=max(range(len(values)), key=lambda r: values[r]),
        fit_s=time.perf_counter() - t0,
    )


def _fit_restarts(
    model: HysteresisGP,
    restarts: int,
    max_iter: int,
    fit_density: bool,
    seed: int,
    callback: Callable[[int, float], None] | None,
) -> HGPFitResult:
    """:func:`fit_hysteresis_gp` from the model's own densities."""
    if restarts < 1 or max_iter < 1:
        raise ValueError(
            f"restarts and max_iter must be >= 1; got {restarts} and {max_iter}."
        )
    t0 = time.perf_counter()
    mll = model.marginal_log_likelihood()
    values: list[float] = []

    def optimizer(mll: ExactMarginalLogLikelihood, **kwargs: object) -> object:
        values.append(-math.inf)  # stays so if the restart raises
        result = fit_gpytorch_mll_scipy(mll, **kwargs)
        values[-1] = -float(result.fval)
        if callback is not None:
            callback(len(values) - 1, values[-1])
        return result

    densities = [mag.raw_density for mag in model.gp.features.magnets]
    grads = [p.requires_grad for p in densities]
    try:
        for p in densities:
            p.requires_grad_(fit_density)
        with torch.random.fork_rng():
            torch.manual_seed(seed)
            fit_gpytorch_mll(
                mll,
                optimizer=optimizer,
                optimizer_kwargs={"options": {"maxiter": max_iter}},
                max_attempts=restarts,
                pick_best_of_all_attempts=True,
                warning_handler=_accept_optimizer_warning,
            )
    except ModelFittingError as err:
        raise RuntimeError(
            f"every one of the {restarts} H-GP fit restarts failed numerically "
            "(covariance not positive definite); check the data for outliers or "
            "duplicated rows with different responses."
        ) from err
    finally:
        for p, g in zip(densities, grads, strict=True):
            p.requires_grad_(g)
    model.train()
    with torch.no_grad():
        value = float(mll(model.gp(*model.gp.train_inputs), model.gp.train_targets))
    model.eval()
    best = max(range(len(values)), key=lambda r: values[r])
    return HGPFitResult(
        mll=value,
        noise_sigma=float(model.noise_sigma.detach()),
        restart_mlls=tuple(values),
        best_restart=best,
        fit_s=time.perf_counter() - t0,
    )


#: Lowest noise variance [standardised units] a data-chosen likelihood allows:
#: below it the exact GP's covariance of ~100 nearby settings stops being
#: positive definite in float64.
MIN_NOISE_VARIANCE = 1e-8
# width of the data-chosen LogNormal noise prior [log variance]: a factor ~7 in
# variance per standard deviation
_NOISE_PRIOR_SCALE = 2.0
# largest starting noise variance [standardised]: the mode of BoTorch's default
# prior, LogNormal(-4, 1); from a larger start (a poor Preisach fit) the
# optimiser meets a flat likelihood and ends where round-off sends it
_NOISE_START = math.exp(-5.0)


def noise_likelihood(noise_std: float, train_Y: Tensor) -> GaussianLikelihood:
    """Gaussian likelihood whose noise prior and floor come from a noise estimate.

    BoTorch's default (LogNormal(-4, 1) on the standardised variance, floor
    1e-4) assumes noise of ~14 % of the output's standard deviation and never
    below 1 %; a magnet measured to 1e-4 of its range sits far below both, and
    the floor alone then reads as the model's noise. Here the prior is
    LogNormal about the variance of ``noise_std`` (standardised by the
    standard deviation of ``train_Y``, as the H-GP's outcome transform does)
    with a scale of 2 (a factor ~7 in variance), and the floor is a tenth of
    that variance, within ``[MIN_NOISE_VARIANCE, 1e-4]``.

    Args:
        noise_std: Estimate of the noise standard deviation [units of
            ``train_Y``], > 0 (e.g. the rms residual of a Preisach fit).
        train_Y: Training outputs, shape ``(n, 1)``.

    Returns:
        A ``GaussianLikelihood`` starting at the estimated variance.

    Raises:
        ValueError: for a ``noise_std`` that is not positive and finite or a
            constant ``train_Y``.
    """
    if not (math.isfinite(noise_std) and noise_std > 0):
        raise ValueError(f"noise_std must be positive and finite; got {noise_std}.")
    y_std = float(train_Y.std())
    if not y_std > 0:
        raise ValueError("train_Y is constant; no noise level to standardise.")
    var = min(max((noise_std / y_std) ** 2, MIN_NOISE_VARIANCE), 1.0)
    floor = min(max(var / 10.0, MIN_NOISE_VARIANCE), 1e-4)
    prior = LogNormalPrior(loc=math.log(var), scale=_NOISE_PRIOR_SCALE)
    return GaussianLikelihood(
        noise_prior=prior,
        noise_constraint=GreaterThan(
            floor, transform=None, initial_value=max(min(var, _NOISE_START), floor)
        ),
    ).to(train_Y)


@dataclass(frozen=True)
class JointStart:
    """How :func:`joint_gp_from_preisach` started an H-GP.

    Attributes:
        preisach_rmse: Rms residual of the Preisach fit of the response
            [units of ``train_Y``]; the noise prior is centred on it.
        preisach_seconds: Wall-clock time of that fit [s].
        density_starts: Raw densities to start the joint fit from (for
            :func:`fit_hysteresis_gp`): the Preisach fit's, then the given
            model's (e.g. uniform: the better start for a response that is
            not monotone in the magnetisation).
    """

    preisach_rmse: float
    preisach_seconds: float
    density_starts: tuple[tuple[Tensor, ...], ...] = ()


def joint_gp_from_preisach(
    train_X: Tensor,
    train_Y: Tensor,
    preisach: PreisachModel,
    column: int = 0,
    steps: int = 300,
    bounds: Tensor | None = None,
) -> tuple[HysteresisGP, JointStart]:
    """An H-GP of one hysteretic column started from a Preisach fit of the response.

    The joint marginal likelihood has poor optima on real magnets: from a
    uniform density the magnetisation of a quadrupole's major loop is a
    staircase far from its field, and the fit explains the difference as
    noise. Here

    1. a copy of ``preisach`` is fitted to the response against the column's
       input (:func:`fit_preisach`: offset, linear term and density); its
       density starts the H-GP's density;
    2. the H-GP gets the column's normalised input as a feature too
       (``current_feature``: the linear term), so that it contains the plain
       GP;
    3. its noise prior and floor are centred on the Preisach fit's rms
       residual (:func:`noise_likelihood`).

    Fit it with :func:`fit_hysteresis_gp` and ``density_starts`` of the
    returned start: the Preisach fit's density and the given one are each
    optimised (with prior-sampled restarts), ranked by marginal likelihood.

    Args:
        train_X: Settings in the order applied, shape ``(n, d)``.
        train_Y: Responses, shape ``(n, 1)``.
        preisach: Model of column ``column`` (mesh, input range, initial
            state); it is copied, not changed.
        column: The hysteretic column of ``train_X``.
        steps: L-BFGS iterations of the Preisach fit.
        bounds: As for :class:`HysteresisGP` (scaling of plain columns).

    Returns:
        ``(model, start)``: the unfitted :class:`HysteresisGP` and a
        :class:`JointStart`.

    Raises:
        ValueError: as :class:`HysteresisGP` and :func:`fit_preisach` do.
    """
    if not is_integer(column) or not 0 <= int(column) < train_X.shape[-1]:
        raise ValueError(
            f"column must be an int in 0..{train_X.shape[-1] - 1}; got {column!r}."
        )
    _validate_training_data(train_X, train_Y, None)
    pm = copy.deepcopy(preisach).to(train_X)
    t0 = time.perf_counter()
    fit = fit_preisach(pm, train_X[:, int(column)], train_Y[:, 0], steps=steps)
    seconds = time.perf_counter() - t0
    y_std = float(train_Y.std())
    noise = max(fit.rmse, math.sqrt(MIN_NOISE_VARIANCE) * y_std)
    model = HysteresisGP(
        train_X,
        train_Y,
        hysteresis={int(column): pm},
        bounds=bounds,
        likelihood=noise_likelihood(noise, train_Y),
        current_feature=True,
    )
    starts = (
        (pm.raw_density.detach().clone(),),
        (preisach.raw_density.detach().to(train_X).clone(),),
    )
    return model, JointStart(fit.rmse, seconds, starts)
