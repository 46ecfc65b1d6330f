"""Figures of phase-space reconstructions: corner plots, images, training curves."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path

import numpy as np
import torch
from matplotlib.axes import Axes
from matplotlib.collections import PolyCollection
from matplotlib.figure import Figure
from matplotlib.ticker import LogFormatter
from torch import Tensor

from diffaccel.data import MultiScanDataset
from diffaccel.plotting.files import save_figures
from diffaccel.plotting.text import literal, no_usetex
from diffaccel.reconstruction import Reconstruction, ScreenForwardModel

__all__ = [
    "FIGURE_DPI",
    "image_figures",
    "plot_corner",
    "plot_image_comparison",
    "plot_rms_evolution",
    "plot_training_curves",
    "result_figures",
    "write_image_figures",
    "write_result_figures",
]

_LABELS = ("x [mm]", "px [mrad]", "y [mm]", "py [mrad]", "z [mm]", "pz [1e-3]")


def _coords_to_plot(dims: int, truth: Tensor | None) -> list[int]:
    return list(range(dims))


def _fixed_margins(
    fig: Figure,
    left: float,
    right: float,
    bottom: float,
    top: float,
    wspace: float = 0.2,
    hspace: float = 0.2,
) -> None:
    """Subplot margins in inches (``wspace``/``hspace``: fractions of an axes).

    Fixed margins instead of ``tight_layout``, which measures every text
    extent with a renderer first: about a third of the figures' cost in a
    default ``reconstruct`` (of the whole command's time).
    """
    w, h = fig.get_size_inches()
    fig.subplots_adjust(
        left=left / w,
        right=1 - right / w,
        bottom=bottom / h,
        top=1 - top / h,
        wspace=wspace,
        hspace=hspace,
    )


@no_usetex
def plot_corner(
    reconstruction: Reconstruction,
    truth: Tensor | None = None,
    *,
    n: int = 50_000,
    bins: int = 60,
    seed: int = 0,
) -> Figure:
    """Corner plot of every 2D projection of the reconstructed phase space.

    Lower triangle: density of the ensemble sample (colour) with contours of the
    ground truth at 10, 50 and 90 % of its peak (white lines) when known;
    diagonal: 1D projections (filled: reconstruction, black line: truth). A 6D
    reconstruction shows all 15 projections, a 4D one the 6 transverse ones.

    Args:
        reconstruction: The ensemble to draw.
        truth: Ground-truth particles ``(M, 6)`` in Bmad coordinates, or None.
        n: Particles drawn from the ensemble.
        bins: Histogram bins per axis.
        seed: Sampling seed.

    Returns:
        The figure (Agg backend; save it with ``fig.savefig``).
    """
    coords = _coords_to_plot(reconstruction.config.dims, truth)
    reco = reconstruction.sample(n, seed=seed).to(torch.float64).numpy() * 1e3
    tru = (
        truth.detach().to("cpu", torch.float64).numpy() * 1e3
        if truth is not None
        else None
    )
    d = len(coords)
    fig = Figure(figsize=(2.1 * d + 0.6, 2.1 * d))
    # the lower triangle and the diagonal only (no hidden axes to build), one
    # artist per histogram (stairs, imshow): the figures count in the command's time
    grid = fig.add_gridspec(d, d)
    axes = np.empty((d, d), dtype=object)
    for i in range(d):
        for j in range(i + 1):
            axes[i, j] = fig.add_subplot(grid[i, j])
    ranges = []
    for c in coords:
        ref = tru[:, c] if tru is not None and tru[:, c].std() > 0 else reco[:, c]
        lo, hi = np.percentile(ref, [0.5, 99.5])
        pad = 0.25 * (hi - lo) if hi > lo else 1e-3
        ranges.append((lo - pad, hi + pad))
    for i, ci in enumerate(coords):
        for j, cj in enumerate(coords):
            if j > i:
                continue
            ax = axes[i, j]
            if i == j:
                edges = np.linspace(*ranges[i], bins + 1)
                h, _ = np.histogram(reco[:, ci], bins=edges, density=True)
                ax.stairs(
                    h, edges, fill=True, color="C0", alpha=0.6, label="reconstruction"
                )
                if tru is not None:
                    ht, _ = np.histogram(tru[:, ci], bins=edges, density=True)
                    ax.stairs(ht, edges, color="k", lw=1.2, label="ground truth")
                ax.set_yticks([])
            else:
                ex = np.linspace(*ranges[j], bins + 1)
                ey = np.linspace(*ranges[i], bins + 1)
                h, _, _ = np.histogram2d(reco[:, cj], reco[:, ci], bins=(ex, ey))
                ax.imshow(
                    h.T,
                    cmap="viridis",
                    origin="lower",
                    extent=(ex[0], ex[-1], ey[0], ey[-1]),
                    aspect="auto",
                    interpolation="nearest",
                )
                if tru is not None:
                    ht, _, _ = np.histogram2d(tru[:, cj], tru[:, ci], bins=(ex, ey))
                    if ht.max() > 0:
                        xc = 0.5 * (ex[1:] + ex[:-1])
                        yc = 0.5 * (ey[1:] + ey[:-1])
                        ax.contour(
                            xc,
                            yc,
                            ht.T / ht.max(),
                            levels=[0.1, 0.5, 0.9],
                            colors="w",
                            linewidths=0.8,
                        )
                ax.set_ylim(ranges[i])
            ax.set_xlim(ranges[j])
            # labels switched off with tick_params, not set_*ticklabels([]),
            # which builds every tick to label it with nothing (~0.1 s here)
            if i == d - 1:
                ax.set_xlabel(_LABELS[cj])
            else:
                ax.tick_params(labelbottom=False)
            if j == 0 and i > 0:
                ax.set_ylabel(_LABELS[ci])
            elif i != j:
                ax.tick_params(labelleft=False)
    title = f"Reconstructed phase space ({reconstruction.n_snapshots}-member ensemble"
    title += ", contours/lines: ground truth)" if tru is not None else ")"
    fig.suptitle(title)
    _fixed_margins(fig, 0.75, 0.15, 0.6, 0.6, wspace=0.1, hspace=0.1)
    if tru is not None:
        handles, labels = axes[0, 0].get_legend_handles_labels()
        # in the empty upper triangle, below the title
        w, h = fig.get_size_inches()
        fig.legend(
            handles,
            labels,
            loc="upper right",
            bbox_to_anchor=(1 - 0.15 / w, 1 - 0.6 / h),
            frameon=False,
        )
    return fig


@no_usetex
def plot_image_comparison(
    measured: Tensor,
    predicted: Tensor,
    settings: Tensor,
    *,
    setting_name: str = "",
    extent: Sequence[float] | None = None,
    held_out: Sequence[bool] | None = None,
    max_columns: int = 10,
    title: str = "",
    predicted_std: Tensor | None = None,
) -> Figure:
    """Measured vs predicted screen images, one column per setting.

    Each block of rows shows measured (top), predicted (middle) and
    predicted - measured (bottom, red/blue, same scale for all settings) for up
    to ``max_columns`` settings; held-out settings are titled in red. With
    ``predicted_std`` a fourth row shows the per-pixel spread of the prediction
    (``Reconstruction.predict_images(..., return_std=True)``) on the scale of
    the difference row, so a difference inside the spread looks no darker.

    Every panel is an image with its own colour scale and a frame, all in one
    set of axes without ticks: a set of axes per panel (their tick machinery)
    cost more than half of this figure's time in a default ``reconstruct``
    (the figures count in the command's time).

    Args:
        measured: Sum-normalised measured images ``(K, H, W)``.
        predicted: Sum-normalised predicted images ``(K, H, W)``.
        settings: Settings ``(K, P)``; their values label each panel.
        setting_name: Label of the columns (e.g. ``"Q1.k1"``).
        extent: ``(x_min, x_max, y_min, y_max)`` of the screen [mm]
            (kept for callers; the panels have no axes to label).
        held_out: Per setting, True if it was not used for training.
        max_columns: Settings per block.
        title: Prefix of the figure title (e.g. the scan name).
        predicted_std: Per-pixel spread of the prediction ``(K, H, W)``.

    Returns:
        The figure.
    """
    m = measured.detach().cpu().numpy()
    p = predicted.detach().cpu().numpy()
    if m.shape != p.shape:
        raise ValueError(f"measured {m.shape} and predicted {p.shape} differ.")
    sd = None if predicted_std is None else predicted_std.detach().cpu().numpy()
    if sd is not None and sd.shape != p.shape:
        raise ValueError(f"predicted_std {sd.shape} and predicted {p.shape} differ.")
    nrow = 3 if sd is None else 4
    k = m.shape[0]
    s = [
        ", ".join(f"{v:.3g}" for v in row)
        for row in torch.as_tensor(settings).reshape(k, -1).tolist()
    ]
    cols = min(k, max_columns)
    blocks = -(-k // cols)
    rows = nrow * blocks
    fig = Figure(figsize=(1.45 * cols + 0.8, 1.47 * rows))
    _fixed_margins(fig, 0.35, 0.05, 0.05, 0.5)
    ax = fig.add_subplot()
    ax.set_axis_off()
    # panel (row r, column c) spans [c (1 + gx), c (1 + gx) + 1] in x and
    # [-r (1 + gy) - 1, -r (1 + gy)] in y (data units = panels; the gaps of
    # the former grid of axes)
    gx, gy = 0.06, 0.22
    ax.set_xlim(0, cols + (cols - 1) * gx)
    ax.set_ylim(-(rows + (rows - 1) * gy), 0)
    dmax = float(np.abs(p - m).max()) or 1.0
    labels = ("measured", "predicted", "pred - meas", "pred spread")
    frames = []
    for idx in range(k):
        b, c = divmod(idx, cols)
        x0 = c * (1 + gx)
        vmax = max(float(m[idx].max()), float(p[idx].max()))
        panels = [
            (m[idx], "viridis", 0.0, vmax),
            (p[idx], "viridis", 0.0, vmax),
            (p[idx] - m[idx], "RdBu_r", -dmax, dmax),
        ]
        if sd is not None:
            panels.append((sd[idx], "Reds", 0.0, dmax))
        for i, (img, cmap, lo, hi) in enumerate(panels):
            top = -(nrow * b + i) * (1 + gy)
            ax.imshow(
                img,
                cmap=cmap,
                vmin=lo,
                vmax=hi,
                origin="lower",
                extent=(x0, x0 + 1, top - 1, top),
                aspect="auto",
            )
            frames.append([(x0, top - 1), (x0 + 1, top - 1), (x0 + 1, top), (x0, top)])
            if c == 0:
                ax.text(
                    -0.04, top - 0.5, labels[i], rotation=90, ha="right", va="center"
                )
        ho = held_out is not None and bool(held_out[idx])
        ax.text(
            x0 + 0.5,
            -nrow * b * (1 + gy) + 0.05,
            s[idx] + (" (test)" if ho else ""),
            fontsize=8,
            color="C3" if ho else "k",
            ha="center",
            va="bottom",
        )
    ax.add_collection(
        PolyCollection(
            frames, facecolors="none", edgecolors="k", linewidths=0.8, clip_on=False
        ),
        autolim=False,
    )
    fig.suptitle(
        (f"{literal(title)}: " if title else "")
        + f"Screen images per setting {literal(setting_name)} (colour scale per "
        f"column; difference scale +-{dmax:.2g})"
    )
    return fig


def _log_scale(ax: Axes, scale: str = "log") -> None:
    """Log (or symlog) y axis with plain tick labels (``0.01``, ``1e-05``).

    The default labels are mathtext (``$10^{-2}$``): the first one makes
    matplotlib build its mathtext parser, ~0.5 s of a default
    ``reconstruct`` whose figures have no other mathtext.
    """
    ax.set_yscale(scale)
    ax.yaxis.set_major_formatter(LogFormatter())
    if scale == "log":
        ax.yaxis.set_minor_formatter(LogFormatter(labelOnlyBase=False))


@no_usetex
def plot_training_curves(reconstruction: Reconstruction) -> Figure:
    """Loss, image mismatch, learning rate and penalty vs step, snapshots marked.

    Args:
        reconstruction: A trained ensemble (uses its ``history``).

    Returns:
        The figure (top: total loss and image mismatch; bottom: learning rate
        and image-penalty weight; dashed verticals: snapshot steps).
    """
    h = reconstruction.history
    steps = np.arange(1, len(h["loss"]) + 1)
    fig = Figure(figsize=(8, 6))
    (a1, a2) = fig.subplots(2, 1, sharex=True)
    a1.plot(steps, h["image_loss"], color="C0", lw=0.8, label="image mismatch D")
    _log_scale(a1)
    a1.set_ylabel("image mismatch (KL)")
    a1b = a1.twinx()
    a1b.plot(steps, h["loss"], color="C1", lw=0.8, label="total loss")
    a1b.set_ylabel("total loss (-H + lambda D)")
    _log_scale(a1b, "symlog")
    a2.plot(steps, h["lr"], color="C2", label="learning rate")
    _log_scale(a2)
    a2.set_ylabel("learning rate")
    a2b = a2.twinx()
    a2b.plot(steps, h["penalty"], color="C3", label="penalty lambda")
    _log_scale(a2b)
    a2b.set_ylabel("image penalty lambda")
    for ax in (a1, a2):
        for i, st in enumerate(h["snapshot_steps"]):
            ax.axvline(
                st,
                color="k",
                ls="--",
                lw=0.8,
                label="snapshot" if i == 0 and ax is a1 else None,
            )
    a2.set_xlabel("step")
    lines = a1.get_legend_handles_labels()
    lines_b = a1b.get_legend_handles_labels()
    a1.legend(lines[0] + lines_b[0], lines[1] + lines_b[1], loc="upper right")
    lines = a2.get_legend_handles_labels()
    lines_b = a2b.get_legend_handles_labels()
    a2.legend(lines[0] + lines_b[0], lines[1] + lines_b[1], loc="lower left")
    fig.suptitle("Training curves")
    _fixed_margins(fig, 1.0, 0.85, 0.55, 0.5, hspace=0.08)
    return fig


@no_usetex
def plot_rms_evolution(
    reconstruction: Reconstruction, truth: Tensor | None = None
) -> Figure:
    """RMS size of each generated coordinate during training.

    Args:
        reconstruction: A trained ensemble (uses ``history["rms"]``).
        truth: Ground-truth particles ``(M, 6)``; their rms is drawn dotted.

    Returns:
        The figure, one panel per reconstructed coordinate (mm / mrad / 1e-3).
    """
    h = reconstruction.history
    rms = np.asarray(h["rms"], dtype=float) * 1e3
    dims = reconstruction.config.dims
    steps = np.arange(1, rms.shape[0] + 1)
    t = (
        truth.detach().to(torch.float64).std(0).numpy() * 1e3
        if truth is not None
        else None
    )
    ncol = 2 if dims == 4 else 3
    fig = Figure(figsize=(4 * ncol, 5.5))
    axes = fig.subplots(2, ncol, sharex=True, squeeze=False)
    for i in range(dims):
        ax = axes.flat[i]
        ax.plot(steps, rms[:, i], color="C0", lw=0.8, label="reconstruction")
        if t is not None:
            ax.axhline(t[i], color="k", ls=":", lw=1.5, label="ground truth")
        for st in h["snapshot_steps"]:
            ax.axvline(st, color="grey", ls="--", lw=0.6)
        ax.set_ylabel(f"rms {_LABELS[i]}")
        ax.set_xlabel("step")
    axes.flat[0].legend(loc="best")
    for j in range(dims, axes.size):
        axes.flat[j].set_axis_off()
    fig.suptitle("RMS sizes during training (dashed: snapshots)")
    _fixed_margins(fig, 0.75, 0.15, 0.55, 0.45, wspace=0.3, hspace=0.3)
    return fig


#: Resolution of the figures of a result folder [dots per inch].
FIGURE_DPI = 110


def result_figures(
    result: Reconstruction,
    dataset: MultiScanDataset,
    *,
    corner: Callable[..., Figure] | None = None,
) -> Iterator[tuple[str, Figure]]:
    """The summary figures of a result folder, as ``(file name, figure)`` pairs.

    ``phase_space.png`` (``corner``, default :func:`plot_corner`, the
    dataset's ground truth overlaid where known), ``training.png``
    (:func:`plot_training_curves`) and ``rms_evolution.png``
    (:func:`plot_rms_evolution`), drawn in that order.
    """
    truth = dataset.ground_truth
    draw_corner = plot_corner if corner is None else corner
    figs = {
        "phase_space.png": draw_corner(result, truth),
        "training.png": plot_training_curves(result),
        "rms_evolution.png": plot_rms_evolution(result, truth),
    }
    yield from figs.items()


def image_figures(
    dataset: MultiScanDataset,
    train_indices: Mapping[str, Sequence[int]],
    predicted: Mapping[str, Tensor],
    predicted_std: Mapping[str, Tensor] | None = None,
    *,
    plot: Callable[..., Figure] | None = None,
) -> Iterator[tuple[str, Figure]]:
    """One measured-vs-predicted image grid per scan, as ``(file name, figure)``.

    ``images.png`` for a single scan, ``images_<scan>.png`` otherwise; each
    drawn when it is taken (a generator).

    Args:
        dataset: The measured scans.
        train_indices: Trained settings per scan; the others are marked held out.
        predicted: Predicted images per scan, ``(K, H, W)``.
        predicted_std: Per-pixel spread of the prediction per scan, ``(K, H, W)``
            (a fourth row of each grid); None: no such row.
        plot: The drawing function (default :func:`plot_image_comparison`).
    """
    draw = plot_image_comparison if plot is None else plot
    for name, scan in dataset:
        train = {int(i) for i in train_indices.get(name, [])}
        fwd = ScreenForwardModel.from_dataset(scan)
        fig_name = "images.png" if len(dataset) == 1 else f"images_{name}.png"
        fig = draw(
            scan.mean_images(),
            predicted[name],
            scan.settings,
            setting_name=", ".join(scan.setting_names),
            extent=fwd.extent_mm(),
            held_out=[i not in train for i in range(scan.n_settings)],
            title=f"scan {name!r}" if len(dataset) > 1 else "",
            predicted_std=None if predicted_std is None else predicted_std[name],
        )
        yield fig_name, fig


def write_result_figures(
    result: Reconstruction,
    dataset: MultiScanDataset,
    folder: Path,
    *,
    corner: Callable[..., Figure] | None = None,
) -> list[str]:
    """Write :func:`result_figures` into ``folder``; returns the file names.

    The ``summary`` callback of
    :class:`~diffaccel.reconstruction.results.ResultFigures` (``corner``: as
    for :func:`result_figures`).
    """
    figs = result_figures(result, dataset, corner=corner)
    return save_figures(figs, folder, dpi=FIGURE_DPI)


def write_image_figures(
    dataset: MultiScanDataset,
    train_indices: Mapping[str, Sequence[int]],
    folder: Path,
    predicted: Mapping[str, Tensor],
    predicted_std: Mapping[str, Tensor] | None = None,
    *,
    plot: Callable[..., Figure] | None = None,
) -> list[str]:
    """Write :func:`image_figures` into ``folder``; returns the file names.

    The ``images`` callback of
    :class:`~diffaccel.reconstruction.results.ResultFigures` (``plot``: as
    for :func:`image_figures`).
    """
    figs = image_figures(dataset, train_indices, predicted, predicted_std, plot=plot)
    return save_figures(figs, folder, dpi=FIGURE_DPI)
