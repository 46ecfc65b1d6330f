"""Figures of the experiment design: singular-value spectrum and expected std."""

from __future__ import annotations

import errno
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from diffaccel.data.atomic import atomic_write

__all__ = [
    "design_figures",
    "plot_expected_std",
    "plot_spectrum",
    "write_design_figures",
]


def plot_spectrum(observability: Mapping[str, Any]) -> Figure:
    """Relative singular values of the moment design, the unseen directions named.

    Args:
        observability: ``Observability.to_dict()`` of
            :func:`diffaccel.reconstruction.design.observability`.

    Returns:
        A figure: singular values (log scale, descending) with each unseen
        direction's words at its bar, and the tolerance line.
    """
    sv = np.asarray(observability["singular_values"], dtype=float)
    fig = Figure(figsize=(7.0, 3.6), layout="constrained")
    ax = fig.add_subplot()
    idx = np.arange(1, len(sv) + 1)
    unseen = {
        round(u["singular_value"], 15): u["words"] for u in observability["unseen"]
    }
    colors = ["C3" if round(v, 15) in unseen else "C0" for v in sv]
    ax.bar(idx, np.maximum(sv, 1e-16), color=colors)
    ax.set_yscale("log")
    ax.set_xlabel("direction (descending singular value)")
    ax.set_ylabel("singular value / largest")
    notes = []
    for i, v in zip(idx, sv, strict=True):
        words = unseen.get(round(v, 15))
        if words:
            ax.annotate(
                str(i),
                (i, max(v, 1e-16)),
                xytext=(0, 2),
                textcoords="offset points",
                ha="center",
                va="bottom",
                fontsize=8,
            )
            notes.append(f"{i}: {words} ({v:.1e})")
    if notes:
        ax.text(
            0.02,
            0.04,
            "unseen:\n" + "\n".join(notes),
            transform=ax.transAxes,
            fontsize=8,
            va="bottom",
            ha="left",
            bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "0.7"},
        )
    extra = observability.get("not_seen") or []
    title = "moment design"
    if extra:
        title += f" ({', '.join(extra)} not seen at all)"
    ax.set_title(title)
    return fig


def plot_expected_std(
    report: Mapping[str, Any], names: list[str] | None = None
) -> Figure:
    """Expected relative std of each quantity against the number of added images.

    Args:
        report: :func:`diffaccel.reconstruction.design.recommend`'s result.
        names: Quantities to draw (default: the targets and any other whose
            std changes by more than 20 % of today's).

    Returns:
        A figure: one line per quantity, x the cumulative added images
        (0: today's scans).
    """
    base = report["baseline_std"]
    steps = report["recommended"]
    n = np.cumsum([0] + [r["n_images"] for r in steps])
    if names is None:
        names = list(report["targets"])
        for q in base:
            if q in names or not steps:
                continue
            if abs(steps[-1]["all_std"][q] - base[q]) > 0.2 * max(base[q], 1e-12):
                names.append(q)
    fig = Figure(figsize=(6.0, 3.8), layout="constrained")
    ax = fig.add_subplot()
    for q in names:
        ys = [base[q]] + [r["all_std"][q] for r in steps]
        ax.plot(
            n,
            100 * np.asarray(ys),
            marker="o",
            lw=2 if q in report["targets"] else 1,
            label=q,
        )
    ax.set_yscale("log")
    ax.set_xlabel("added images")
    ax.set_ylabel("expected relative std [%]")
    ax.legend(fontsize=8, ncols=2)
    return fig


def design_figures(
    observability: Mapping[str, Any], report: Mapping[str, Any] | None = None
) -> Iterator[tuple[str, Figure]]:
    """The figures of a design, as ``(file name, figure)`` pairs.

    ``singular_values.png`` (:func:`plot_spectrum`) and, where ``report``
    (of :func:`~diffaccel.reconstruction.design.recommend`) recommends
    settings, ``expected_std.png`` (:func:`plot_expected_std`).
    """
    yield "singular_values.png", plot_spectrum(observability)
    if report is not None and report["recommended"]:
        yield "expected_std.png", plot_expected_std(report)


def write_design_figures(
    folder: Path,
    observability: Mapping[str, Any],
    report: Mapping[str, Any] | None = None,
) -> list[Path]:
    """Write the :func:`design_figures` into ``folder`` (made if missing) as PNG.

    Never replaces a file: the figures before one that exists stay written.

    Raises:
        FileExistsError: a figure's file exists (its ``filename``).
    """
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for name, fig in design_figures(observability, report):
        path = folder / name
        try:
            atomic_write(
                path,
                lambda p, f=fig: f.savefig(p, format="png", dpi=120),
                overwrite=False,
            )
        except FileExistsError as err:
            raise FileExistsError(errno.EEXIST, "exists", str(path)) from err
        written.append(path)
    return written
