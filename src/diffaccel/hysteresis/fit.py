"""Fitting a Preisach model to a measured input/output history."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import Tensor

from diffaccel.data.magnet_stream import MAX_MAGNITUDE
from diffaccel.dynamics import as_real_tensor
from diffaccel.dynamics.linalg import lstsq
from diffaccel.hysteresis.preisach import PreisachModel

__all__ = [
    "MAX_MAGNITUDE",
    "MIN_FIT_POINTS",
    "FitResult",
    "check_series",
    "density_roughness",
    "fit_preisach",
]

logger = logging.getLogger(__name__)

# offset, slope and scale need at least three points; two more to see a loop
MIN_FIT_POINTS = 5


@dataclass
class FitResult:
    """Outcome of :func:`fit_preisach`.

    Attributes:
        rmse: Root-mean-square training residual [output units].
        rmse_percent: ``rmse`` in percent of the training output range [%].
        loss: Final objective (normalised mse + regularisation) [1].
        losses: Objective at every evaluation (L-BFGS) or step (Adam) [1].
        steps: Objective evaluations (L-BFGS) or steps (Adam) taken.
        seconds: Wall-clock duration of the fit [s].
        optimizer: ``"lbfgs"`` or ``"adam"``.
    """

    rmse: float
    rmse_percent: float
    loss: float
    losses: list[float] = field(default_factory=list)
    steps: int = 0
    seconds: float = 0.0
    optimizer: str = "lbfgs"


def _neighbour_pairs(alpha: Tensor, beta: Tensor) -> tuple[Tensor, Tensor]:
    """Index pairs of mesh neighbours along rows (equal alpha) and columns."""
    pairs_i, pairs_j = [], []
    for key, along in ((alpha, beta), (beta, alpha)):
        order = torch.argsort(along, stable=True)
        order = order[torch.argsort(key[order], stable=True)]
        same = key[order[1:]] == key[order[:-1]]
        pairs_i.append(order[:-1][same])
        pairs_j.append(order[1:][same])
    return torch.cat(pairs_i), torch.cat(pairs_j)


def density_roughness(model: PreisachModel) -> Tensor:
    """Mean squared difference of the relative density between mesh neighbours.

    Neighbours are consecutive points of equal ``alpha`` (rows) or equal
    ``beta`` (columns), which for a triangular mesh is its 4-neighbourhood. The
    density is divided by its mean first, so the penalty does not depend on the
    (unidentifiable) overall density scale.

    Returns:
        Scalar roughness [1]; 0 for a mesh without row/column neighbours.
    """
    i, j = _neighbour_pairs(model.alpha, model.beta)
    if i.numel() == 0:
        return model.raw_density.sum() * 0.0
    d = model.density
    d = d / d.mean()
    return ((d[i] - d[j]) ** 2).mean()


class _Roughness(torch.nn.Module):
    """``density_roughness`` as a module, for ``torch.func.functional_call``."""

    def __init__(self, model: PreisachModel) -> None:
        super().__init__()
        self.model = model

    def forward(self) -> Tensor:
        return density_roughness(self.model)


class _FromStates(torch.nn.Module):
    """The model's output from a fixed exact state table ``(T, M)``.

    With a known initial state the relay states of a training history do not
    depend on the parameters, so a fit can compute them once and evaluate the
    output as one matrix-vector product (for ``torch.func.functional_call``).
    """

    def __init__(self, model: PreisachModel, un: Tensor, states: Tensor) -> None:
        super().__init__()
        self.model = model
        self.un = un
        self.states = states

    def forward(self) -> Tensor:
        w = self.model.weights
        return self.model._output(self.un, (self.states @ w) / w.sum())


# largest state table (T x M entries, float64) a fit precomputes: 40 MB
_MAX_STATE_TABLE = 5_000_000


def check_series(
    current: Tensor, field_: Tensor, dtype, device
) -> tuple[Tensor, Tensor]:
    """Checked 1-D training series ``(current, output)`` as ``dtype`` on ``device``.

    Raises:
        ValueError: naming the problem (shape, length, NaN/inf, magnitude,
            constant output, too few points).
    """
    u = as_real_tensor(current, "current", dtype=dtype, device=device)
    y = as_real_tensor(field_, "output", dtype=dtype, device=device)
    if u.ndim != 1 or y.ndim != 1:
        raise ValueError(
            "fit_preisach needs 1-D time series; got current shape "
            f"{tuple(u.shape)} and output shape {tuple(y.shape)}."
        )
    if u.shape != y.shape:
        raise ValueError(
            f"current and output lengths differ: {u.numel()} vs {y.numel()}."
        )
    if u.numel() < MIN_FIT_POINTS:
        raise ValueError(
            f"fit_preisach needs at least {MIN_FIT_POINTS} points; got {u.numel()}."
        )
    if not (torch.isfinite(u).all() and torch.isfinite(y).all()):
        raise ValueError("current or output contains NaN or infinite values.")
    for name, v in (("current", u), ("output", y)):
        big = v.abs() > MAX_MAGNITUDE
        if big.any():
            i = int(big.nonzero()[0, 0])
            raise ValueError(
                f"{name} row {i} is {float(v[i]):.6g}: beyond {MAX_MAGNITUDE:.0e} "
                "in magnitude, not a measurement (a unit or parsing error?)."
            )
    if float(y.max() - y.min()) <= 0:
        raise ValueError("output is constant; nothing to fit.")
    return u, y


def fit_preisach(
    model: PreisachModel,
    current: Tensor,
    field: Tensor,
    *,
    optimizer: str = "lbfgs",
    steps: int = 200,
    lr: float | None = None,
    smoothness: float = 0.0,
    initial_state: str | Tensor | None = None,
    callback: Callable[[int, float], None] | None = None,
    loss_rows: Tensor | None = None,
) -> FitResult:
    """Fit density, offset, slope and scale of ``model`` to one measured history.

    Sets the model's output normalisation from ``field`` (minimum and range),
    initialises offset, slope and scale by linear least squares with the
    current density, then minimises the mean squared normalised residual plus
    ``smoothness * density_roughness(model)`` in exact-relay mode (the output
    is linear in the hysteron weights there, so the problem is smooth).

    Args:
        model: Model to fit in place; its ``input_range`` must contain ``current``.
        current: Inputs in time order [input units, e.g. A], shape ``(T,)``.
        field: Measured outputs [output units, e.g. T m], shape ``(T,)``.
        optimizer: ``"lbfgs"`` (default; strong-Wolfe line search) or ``"adam"``.
        steps: Optimiser steps (L-BFGS iterations, at most ``2 * steps``
            objective evaluations; or Adam steps).
        lr: Learning rate; default 1 for L-BFGS and 0.01 for Adam.
        smoothness: Weight of the density roughness penalty [1]; 0 (default)
            leaves the density free (best on held-out training rows of the SLAC
            quadrupole data; see ``benchmarks/preisach_slac.py``).
        initial_state: State before ``current[0]``; ``None`` is the model's own.
        callback: Called as ``callback(step, loss)`` after every step.
        loss_rows: Boolean mask, shape ``(T,)``, of the rows whose residuals
            enter the objective (and the output normalisation and the
            least-squares start); the other rows still drive the hysterons'
            history. ``None``: every row. For validation on rows held out
            inside a history.

    Returns:
        A :class:`FitResult`.

    Raises:
        ValueError: on mismatched lengths, non-finite values, fewer than
            ``MIN_FIT_POINTS`` points, inputs outside the model's range, an
            unknown optimiser or a non-positive step count.
    """
    if optimizer not in ("lbfgs", "adam"):
        raise ValueError(f"optimizer must be 'lbfgs' or 'adam'; got {optimizer!r}.")
    if steps < 1:
        raise ValueError(f"steps must be >= 1; got {steps}.")
    if not (math.isfinite(smoothness) and smoothness >= 0):
        raise ValueError(f"smoothness must be finite and >= 0; got {smoothness}.")
    u, y = check_series(current, field, model.alpha.dtype, model.alpha.device)
    model.check_input_range(u, "training inputs")  # before touching the model
    if loss_rows is None:
        rows = torch.ones_like(u, dtype=torch.bool)
    else:
        rows = torch.as_tensor(loss_rows, device=u.device)
        if rows.shape != u.shape or rows.dtype != torch.bool:
            raise ValueError(
                f"loss_rows must be a boolean mask of shape {tuple(u.shape)}; got "
                f"{rows.dtype} {tuple(rows.shape)}."
            )
        if int(rows.sum()) < MIN_FIT_POINTS:
            raise ValueError(
                f"loss_rows selects {int(rows.sum())} rows; need at least "
                f"{MIN_FIT_POINTS}."
            )
        if float(y[rows].max() - y[rows].min()) <= 0:
            raise ValueError("output is constant over loss_rows; nothing to fit.")
    t0 = time.perf_counter()
    with torch.no_grad():
        loc, span = y[rows].min(), y[rows].max() - y[rows].min()
        model.output_loc.copy_(loc)
        model.output_scale.copy_(span)
        yn = (y - loc) / span
        un = model.normalize_input(u)
        m = model.magnetization(u, initial_state)
        if model.odd:  # offset = -loc / span - slope / 2
            basis = torch.stack([un - 0.5, m], dim=1)
            target = yn + loc / span
            coef = lstsq(basis[rows], target[rows].unsqueeze(1)).squeeze(1)
            coef = torch.cat([(-loc / span - 0.5 * coef[0]).reshape(1), coef])
        else:
            basis = torch.stack([torch.ones_like(un), un, m], dim=1)
            coef = lstsq(basis[rows], yn[rows].unsqueeze(1)).squeeze(1)
        model.offset.copy_(coef[0])
        model.slope.copy_(coef[1])
        model.scale.copy_(coef[2])

    # Precondition: the output changes by ~scale / M per unit of one hysteron's
    # raw density, by ~1 per unit of offset or slope. Optimise raw parameters
    # divided by a per-group factor so that all groups have similar curvature
    # (L-BFGS stalls otherwise; Adam is insensitive to it).
    names = [
        n
        for n, p in model.named_parameters()
        if p.requires_grad and not (model.odd and n == "offset")
    ]
    m_count = model.alpha.numel()
    per_hysteron = (m_count**0.5) / max(abs(float(model.scale.detach())), 1e-3)
    factor = {
        n: (
            per_hysteron
            if optimizer == "lbfgs" and n in ("raw_density", "raw_initial_state")
            else 1.0
        )
        for n in names
    }
    own = dict(model.named_parameters())
    proxies = {
        n: (own[n].detach() / factor[n]).clone().requires_grad_(True) for n in names
    }

    def write_back() -> None:
        with torch.no_grad():
            for n in names:
                own[n].copy_(proxies[n] * factor[n])
            if model.odd:
                model.offset.copy_(model.effective_offset())

    kind = model.initial_state_kind if initial_state is None else initial_state
    learned = (
        "raw_initial_state" in names and isinstance(kind, str) and kind == "learned"
    )
    from_states = None
    if not learned and u.numel() * m_count <= _MAX_STATE_TABLE:
        with torch.no_grad():
            table = model.states(u, initial_state)
        from_states = _FromStates(model, model.normalize_input(u), table)

    def objective() -> Tensor:
        subst = {n: proxies[n] * factor[n] for n in names}
        if from_states is not None:
            m = torch.func.functional_call(
                from_states, {f"model.{n}": v for n, v in subst.items()}, ()
            )
        else:
            m = torch.func.functional_call(
                model, subst, (u,), {"initial_state": initial_state}, strict=False
            )
        pred = (m - model.output_loc) / model.output_scale
        loss = ((pred - yn)[rows] ** 2).mean()
        if smoothness > 0:
            loss = loss + smoothness * torch.func.functional_call(
                _Roughness(model), {f"model.{n}": v for n, v in subst.items()}, ()
            )
        return loss

    losses: list[float] = []
    params = list(proxies.values())
    if optimizer == "lbfgs":
        opt = torch.optim.LBFGS(
            params,
            lr=1.0 if lr is None else lr,
            max_iter=steps,
            max_eval=2 * steps,
            history_size=50,
            tolerance_grad=0.0,
            tolerance_change=1e-14,
            line_search_fn="strong_wolfe",
        )

        def closure() -> Tensor:
            opt.zero_grad()
            loss = objective()
            loss.backward()
            losses.append(float(loss.detach()))
            if callback is not None:
                callback(len(losses) - 1, losses[-1])
            return loss

        opt.step(closure)
    else:
        opt = torch.optim.Adam(params, lr=0.01 if lr is None else lr)
        for step in range(steps):
            opt.zero_grad()
            loss = objective()
            loss.backward()
            opt.step()
            losses.append(float(loss.detach()))
            if callback is not None:
                callback(step, losses[-1])
    write_back()
    with torch.no_grad():
        resid = (model(u, initial_state) - y)[rows]
        rmse = float(resid.pow(2).mean().sqrt())
        final = float(objective())
    seconds = time.perf_counter() - t0
    logger.info(
        "Preisach fit: %d steps, rmse %.4g in %.2f s", len(losses), rmse, seconds
    )
    return FitResult(
        rmse=rmse,
        rmse_percent=100.0 * rmse / float(span),
        loss=final,
        losses=losses,
        steps=len(losses),
        seconds=seconds,
        optimizer=optimizer,
    )
