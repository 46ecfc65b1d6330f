"""Figures of Preisach hysteresis models: density plane, loops and residuals."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure
from matplotlib.tri import Triangulation
from torch import Tensor

from diffaccel.hysteresis import PreisachModel
from diffaccel.plotting.files import save_png
from diffaccel.plotting.text import literal, no_usetex

__all__ = [
    "FIT_FIGURES",
    "plot_preisach_density",
    "plot_preisach_fit",
    "write_fit_figures",
]

#: The figures of a fit folder (:func:`write_fit_figures`).
FIT_FIGURES = ("fit.png", "density.png")


def _np(x: Tensor) -> np.ndarray:
    return x.detach().cpu().double().numpy()


@no_usetex
def plot_preisach_density(
    model: PreisachModel, input_label: str = "current [A]"
) -> Figure:
    """Hysteron density on the Preisach plane, in physical input units.

    Args:
        model: A Preisach model.
        input_label: Axis label of the input quantity, with its unit.

    Returns:
        A figure with one axes: ``beta`` (down threshold) horizontally,
        ``alpha`` (up threshold) vertically, density colour-coded.
    """
    lo, hi = model.input_range
    alpha = lo + (hi - lo) * _np(model.alpha)
    beta = lo + (hi - lo) * _np(model.beta)
    density = _np(model.density)
    fig = Figure(figsize=(5.2, 4.4), layout="constrained")
    ax = fig.add_subplot()
    if alpha.size >= 3:
        try:
            tri = Triangulation(beta, alpha)
            art = ax.tripcolor(tri, density, shading="gouraud", cmap="viridis")
        except (ValueError, RuntimeError):  # collinear or too few points
            art = ax.scatter(beta, alpha, c=density, s=12, cmap="viridis")
    else:
        art = ax.scatter(beta, alpha, c=density, s=30, cmap="viridis")
    ax.plot([lo, hi], [lo, hi], color="k", lw=0.8)
    ax.set_xlim(lo, hi)
    ax.set_ylim(lo, hi)
    ax.set_aspect("equal")
    ax.set_xlabel(f"beta: down threshold, {literal(input_label)}")
    ax.set_ylabel(f"alpha: up threshold, {literal(input_label)}")
    kind = "symmetric " if model.symmetric else ""
    ax.set_title(f"Preisach density, {kind}({alpha.size} hysterons)")
    if model.symmetric:  # the mirror line alpha + beta = lo + hi
        ax.plot([lo, hi], [hi, lo], color="w", lw=0.8, ls="--")
    fig.colorbar(art, ax=ax, label="density [1]")
    return fig


@no_usetex
def plot_preisach_fit(
    model: PreisachModel,
    current: Tensor,
    field: Tensor,
    n_train: int | None = None,
    std: Tensor | None = None,
    initial_state: str | Tensor | None = None,
    input_label: str = "current [A]",
    output_label: str = "field [T m]",
) -> Figure:
    """Measured and modelled loops with residuals, training and prediction rows.

    Args:
        model: A fitted Preisach model.
        current: Inputs in time order [input units], shape ``(T,)``.
        field: Measured outputs [output units], shape ``(T,)``.
        n_train: Rows ``[:n_train]`` were fitted, the rest are predictions;
            ``None`` means all were fitted.
        std: Predictive standard deviation [output units], shape ``(T,)``;
            drawn as a 2-std band about the prediction when given.
        initial_state: State before ``current[0]``; ``None`` is the model's own.
        input_label: Input axis label with unit.
        output_label: Output axis label with unit.

    Returns:
        A figure: loops (output minus its best straight line, vs input) on the
        left, residuals against row index on the right, training rows in blue
        and predicted rows in orange.

    Raises:
        ValueError: if ``current``, ``field`` (and ``std``) have different
            shapes.
    """
    if current.shape != field.shape or current.ndim != 1:
        raise ValueError(
            "current and field must both have shape (T,); got "
            f"{tuple(current.shape)} and {tuple(field.shape)}."
        )
    if std is not None and std.shape != current.shape:
        raise ValueError(
            f"std must have shape {tuple(current.shape)}; got {tuple(std.shape)}."
        )
    with torch.no_grad():
        pred = _np(model(current, initial_state))
    u, y = _np(current), _np(field)
    n = len(u) if n_train is None else int(n_train)
    idx = np.arange(len(u))
    resid = y - pred
    span = float(np.ptp(y[:n])) or 1.0  # range of the fitted rows
    # subtract the best straight line so that the loops (often < 1 % of the
    # output) are visible
    coef = np.polyfit(u, y, 1)
    line = np.polyval(coef, u)
    yl, pl = y - line, pred - line
    fig = Figure(figsize=(11, 4.2), layout="constrained")
    ax_loop, ax_res = fig.subplots(1, 2)
    ax_loop.plot(u[:n], yl[:n], "o", ms=3.5, color="C0", label="measured (fit)")
    ax_loop.plot(u[:n], pl[:n], "-", lw=1, color="C0", alpha=0.7, label="model (fit)")
    if std is not None:
        band = 2.0 * _np(std)
        ax_loop.errorbar(
            u, pl, yerr=band, fmt="none", ecolor="grey", elinewidth=0.8, capsize=2,
            alpha=0.6, label="model +- 2 std",
        )  # fmt: skip
    if n < len(u):
        ax_loop.plot(u[n:], yl[n:], "s", ms=3.5, color="C1", label="measured (test)")
        ax_loop.plot(
            u[n - 1 :], pl[n - 1 :], "-", lw=1, color="C1", alpha=0.7,
            label="model (prediction)",
        )  # fmt: skip
    ax_loop.set_xlabel(literal(input_label))
    ax_loop.set_ylabel(f"{literal(output_label)} - ({coef[0]:.4g} x + {coef[1]:.3g})")
    ax_loop.legend(fontsize=8)
    ax_loop.set_title("Hysteresis loops (best straight line subtracted)")
    ax_res.axhline(0.0, color="k", lw=0.6)
    ax_res.plot(idx[:n], 100 * resid[:n] / span, "o-", ms=3, lw=0.8, color="C0")
    if n < len(u):
        ax_res.plot(idx[n:], 100 * resid[n:] / span, "s-", ms=3, lw=0.8, color="C1")
    if std is not None:
        band = 200.0 * _np(std) / span
        ax_res.fill_between(idx, -band, band, color="grey", alpha=0.25, lw=0)
        ax_res.axvline(n - 0.5, color="grey", ls="--", lw=0.8)

    def rms(r: np.ndarray) -> float:
        return float(np.sqrt(np.mean(r**2))) if r.size else float("nan")

    ax_res.set_title(
        f"residual rms: fit {100 * rms(resid[:n]) / span:.3f} %, "
        f"prediction {100 * rms(resid[n:]) / span:.3f} % of range"
    )
    ax_res.set_xlabel("row (time order)")
    ax_res.set_ylabel("measured - model [% of output range]")
    return fig


def write_fit_figures(
    folder: Path,
    model: PreisachModel,
    current: Tensor,
    field: Tensor,
    n_train: int,
    std: Tensor,
    input_label: str,
    output_label: str,
) -> list[str]:
    """Write ``fit.png`` (:func:`plot_preisach_fit`) and ``density.png``
    (:func:`plot_preisach_density`) of a fit into ``folder``.

    Args:
        folder: An existing folder.
        model: The fitted model.
        current: Inputs of every row in time order, shape ``(T,)``.
        field: Measured outputs, shape ``(T,)``.
        n_train: Rows ``[:n_train]`` were fitted.
        std: Predictive std of every row, shape ``(T,)``.
        input_label: Input axis label (a column name, with unit where it has one).
        output_label: Output axis label.

    Returns:
        The file names, :data:`FIT_FIGURES`.
    """
    fig = plot_preisach_fit(
        model,
        current,
        field,
        n_train=n_train,
        std=std,
        input_label=input_label,
        output_label=output_label,
    )
    save_png(fig, folder / FIT_FIGURES[0])
    fig = plot_preisach_density(model, input_label=input_label)
    save_png(fig, folder / FIT_FIGURES[1])
    return list(FIT_FIGURES)
