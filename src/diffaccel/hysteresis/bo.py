"""Bayesian optimisation of a beam response over hysteretic magnet settings.

:class:`HysteresisBO` is an ask/tell loop: ``tell`` records measurements (in the
order the settings were applied) and refits a :class:`HysteresisGP`; ``ask``
proposes the next setting(s) with a stock BoTorch acquisition function, judged
from the magnetic state the applied history left behind.
"""

from __future__ import annotations

import copy
import logging
import math
import operator
from collections.abc import Mapping
from typing import Literal

import torch
from botorch.acquisition import (
    LogExpectedImprovement,
    UpperConfidenceBound,
    qLogExpectedImprovement,
    qUpperConfidenceBound,
)
from botorch.acquisition.acquisition import AcquisitionFunction
from botorch.optim import optimize_acqf
from torch import Tensor

from diffaccel.dynamics import is_integer
from diffaccel.hysteresis.hgp import HGPFitResult, HysteresisGP, fit_hysteresis_gp
from diffaccel.hysteresis.preisach import PreisachModel

__all__ = ["HysteresisBO"]

logger = logging.getLogger(__name__)

Acquisition = Literal["ucb", "logei"]


def _positive_int(name: str, value: object) -> int:
    """``value`` as an int >= 1, or a ValueError naming ``name``."""
    try:
        if isinstance(value, bool):
            raise TypeError
        n = operator.index(value)
    except TypeError:
        raise ValueError(f"{name} must be an int >= 1; got {value!r}.") from None
    if n < 1:
        raise ValueError(f"{name} must be >= 1; got {n}.")
    return n


class HysteresisBO:
    """Ask/tell Bayesian optimiser of a beam response over magnet settings.

    Hysteretic input columns (keys of ``hysteresis``) are magnet currents whose
    effect goes through a Preisach model of the applied history; other columns
    are plain inputs. After each ``tell`` the H-GP is rebuilt on the whole
    history and refitted, warm-started from the previous fit. ``ask(q)`` returns
    ``q`` settings to be applied *in that order*: the acquisition judges each
    from the state left by the ones before it. With ``hysteresis={}`` the model
    is exactly BoTorch's ``SingleTaskGP`` (plain-GP baseline). Each refit starts
    the densities from the given Preisach models (the prior guess, e.g. uniform
    or measured on a test stand) and warm-starts the GP hyperparameters.

    Args:
        bounds: Lower and upper bound of each input, shape ``(2, d)``, in the
            units of the inputs (current [A] for hysteretic columns).
        hysteresis: Map from input column to its Preisach model (prior guess;
            its density is refitted with the GP).
        acquisition: ``"ucb"`` (upper confidence bound) or ``"logei"`` (log
            expected improvement); the ``q > 1`` versions are the Monte-Carlo
            ``qUCB`` / ``qLogEI``.
        beta: UCB exploration weight (``mean + sqrt(beta) * sigma``).
        maximize: Maximise the response if True, minimise it otherwise.
        fit_restarts: Restarts of each H-GP fit (see ``fit_hysteresis_gp``).
        fit_max_iter: L-BFGS-B iterations per fit restart.
        fit_density: Refit the Preisach densities with the GP (True) or keep
            the given densities (e.g. measured on a test stand) fixed.
        density_prior_scale: Prior width of the refitted raw densities about
            the given ones (see ``HysteresisGP``); ``None`` for no prior.
        num_restarts: Starting points of the acquisition optimiser.
        raw_samples: Random samples used to choose those starting points.
        seed: Seed of the fit restarts and acquisition optimiser.

    Shapes:
        ``tell(X (n, d), Y (n, 1))``; ``ask(q) -> (q, d)``.

    Raises:
        ValueError: for malformed bounds, an unknown acquisition or bad data.

    Example:
        >>> import torch
        >>> bo = HysteresisBO(torch.tensor([[0.0], [1.0]], dtype=torch.float64), {})
        >>> X = torch.tensor([[0.1], [0.5], [0.9]], dtype=torch.float64)
        >>> bo.tell(X, -((X - 0.4) ** 2))
        >>> bo.ask().shape
        torch.Size([1, 1])
    """

    def __init__(
        self,
        bounds: Tensor,
        hysteresis: Mapping[int, PreisachModel],
        acquisition: Acquisition = "ucb",
        beta: float = 2.0,
        maximize: bool = True,
        fit_restarts: int = 1,
        fit_max_iter: int = 100,
        fit_density: bool = True,
        density_prior_scale: float | None = 1.0,
        num_restarts: int = 4,
        raw_samples: int = 128,
        seed: int = 0,
    ) -> None:
        bounds = torch.as_tensor(bounds)
        if bounds.dim() != 2 or bounds.shape[0] != 2 or not bounds.is_floating_point():
            raise ValueError(
                f"bounds must be a float tensor of shape (2, d); got "
                f"{tuple(bounds.shape)} {bounds.dtype}."
            )
        if not torch.isfinite(bounds).all():
            raise ValueError(
                f"bounds contain NaN or infinite values; got {bounds.tolist()}."
            )
        if not (bounds[1] > bounds[0]).all():
            raise ValueError(f"bounds need lower < upper; got {bounds.tolist()}.")
        d = bounds.shape[1]
        for c in hysteresis:
            if not is_integer(c):
                raise ValueError(
                    f"hysteresis keys must be int column indices; got {c!r}."
                )
            if not 0 <= c < d:
                raise ValueError(
                    f"hysteresis column {c} does not exist: bounds have d={d} "
                    f"columns (0..{d - 1})."
                )
        if acquisition not in ("ucb", "logei"):
            raise ValueError(
                f"acquisition must be 'ucb' or 'logei'; got {acquisition!r}."
            )
        try:
            beta_f = float(beta)
        except (TypeError, ValueError, RuntimeError):
            msg = f"beta must be a finite number > 0; got {beta!r}."
            raise ValueError(msg) from None
        if not (math.isfinite(beta_f) and beta_f > 0):
            raise ValueError(f"beta must be finite and > 0; got {beta}.")
        fit_restarts = _positive_int("fit_restarts", fit_restarts)
        fit_max_iter = _positive_int("fit_max_iter", fit_max_iter)
        num_restarts = _positive_int("num_restarts", num_restarts)
        raw_samples = _positive_int("raw_samples", raw_samples)
        self.bounds = bounds
        self.hysteresis = {int(c): pm for c, pm in hysteresis.items()}
        self.acquisition = acquisition
        self.beta = float(beta)
        self.maximize = bool(maximize)
        self.fit_restarts = int(fit_restarts)
        self.fit_max_iter = int(fit_max_iter)
        self.fit_density = bool(fit_density)
        self.density_prior_scale = density_prior_scale
        self.num_restarts = int(num_restarts)
        self.raw_samples = int(raw_samples)
        self.seed = int(seed)
        self.X = bounds.new_zeros(0, bounds.shape[1])
        self.Y = bounds.new_zeros(0, 1)
        self.model: HysteresisGP | None = None
        self.last_fit: HGPFitResult | None = None
        self._n_fits = 0

    # ------------------------------------------------------------------ data
    def tell(self, X: Tensor, Y: Tensor) -> None:
        """Record settings applied in order and the responses measured after each.

        Args:
            X: Settings, shape ``(n, d)`` (or ``(d,)`` for one).
            Y: Responses, shape ``(n, 1)`` (or ``(n,)`` / scalar).

        Raises:
            ValueError: for shape mismatches or non-finite values.
        """
        X = torch.as_tensor(X, dtype=self.bounds.dtype, device=self.bounds.device)
        Y = torch.as_tensor(Y, dtype=self.bounds.dtype, device=self.bounds.device)
        X = X.reshape(-1, self.bounds.shape[1]) if X.dim() <= 1 else X
        Y = Y.reshape(-1, 1)
        if X.dim() != 2 or X.shape[-1] != self.bounds.shape[1]:
            raise ValueError(
                f"X must have shape (n, {self.bounds.shape[1]}); got {tuple(X.shape)}."
            )
        if Y.shape[0] != X.shape[0]:
            raise ValueError(
                f"X has {X.shape[0]} settings but Y has {Y.shape[0]} responses."
            )
        if not (torch.isfinite(X).all() and torch.isfinite(Y).all()):
            raise ValueError("X and Y must be finite (no NaN or inf).")
        self.X = torch.cat([self.X, X])
        self.Y = torch.cat([self.Y, Y])
        if self.X.shape[0] >= 3 and bool((self.Y != self.Y[0]).any()):
            self._refit()
        else:
            self.model = None

    def _refit(self) -> None:
        sign = 1.0 if self.maximize else -1.0
        prev = self.model
        modules: dict[str, object] = {}
        if prev is not None:  # warm-start the GP; densities restart from the prior
            modules = {
                "likelihood": copy.deepcopy(prev.gp.likelihood),
                "covar_module": copy.deepcopy(prev.gp.covar_module),
                "mean_module": copy.deepcopy(prev.gp.mean_module),
            }
        hyst: Mapping[int, PreisachModel] = self.hysteresis
        model = HysteresisGP(
            self.X,
            sign * self.Y,
            hysteresis=hyst,
            bounds=self.bounds,
            # a prior on frozen densities only adds a constant to the MLL, which
            # makes L-BFGS-B's relative stopping test end the fit early
            density_prior_scale=(
                self.density_prior_scale if hyst and self.fit_density else None
            ),
            **modules,
        )
        self.last_fit = fit_hysteresis_gp(
            model,
            restarts=self.fit_restarts,
            max_iter=self.fit_max_iter,
            fit_density=self.fit_density,
            seed=self.seed + self._n_fits,
        )
        self._n_fits += 1
        self.model = model

    # -------------------------------------------------------------- proposals
    def acquisition_function(self, q: int = 1) -> AcquisitionFunction:
        """The acquisition function of the current model (responses maximised).

        Args:
            q: Number of settings proposed jointly (applied in order).

        Returns:
            A BoTorch acquisition function over ``batch x q x d`` inputs.

        Raises:
            RuntimeError: before a model could be fitted (fewer than 3 points or
                constant responses).
        """
        if self.model is None:
            raise RuntimeError(
                "no model yet: tell at least 3 settings with non-constant responses "
                "before asking."
            )
        best = (self.Y if self.maximize else -self.Y).max()
        if q == 1:
            if self.acquisition == "ucb":
                return UpperConfidenceBound(self.model, beta=self.beta)
            return LogExpectedImprovement(self.model, best_f=best)
        if self.acquisition == "ucb":
            return qUpperConfidenceBound(self.model, beta=self.beta)
        return qLogExpectedImprovement(self.model, best_f=best)

    def ask(self, q: int = 1) -> Tensor:
        """Propose the next ``q`` settings, to be applied in this order.

        Args:
            q: Number of settings (``>= 1``).

        Returns:
            Settings, shape ``(q, d)``.

        Raises:
            ValueError: unless ``q`` is an int >= 1.
        """
        q = _positive_int("q", q)
        acq = self.acquisition_function(q)
        gen = torch.random.fork_rng()
        with gen:
            torch.manual_seed(self.seed + 7919 * self._n_fits)
            cand, _ = optimize_acqf(
                acq,
                bounds=self.bounds,
                q=q,
                num_restarts=self.num_restarts,
                raw_samples=self.raw_samples,
            )
        return cand.detach()

    @property
    def best(self) -> tuple[Tensor, Tensor]:
        """Best measured setting ``(d,)`` and its response ``()`` so far."""
        if self.Y.shape[0] == 0:
            raise RuntimeError("no measurements yet.")
        i = int(self.Y.argmax() if self.maximize else self.Y.argmin())
        return self.X[i], self.Y[i, 0]
