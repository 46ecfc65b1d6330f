"""How well a Preisach fit predicts its history: rms errors, band coverage, alarms.

:func:`score_fit` predicts every row of a magnet history from a
:class:`~diffaccel.hysteresis.MagnetFit` of its first rows and returns the
numbers of a fit folder's ``summary.json``: rms errors on the training and the
held-out rows, the same for a straight line fitted to the training rows, the
share of held-out rows inside the 2-std band, and the alarms of
:mod:`diffaccel.hysteresis.alarms`. :func:`fit_line` is the one-line
account of such a summary, :func:`fit_messages` the warnings and notes of a
fit. :func:`read_fit_history` reads and checks the CSV history of
``hysteresis fit``; :func:`fit_history` fits its first rows and scores it.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from diffaccel.data import OptionError
from diffaccel.data.magnet_csv import MagnetHistory, read_magnet_csv
from diffaccel.data.magnet_stream import (
    DEFAULT_TIME_COLUMN,
    check_magnitude,
    check_time_column,
)
from diffaccel.dynamics.linalg import lstsq
from diffaccel.hysteresis.alarms import input_outlier_alarms, preisach_alarms
from diffaccel.hysteresis.band import BandFallbackWarning
from diffaccel.hysteresis.predictive import (
    MagnetFit,
    fit_magnet,
    min_training_rows,
    rms,
)
from diffaccel.hysteresis.stream import InputRangeWarning

__all__ = [
    "FitScore",
    "fit_history",
    "fit_line",
    "fit_messages",
    "read_fit_history",
    "score_fit",
]


@dataclass(frozen=True)
class FitScore:
    """The outcome of :func:`score_fit`.

    Attributes:
        prediction: Predicted output of every row, shape ``(T,)`` [output units].
        std: Its predictive std (one standard deviation with noise), ``(T,)``.
        summary: The numbers of ``summary.json`` (JSON-ready).
        notes: Input-range notes of the prediction (rows beyond the model's
            input range), also under ``summary["notes"]``.
        alarms: Warnings about the fit, also under ``summary["warnings"]``.
    """

    prediction: Tensor
    std: Tensor
    summary: dict[str, Any]
    notes: list[str]
    alarms: list[str]


def score_fit(
    fit: MagnetFit,
    input: Tensor,
    output: Tensor,
    train_rows: int,
    *,
    data: str,
    input_column: str,
    output_column: str,
    mesh_size: int,
    smoothness: float,
    initial_state: str,
) -> FitScore:
    """Predict every row of a history from a fit of its first ``train_rows`` rows.

    Args:
        fit: The fit of ``input[:train_rows]``, ``output[:train_rows]``
            (:func:`~diffaccel.hysteresis.fit_magnet`).
        input: Inputs of every row in time order, shape ``(T,)`` [input units].
        output: Measured outputs, shape ``(T,)`` [output units].
        train_rows: Rows the fit saw (the first ones); the rest are held out.
        data: Name of the history's file (recorded in the summary).
        input_column: Name of the input column (summary, alarms).
        output_column: Name of the output column (summary).
        mesh_size: Cells per axis of the fit's mesh (summary, alarms).
        smoothness: Weight of the fit's roughness penalty (summary).
        initial_state: The fit's initial-state option (summary).

    Returns:
        A :class:`FitScore`. Percentages in the summary are of the training
        output range; held-out numbers are None without held-out rows.

    Raises:
        ValueError: inputs the model cannot predict (e.g. non-finite).
    """
    model = fit.model
    u, y = input, output
    u_tr, y_tr = u[:train_rows], y[:train_rows]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", InputRangeWarning)
        with torch.no_grad():
            pred = model(u)
            std = fit.band.std(model, u)
    notes = [str(w.message) for w in caught if w.category is InputRangeWarning]
    span = float(y_tr.max() - y_tr.min())
    n_te = len(u) - train_rows
    resid = pred - y
    train_rmse = rms(resid[:train_rows])
    test_rmse = rms(resid[train_rows:]) if n_te else None
    basis = torch.stack([torch.ones_like(u), u], dim=1)
    coef = lstsq(basis[:train_rows], y_tr[:, None])
    line_rmse = rms((basis @ coef).squeeze(1)[train_rows:] - y[train_rows:])
    line_train = rms((basis @ coef).squeeze(1)[:train_rows] - y_tr)
    lo, hi = model.input_range
    rows = (test_rmse, line_rmse, "held-out") if n_te else None
    alarms = preisach_alarms(
        *(rows or (train_rmse, line_train, "training")),
        train_rmse=train_rmse, line_train_rmse=line_train,
        input_range=(lo, hi), train_span=float(u_tr.max() - u_tr.min()),
        cell_width=(hi - lo) / mesh_size, output_range=span,
    )  # fmt: skip
    alarms = input_outlier_alarms(u.tolist(), input_column) + alarms
    inside = (resid[train_rows:].abs() <= 2.0 * std[train_rows:]).double()

    def pct(v: float | None) -> float | None:
        return None if v is None else 100.0 * v / span

    summary = {
        "data": data,
        "input_column": input_column,
        "output_column": output_column,
        "rows": len(u),
        "train_rows": train_rows,
        "test_rows": n_te,
        "output_range": span,
        "output_range_rows": "training",
        "train_rmse": train_rmse,
        "train_rmse_percent": pct(train_rmse),
        "test_rmse": test_rmse,
        "test_rmse_percent": pct(test_rmse),
        "straight_line_test_rmse": line_rmse if n_te else None,
        "test_inside_2std": float(inside.mean()) if n_te else None,
        "test_mean_std": float(std[train_rows:].mean()) if n_te else None,
        "fit_seconds": fit.seconds,
        "steps": fit.result.steps,
        "mesh_size": mesh_size,
        "n_hysterons": int(model.alpha.numel()),
        "symmetric": fit.symmetric,
        "odd": model.odd,
        "mesh_adapt": fit.mesh_adapt,
        "mesh_validation": fit.mesh_validation,
        "band_fallback": fit.band_fallback,
        "band_calibration": fit.calibration,
        "band_directions": int(fit.band.directions.shape[0]),
        "validation": fit.validation,
        "smoothness": smoothness,
        "initial_state": initial_state,
        "input_range": list(model.input_range),
        "notes": notes,
        "warnings": alarms,
    }
    return FitScore(pred, std, summary, notes, alarms)


def fit_line(summary: Mapping[str, Any]) -> str:
    """One line on a fit's summary (:func:`score_fit`): rows, time, rms errors.

    The training and held-out rms errors [output units], each also as a
    percentage of the training output range, the straight line's held-out
    error and the share of held-out rows inside 2 std (``n/a`` without
    held-out rows).
    """
    span = summary["output_range"]
    test_rmse = summary["test_rmse"]
    test_txt = (
        "n/a"
        if test_rmse is None
        else f"{test_rmse:.4g} ({100.0 * test_rmse / span:.3f} %; straight line "
        f"{100.0 * summary['straight_line_test_rmse'] / span:.3f} %), "
        f"{100 * summary['test_inside_2std']:.0f} % of them inside 2 std"
    )
    train_rmse = summary["train_rmse"]
    return (
        f"fit {summary['train_rows']} rows in {summary['fit_seconds']:.2f} s "
        f"(symmetric {summary['symmetric']}): train rmse {train_rmse:.4g} "
        f"({100.0 * train_rmse / span:.3f} %), held-out rmse {test_txt}; "
        f"percentages of the training output range {span:.4g}"
    )


def read_fit_history(
    data: Path,
    input_column: str,
    output_column: str,
    time_column: str | None,
    train_rows: int,
) -> MagnetHistory:
    """The magnet history in the CSV file ``data``, checked for a fit of its first rows.

    ``time_column``: None reads the default time column where the file has it
    (:func:`~diffaccel.data.read_magnet_csv`); a named one must exist.

    Raises:
        OSError, ValueError: a file that cannot be read as a magnet history
            (:class:`~diffaccel.data.FormatError`), or a value beyond
            :data:`~diffaccel.data.magnet_stream.MAX_MAGNITUDE`.
        OptionError: a missing ``--time-column``; ``--train-rows`` beyond the
            rows of the file or below :func:`min_training_rows`.
    """
    hist = read_magnet_csv(
        data,
        input_column,
        output_column,
        time_column=time_column or DEFAULT_TIME_COLUMN,
    )
    check_time_column(data, hist.header, time_column)
    if train_rows > len(hist):
        raise OptionError(
            f"{train_rows} exceeds the {len(hist)} rows of {data}.", "--train-rows"
        )
    if train_rows < min_training_rows():
        raise OptionError(
            f"a fit needs at least {min_training_rows()} training rows; got "
            f"{train_rows}.",
            "--train-rows",
        )
    for name, values in ((input_column, hist.input), (output_column, hist.output)):
        check_magnitude(data, name, values)
    return hist


def fit_history(
    hist: MagnetHistory,
    train_rows: int,
    *,
    data: str,
    callback: Callable[[int, float], None] | None = None,
    mesh_size: int = 20,
    smoothness: float = 0.0,
    initial_state: str = "negative",
    **options: Any,
) -> tuple[MagnetFit, FitScore]:
    """Fit the first ``train_rows`` rows of ``hist`` and score every row.

    :func:`~diffaccel.hysteresis.fit_magnet` with ``mesh_size``,
    ``smoothness``, ``initial_state``, ``callback`` and its other ``options``,
    then :func:`score_fit` (``data``: the file's name in the summary). A
    fallback of the predictive band is reported once, as the fit's
    ``band_fallback``, not also as a warning; other warnings pass on.

    Raises:
        ValueError: training rows the model cannot fit or predict.
    """
    u, y = hist.input, hist.output
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", BandFallbackWarning)
        fit = fit_magnet(
            u[:train_rows],
            y[:train_rows],
            mesh_size=mesh_size,
            initial_state=initial_state,
            smoothness=smoothness,
            callback=callback,
            **options,
        )
    for w in caught:
        if w.category is not BandFallbackWarning:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    score = score_fit(
        fit,
        u,
        y,
        train_rows,
        data=data,
        input_column=hist.input_column,
        output_column=hist.output_column,
        mesh_size=mesh_size,
        smoothness=smoothness,
        initial_state=initial_state,
    )
    return fit, score


def fit_messages(fit: MagnetFit, score: FitScore) -> Sequence[str]:
    """The lines a fit reports besides its summary: band fallback, notes, alarms.

    Each prefixed ``warning:`` or ``note:``, in that order.
    """
    fallback = [] if fit.band_fallback is None else [fit.band_fallback]
    return [
        *(f"warning: {text}" for text in fallback),
        *(f"note: {note}" for note in score.notes),
        *(f"warning: {alarm}" for alarm in score.alarms),
    ]
