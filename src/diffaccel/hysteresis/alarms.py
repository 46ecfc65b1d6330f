"""Fit-quality alarms of hysteresis fits, from numbers the fits already have.

Each alarm is one line that names the signal, its numbers, and the likely
causes of *that* signal, most likely first; a good fit raises none. Plain
Python (no torch), so that every command can use them.

Thresholds, set on synthetic good and bad fits (``benchmarks/hysteresis_alarms.py``,
default options as the CLI):

* :data:`LINE_RATIO` (0.7): a Preisach fit whose rms error (held-out rows, or
  the training rows when none are held out) is at least this fraction of a
  straight line's on the same rows has learnt little beyond the line. Good
  fits: 0.05-0.44 of the line on 20 synthetic cases (5 unipolar quadrupoles
  with 2 % hysteresis: 0.21-0.24; 8 bipolar quadrupoles: 0.20-0.44; 7 B-H
  loops resolved by the mesh: 0.05-0.14), 0.33 on the SLAC quadrupole; no
  alarm. Bad fits: 1.00 with an input range 100x the data, 1.10-1.18 with the
  rows shuffled (time order lost), 1.13-1.33 for a magnet without hysteresis
  above its noise; every one alarms.
* :data:`GP_NOISE_RATIO`, :data:`GP_HELDOUT_RATIO` (1.1 each): an H-GP whose
  noise or held-out rms error exceeds the plain GP's by this factor is worse
  than ignoring the hysteresis (10 % above parity for the scatter of fits on
  the same rows). Good H-GPs (started from a Preisach fit): noise 0.04-0.12 and
  held-out error 0.04-0.08 of the plain GP's on 3 synthetic quadrupoles and 2
  beam transmissions; bad ones (a uniform starting density without the input
  feature, on a quadrupole's field): 10-12 both; no false and no missed
  alarm.
"""

from __future__ import annotations

import math

__all__ = [
    "GP_HELDOUT_RATIO",
    "GP_NOISE_RATIO",
    "LINE_RATIO",
    "OUTLIER_GAP",
    "WIDE_RANGE",
    "hgp_alarms",
    "input_outlier_alarms",
    "preisach_alarms",
]

#: rms error / straight line's rms error at or above which a Preisach fit warns
LINE_RATIO = 0.7
#: H-GP noise / plain GP noise above which an H-GP warns
GP_NOISE_RATIO = 1.1
#: H-GP held-out rms / plain GP held-out rms above which an H-GP warns
GP_HELDOUT_RATIO = 1.1
#: input range / training inputs' span beyond which the range is named first
WIDE_RANGE = 3.0
#: gap between the largest (smallest) input and the next one, in spans of the
#: other inputs, beyond which that input is reported as a stray value
OUTLIER_GAP = 10.0


def input_outlier_alarms(values: list[float], column: str) -> list[str]:
    """One line per end of the inputs that a single stray value stretches.

    An input cell far outside all the others (a typo such as ``1e99``, a value
    in another unit) sets the fit's input range by itself, and the mesh then
    has no cells where the data are. The largest and the smallest input are
    each compared with the span of all the others: a gap above
    :data:`OUTLIER_GAP` spans is reported with its row (1-based data row).
    Measured histories have gaps of one step of their scan at most (a ramp of
    ``N`` even steps: ``1 / (N - 1)`` spans; the SLAC quadrupole's, which
    revisits its extremes: below 1e-4 spans).

    Example:
        >>> input_outlier_alarms([0.0, 1.0, 2.0, 1e99, 1.5], "current_A")[0][:37]
        "input column 'current_A', data row 4:"
        >>> input_outlier_alarms([0.0, 1.0, 2.0, 1.5], "current_A")
        []
    """
    finite = [(v, i) for i, v in enumerate(values) if math.isfinite(v)]
    if len(finite) < 3:
        return []
    ordered = sorted(finite)
    out = []
    for value, row, neighbour, rest in (
        (*ordered[-1], ordered[-2][0], ordered[:-1]),
        (*ordered[0], ordered[1][0], ordered[1:]),
    ):
        span = rest[-1][0] - rest[0][0]
        gap = abs(value - neighbour)
        if span > 0 and gap > OUTLIER_GAP * span:
            out.append(
                f"input column {column!r}, data row {row + 1}: {value:g} lies "
                f"{gap / span:.3g} spans of the other inputs ({rest[0][0]:g} .. "
                f"{rest[-1][0]:g}) beyond them and sets the fit's input range by "
                "itself. Likely causes: a typo or a stray value in that cell; a "
                "value in another unit; a row from another measurement"
            )
    return out


def _ok(*values: float | None) -> bool:
    return all(v is not None and math.isfinite(v) for v in values)


def preisach_alarms(
    rmse: float | None,
    line_rmse: float | None,
    rows: str,
    *,
    train_rmse: float | None = None,
    line_train_rmse: float | None = None,
    input_range: tuple[float, float] | None = None,
    train_span: float | None = None,
    cell_width: float | None = None,
    output_range: float | None = None,
) -> list[str]:
    """Alarms of a Preisach fit whose error is close to a straight line's.

    Args:
        rmse: The fit's rms error on ``rows`` [output units].
        line_rmse: A straight line's (fitted on the training rows) on the
            same rows [output units].
        rows: ``"held-out"`` or ``"training"``: which rows the errors are of.
        train_rmse: The fit's rms error on the training rows (to tell a fit
            that missed the loop from one that missed the held-out rows).
        line_train_rmse: The line's on the training rows.
        input_range: The model's ``(lo, hi)`` [input units].
        train_span: Span of the training inputs [input units].
        cell_width: Width of one mesh cell [input units].
        output_range: Span of the training outputs [output units].

    Returns:
        Zero or one alarm line.
    """
    if not _ok(rmse, line_rmse) or not line_rmse > 0:
        return []
    ratio = rmse / line_rmse
    if ratio < LINE_RATIO:
        return []
    causes: list[str] = []
    width = None if input_range is None else input_range[1] - input_range[0]
    if _ok(width, train_span) and train_span > 0 and width > WIDE_RANGE * train_span:
        causes.append(
            f"the input range [{input_range[0]:.6g}, {input_range[1]:.6g}] is "
            f"{width / train_span:.3g}x the training inputs' span, so few hysterons "
            "lie where the data are (check --input-range and outlier inputs)"
        )
    train_bad = _ok(train_rmse, line_train_rmse) and line_train_rmse > 0
    train_bad = train_bad and train_rmse >= LINE_RATIO * line_train_rmse
    if rows == "held-out" and not train_bad:
        causes.append(
            "the held-out rows exercise branches or minor loops the training rows "
            "never did (train on rows that reverse where the held-out rows do)"
        )
        causes.append(
            "the rows are not in time order, or the state before the first row "
            "is not the one assumed (--time-column, --initial-state)"
        )
    else:
        if cell_width is not None and math.isfinite(cell_width):
            causes.append(
                f"the material switches within one mesh cell ({cell_width:.4g} "
                "input units: a coercive field below it, as in soft iron), so the "
                "loop is not resolved (a finer or wide-range mesh)"
            )
        causes.append(
            "the rows are not in time order, or the state before the first row "
            "is not the one assumed (--time-column, --initial-state)"
        )
    if _ok(line_rmse, output_range) and output_range > 0:
        causes.append(
            f"the output is nearly a straight line of the input (the line misses "
            f"by {100 * line_rmse / output_range:.3g} % of the range): little "
            "hysteresis above the measurement noise, nothing for the model to add"
        )
    return [
        f"the hysteresis fit's {rows} rms error {rmse:.4g} is {ratio:.2f} of a "
        f"straight line's ({line_rmse:.4g}; alarm at {LINE_RATIO}): the model adds "
        f"little to a line. Likely causes: {'; '.join(causes)}."
    ]


def hgp_alarms(
    noise: float,
    plain_noise: float,
    heldout_rmse: float | None = None,
    plain_heldout_rmse: float | None = None,
) -> list[str]:
    """Alarms of an H-GP worse than the plain GP (noise, held-out rms error).

    Args:
        noise: The H-GP's noise standard deviation [units of the response].
        plain_noise: The plain GP's.
        heldout_rmse: The H-GP's rms error on held-out rows (``None``: none).
        plain_heldout_rmse: The plain GP's there.

    Returns:
        Zero, one or two alarm lines.
    """
    out = []
    if _ok(noise, plain_noise) and plain_noise > 0:
        ratio = noise / plain_noise
        if ratio > GP_NOISE_RATIO:
            out.append(
                f"the H-GP's noise {noise:.4g} is {ratio:.2f}x the plain GP's "
                f"({plain_noise:.4g}; alarm above {GP_NOISE_RATIO}): the joint fit "
                "explains the response as noise instead of magnetic state. Likely "
                "causes: the fit stopped in a poor optimum (more --restarts, "
                "another --seed); the response does not follow this input's "
                "hysteresis (a plain GP is the better model); the rows are not in "
                "time order or the initial state is wrong (--time-column, "
                "--initial-state); the input range leaves the data in few mesh "
                "cells (--input-range)."
            )
    if _ok(heldout_rmse, plain_heldout_rmse) and plain_heldout_rmse > 0:
        ratio = heldout_rmse / plain_heldout_rmse
        if ratio > GP_HELDOUT_RATIO:
            out.append(
                f"the H-GP's held-out rms error {heldout_rmse:.4g} is {ratio:.2f}x "
                f"the plain GP's ({plain_heldout_rmse:.4g}; alarm above "
                f"{GP_HELDOUT_RATIO}): the magnetic state it predicts for the "
                "held-out rows misleads it. Likely causes: the held-out rows reach "
                "states the training history never did (minor loops, other "
                "branches); the density overfits the training rows (a coarser "
                "--mesh-size); the rows are not in time order or the initial "
                "state is wrong (--time-column, --initial-state)."
            )
    return out
