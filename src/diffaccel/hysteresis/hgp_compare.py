"""A joint hysteresis GP of one magnet history, against a plain GP of the same rows.

:func:`read_gp_data` reads the history's columns from CSV, :func:`gp_setup`
builds both models on the first rows of a history (the H-GP started from a
Preisach fit of the response,
:func:`~diffaccel.hysteresis.hgp.joint_gp_from_preisach`), :func:`fit_gps`
fits them and :func:`gp_summary` scores them on the held-out last rows (the
H-GP continuing the history), with the alarms of
:func:`~diffaccel.hysteresis.alarms.hgp_alarms`. Imports GPyTorch and BoTorch.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from diffaccel.data import OptionError
from diffaccel.data.magnet_csv import read_magnet_csv
from diffaccel.data.magnet_stream import (
    DEFAULT_TIME_COLUMN,
    check_magnitude,
    check_time_column,
)
from diffaccel.hysteresis.alarms import hgp_alarms
from diffaccel.hysteresis.fit import MIN_FIT_POINTS
from diffaccel.hysteresis.hgp import (
    HGPFitResult,
    HysteresisGP,
    JointStart,
    fit_hysteresis_gp,
    joint_gp_from_preisach,
)
from diffaccel.hysteresis.mesh import PreisachMesh
from diffaccel.hysteresis.preisach import PreisachModel

__all__ = [
    "GPSetup",
    "fit_gps",
    "gp_line",
    "gp_setup",
    "gp_summary",
    "read_gp_data",
]

#: Margin added to the data range of the hysteretic input (share of the range).
RANGE_MARGIN = 0.01
#: L-BFGS iterations of the Preisach fit that starts the H-GP's density.
PREISACH_STEPS = 300
#: Share of the last rows held out by default.
HOLDOUT = 0.25


def read_gp_data(
    data: Path,
    x_column: str,
    y_column: str,
    plain_columns: Sequence[str] = (),
    time_column: str | None = None,
    holdout: float = HOLDOUT,
) -> tuple[Tensor, Tensor, int]:
    """The settings and responses of a magnet history in CSV, and the rows to fit.

    Args:
        data: The CSV file, rows in the order the settings were applied.
        x_column: Column of the hysteretic input (magnet current).
        y_column: Column of the beam response.
        plain_columns: Extra non-hysteretic input columns.
        time_column: Column of measurement times (None: the default where the
            file has it; see :func:`~diffaccel.data.read_magnet_csv`).
        holdout: Share of the last rows held out.

    Returns:
        ``X`` ``(T, 1 + len(plain_columns))`` (the hysteretic input first),
        ``Y`` ``(T, 1)`` and the number of rows to fit (the first ones).

    Raises:
        OptionError: a plain column given twice or also as ``x_column`` or
            ``y_column`` (``--plain``); a missing ``time_column``
            (``--time-column``).
        ValueError: a file that cannot be read as a magnet history, values
            beyond :data:`~diffaccel.data.magnet_stream.MAX_MAGNITUDE`, a
            constant input, or fewer than ``MIN_FIT_POINTS`` rows to fit.
    """
    repeated = sorted({c for c in plain_columns if plain_columns.count(c) > 1})
    if repeated:
        raise OptionError(f"column(s) {repeated} given more than once", "--plain")
    for col, option in ((x_column, "--x"), (y_column, "--y")):
        if col in plain_columns:
            raise OptionError(
                f"column {col!r} is the {option} column; --plain names extra, "
                "non-hysteretic input columns.",
                "--plain",
            )
    time_col = time_column or DEFAULT_TIME_COLUMN
    hist = read_magnet_csv(data, x_column, y_column, time_column=time_col)
    check_time_column(data, hist.header, time_column)
    check_magnitude(data, x_column, hist.input)
    check_magnitude(data, y_column, hist.output)
    if float(hist.input.max() - hist.input.min()) <= 0:
        raise ValueError(
            f"{data}: column {x_column!r} is constant ({float(hist.input[0]):g}); "
            "a hysteresis GP needs the magnet input to vary."
        )
    cols = [hist.input]
    for col in plain_columns:
        cols.append(read_magnet_csv(data, col, y_column, time_column=time_col).input)
        check_magnitude(data, col, cols[-1])
    X = torch.stack(cols, dim=-1)
    n_te = round(holdout * X.shape[0])
    n_tr = X.shape[0] - n_te
    if n_tr < MIN_FIT_POINTS:
        raise ValueError(
            f"{data}: --holdout {holdout:g} leaves {n_tr} of {X.shape[0]} rows "
            f"to fit; need at least {MIN_FIT_POINTS}."
        )
    return X, hist.output.unsqueeze(-1), n_tr


@dataclass(frozen=True)
class GPSetup:
    """The unfitted models of :func:`gp_setup`.

    Attributes:
        model: The H-GP of column 0 (hysteretic), trained on the first rows.
        plain: A plain GP (no hysteresis) of the same rows.
        start: The Preisach fit that starts the H-GP's density.
        prior: The Preisach model of column 0 (mesh, input range, state).
        input_range: Its input range ``(lo, hi)`` [units of column 0].
        n_train: Rows the models are trained on (the first ones).
    """

    model: HysteresisGP
    plain: HysteresisGP
    start: JointStart
    prior: PreisachModel
    input_range: tuple[float, float]
    n_train: int


def gp_setup(
    X: Tensor,
    Y: Tensor,
    n_train: int,
    *,
    mesh_size: int,
    initial_state: str,
    input_range: tuple[float, float] | None = None,
) -> GPSetup:
    """Build the H-GP and the plain GP of the first ``n_train`` rows.

    The settings of every row are known in advance (the responses of the
    held-out rows are not used): the input range and the bounds of the plain
    columns cover them all.

    Args:
        X: Settings in the order applied, shape ``(T, d)``; column 0 is the
            hysteretic input, the others plain inputs.
        Y: Responses, shape ``(T, 1)``.
        n_train: Rows to train on (the first ones).
        mesh_size: Cells per axis of the triangular Preisach mesh.
        initial_state: Magnet state before the first row.
        input_range: Preisach input range; default: the range of column 0
            +- :data:`RANGE_MARGIN` of it.

    Raises:
        ValueError: data the models refuse (too few rows, non-finite values).
    """
    lo, hi = (float(X[:, 0].min()), float(X[:, 0].max()))
    if input_range is None:
        margin = RANGE_MARGIN * max(hi - lo, 1e-12)
        input_range = (lo - margin, hi + margin)
    prior = PreisachModel(
        PreisachMesh.triangular(n=mesh_size),
        input_range=input_range,
        initial_state=initial_state,
    )
    bounds = torch.stack([X.min(dim=0).values, X.max(dim=0).values])
    X_tr, Y_tr = X[:n_train], Y[:n_train]
    model, start = joint_gp_from_preisach(
        X_tr, Y_tr, prior, column=0, steps=PREISACH_STEPS, bounds=bounds
    )
    plain = HysteresisGP(X_tr, Y_tr, hysteresis={}, bounds=bounds)
    return GPSetup(model, plain, start, prior, tuple(input_range), n_train)


def fit_gps(
    setup: GPSetup,
    *,
    restarts: int,
    max_iter: int,
    seed: int,
    callback: Callable[[int, float], None] | None = None,
) -> tuple[HGPFitResult, HGPFitResult]:
    """Fit the H-GP (``restarts`` optimisations, ranked) and the plain GP (one).

    ``callback(restart, mll)`` follows the H-GP's restarts (at least two:
    from the Preisach fit's density and from a uniform one). GPyTorch's
    warnings about matrices not positive definite (handled by its jitter) are
    silenced.

    Returns:
        ``(H-GP result, plain GP result)``.
    """
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*not p.d.*")
        res = fit_hysteresis_gp(
            setup.model,
            restarts=restarts,
            max_iter=max_iter,
            seed=seed,
            callback=callback,
            density_starts=setup.start.density_starts,
        )
        plain_fit = fit_hysteresis_gp(
            setup.plain, restarts=1, max_iter=max_iter, seed=seed
        )
    return res, plain_fit


def _rmse(pred: Tensor, target: Tensor) -> float:
    return float((pred - target).pow(2).mean().sqrt())


def gp_summary(
    setup: GPSetup,
    X: Tensor,
    Y: Tensor,
    res: HGPFitResult,
    plain_fit: HGPFitResult,
    *,
    data: str,
    x: str,
    y: str,
    plain_inputs: Sequence[str],
    initial_state: str,
) -> dict[str, Any]:
    """The numbers of ``gp_summary.json``: noise, rms errors, likelihoods, alarms.

    Held-out rms errors [units of the response] are of the rows after
    ``setup.n_train`` (None where there are none); ``rmse_vs_data`` and
    ``mean_predictive_sigma`` are of the H-GP's posterior on its training
    history. ``data``, ``x``, ``y``, ``plain_inputs`` and ``initial_state``
    are recorded as given.
    """
    model, plain, n_tr = setup.model, setup.plain, setup.n_train
    n_te = X.shape[0] - n_tr
    with torch.no_grad():
        post = model.posterior_on_history()
        mean = post.mean.squeeze(-1)
        sigma = post.variance.squeeze(-1).clamp_min(0).sqrt()
        heldout = plain_heldout = None
        if n_te:
            X_te, y_te = X[n_tr:], Y[n_tr:, 0]
            heldout = _rmse(model.posterior_sequence(X_te).mean.reshape(-1), y_te)
            pred = plain.posterior(X_te.unsqueeze(0)).mean.reshape(-1)
            plain_heldout = _rmse(pred, y_te)
    alarms = hgp_alarms(res.noise_sigma, plain_fit.noise_sigma, heldout, plain_heldout)
    return {
        "data": data,
        "x": x,
        "y": y,
        "plain_inputs": list(plain_inputs),
        "n_points": int(X.shape[0]),
        "train_rows": n_tr,
        "test_rows": n_te,
        "n_hysterons": int(setup.prior.alpha.numel()),
        "input_range": list(setup.input_range),
        "initial_state": initial_state,
        "noise_sigma": res.noise_sigma,
        "mean_predictive_sigma": float(sigma.mean()),
        "rmse_vs_data": _rmse(mean, Y[:n_tr].squeeze(-1)),
        "heldout_rmse": heldout,
        "mll_per_point": res.mll,
        "restart_mlls": list(res.restart_mlls),
        "fit_s": res.fit_s,
        "plain_gp_noise_sigma": plain_fit.noise_sigma,
        "plain_gp_mll_per_point": plain_fit.mll,
        "plain_gp_heldout_rmse": plain_heldout,
        "preisach_start_rmse": setup.start.preisach_rmse,
        "preisach_start_s": setup.start.preisach_seconds,
        "warnings": alarms,
    }


def gp_line(summary: dict[str, Any]) -> str:
    """One line on a :func:`gp_summary`: noise, held-out rms errors, fit time."""
    heldout = summary["heldout_rmse"]
    held = (
        ""
        if heldout is None
        else f", held-out rmse {heldout:.4g} (plain GP "
        f"{summary['plain_gp_heldout_rmse']:.4g}) on the last "
        f"{summary['test_rows']} rows"
    )
    return (
        f"H-GP noise sigma {summary['noise_sigma']:.4g} "
        f"(plain GP {summary['plain_gp_noise_sigma']:.4g}){held}, "
        f"fit {summary['fit_s']:.1f} s"
    )
