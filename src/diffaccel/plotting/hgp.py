"""Figures of hysteresis-aware GP models and Bayesian-optimisation runs."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch
from matplotlib.figure import Figure
from torch import Tensor

from diffaccel.hysteresis import HysteresisGP
from diffaccel.plotting.text import literal, no_usetex

__all__ = ["plot_best_so_far", "plot_gp_vs_hgp", "plot_hgp_history"]


def _np(x: Tensor | np.ndarray) -> np.ndarray:
    if isinstance(x, Tensor):
        return x.detach().cpu().double().numpy()
    return np.asarray(x, dtype=float)


@no_usetex
def plot_gp_vs_hgp(
    current: Tensor,
    y: Tensor,
    gp_mean: Tensor,
    gp_sigma: Tensor,
    hgp_mean: Tensor,
    hgp_sigma: Tensor,
    cycle: Tensor,
    xlabel: str = "current [A]",
    ylabel: str = "response",
) -> Figure:
    """Plain GP versus H-GP on a cycled magnet, as in Roussel & Edelen (2022).

    Left: the plain GP's mean +- 2 sigma against current with the data. Right:
    the H-GP's predictions at the same points, coloured by cycle, with +- 2 sigma.

    Args:
        current: Magnet current of each point [A], shape ``(n,)`` in time order.
        y: Measured responses, shape ``(n,)``.
        gp_mean: Plain-GP posterior mean at the points, shape ``(n,)``.
        gp_sigma: Plain-GP posterior standard deviation, shape ``(n,)``.
        hgp_mean: H-GP posterior mean, shape ``(n,)``.
        hgp_sigma: H-GP posterior standard deviation, shape ``(n,)``.
        cycle: Cycle index of each point (integers), shape ``(n,)``.
        xlabel: Label of the current axis.
        ylabel: Label of the response axis.

    Returns:
        The figure (two panels).

    Shapes:
        Every input is ``(n,)``.
    """
    u, yy = _np(current), _np(y)
    gm, gs, hm, hs = _np(gp_mean), _np(gp_sigma), _np(hgp_mean), _np(hgp_sigma)
    cyc = _np(cycle).astype(int)
    fig = Figure(figsize=(10, 4), layout="constrained")
    ax_gp, ax_h = fig.subplots(1, 2, sharey=True)
    grid = np.argsort(u, kind="stable")
    ax_gp.fill_between(
        u[grid], (gm - 2 * gs)[grid], (gm + 2 * gs)[grid], alpha=0.3, label="±2σ"
    )
    ax_gp.plot(u[grid], gm[grid], "C0-", label="GP mean")
    ax_gp.plot(u, yy, "k.", ms=3, label="data")
    ax_gp.set_title("plain GP on current")
    ax_gp.set_xlabel(literal(xlabel))
    ax_gp.set_ylabel(literal(ylabel))
    ax_gp.legend(loc="best", fontsize=8)
    for k in np.unique(cyc):
        sel = cyc == k
        ax_h.errorbar(
            u[sel],
            hm[sel],
            yerr=2 * hs[sel],
            fmt=".-",
            ms=3,
            lw=0.8,
            capsize=0,
            color=f"C{int(k) % 10}",
            label=f"cycle {int(k) + 1}",
        )
    ax_h.plot(u, yy, "k.", ms=2, alpha=0.5)
    ax_h.set_title("H-GP (±2σ), coloured by cycle")
    ax_h.set_xlabel(literal(xlabel))
    ax_h.legend(loc="best", fontsize=8)
    return fig


@no_usetex
def plot_best_so_far(
    curves: Mapping[str, Tensor | np.ndarray],
    higher_is_better: bool,
    ylabel: str = "best so far",
    log_y: bool = False,
) -> Figure:
    """Median best-so-far curves of optimisation runs with quartile bands.

    Args:
        curves: Method name -> best-so-far values, shape ``(S, T)`` for ``S``
            seeds and ``T`` steps (already cumulative best).
        higher_is_better: Direction of the objective (only for the title).
        ylabel: Label of the objective axis.
        log_y: Logarithmic objective axis.

    Returns:
        The figure.

    Shapes:
        Each curve array is ``(S, T)``.
    """
    fig = Figure(figsize=(6, 4), layout="constrained")
    ax = fig.subplots()
    for i, (name, c) in enumerate(curves.items()):
        arr = _np(c)
        steps = np.arange(1, arr.shape[1] + 1)
        q25, med, q75 = np.quantile(arr, [0.25, 0.5, 0.75], axis=0)
        ax.fill_between(steps, q25, q75, color=f"C{i}", alpha=0.25)
        ax.plot(steps, med, color=f"C{i}", label=f"{literal(name)} (median, IQR)")
    ax.set_xlabel("step")
    ax.set_ylabel(literal(ylabel))
    if log_y:
        ax.set_yscale("log")
    ax.set_title("higher is better" if higher_is_better else "lower is better")
    ax.legend(loc="best")
    return fig


@no_usetex
def plot_hgp_history(
    model: HysteresisGP, column: int = 0, xlabel: str = "x", ylabel: str = "y"
) -> Figure:
    """A fitted H-GP on its training history.

    Left: data and posterior mean +- 2 sigma against step. Right: data against
    input column ``column``, coloured by step, with the posterior mean.

    Args:
        model: A (fitted) :class:`~diffaccel.hysteresis.HysteresisGP`.
        column: Input column for the right panel.
        xlabel: Label of that input.
        ylabel: Label of the response.

    Returns:
        The figure.
    """
    with torch.no_grad():
        post = model.posterior_on_history()
        mean = _np(post.mean.squeeze(-1))
        sigma = _np(post.variance.squeeze(-1).clamp_min(0).sqrt())
    x = _np(model.train_X[:, column])
    y = _np(model.train_Y.squeeze(-1))
    steps = np.arange(len(y))
    fig = Figure(figsize=(10, 4), layout="constrained")
    ax_t, ax_x = fig.subplots(1, 2)
    ax_t.fill_between(steps, mean - 2 * sigma, mean + 2 * sigma, alpha=0.3)
    ax_t.plot(steps, mean, "C0-", label="H-GP mean ±2σ")
    ax_t.plot(steps, y, "k.", ms=3, label="data")
    ax_t.set_xlabel("step")
    ax_t.set_ylabel(literal(ylabel))
    ax_t.legend(loc="best", fontsize=8)
    sc = ax_x.scatter(x, y, c=steps, s=10, cmap="viridis", label="data")
    ax_x.plot(x, mean, "-", color="0.4", lw=0.6, label="H-GP mean (in order)")
    ax_x.set_xlabel(literal(xlabel))
    ax_x.set_ylabel(literal(ylabel))
    ax_x.legend(loc="best", fontsize=8)
    fig.colorbar(sc, ax=ax_x, label="step")
    return fig
