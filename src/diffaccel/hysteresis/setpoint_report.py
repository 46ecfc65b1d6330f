"""A magnet's set point (:func:`~diffaccel.hysteresis.plan_setpoint`) as text and JSON.

numpy only, as :mod:`diffaccel.hysteresis.setpoint`. A target is an output
[output units] or, with a magnetic ``length`` [m] and ``p0c`` [eV], a
quadrupole strength k1 [1/m^2] whose output is the integrated gradient
(:func:`~diffaccel.hysteresis.field_for_k1`). :func:`plan_history_setpoint`
plans the set point after a history read from CSV chunk by chunk, its
refusals in words.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from diffaccel.data import FormatError, OptionError
from diffaccel.data.magnet_stream import check_magnitude
from diffaccel.hysteresis.setpoint import (
    SetPoint,
    UnreachableTargetError,
    field_for_k1,
    plan_setpoint,
)
from diffaccel.hysteresis.stream import InputRangeWarning, StreamSpec

__all__ = [
    "ACCEPT",
    "check_limits",
    "jump_text",
    "plan_history_setpoint",
    "setpoint_lines",
    "setpoint_summary",
    "unreachable_text",
]

#: Largest |error| of a set point accepted, as a fraction of the output range.
ACCEPT = 1e-6


def _g(v: float) -> str:
    """A number to 12 significant digits (set again, it gives the same output)."""
    return f"{v:.12g}"


def unreachable_text(
    err: UnreachableTargetError,
    *,
    target: float,
    output: float,
    input_column: str,
    output_column: str,
    length: float | None = None,
    p0c: float | None = None,
) -> str:
    """Why ``target`` cannot be reached: the reachable outputs within the limits.

    Args:
        err: The refusal of :func:`~diffaccel.hysteresis.plan_setpoint`.
        target: The target as given (an output, or k1 with ``length``).
        output: Its output [output units].
        input_column: Name of the input.
        output_column: Name of the output.
        length: Magnetic length [m] of a k1 target (None: an output target).
        p0c: Reference momentum times c [eV] of a k1 target.
    """
    lo, hi = err.reachable
    what = f"{output_column} {_g(target)}"
    span = f"{output_column} {lo:.6g} .. {hi:.6g}"
    if length is not None:
        per = output / target if target else field_for_k1(1.0, length, p0c)
        what = f"k1 {_g(target)} 1/m^2 ({output_column} {output:.6g})"
        span = f"k1 {lo / per:.6g} .. {hi / per:.6g} 1/m^2 ({span})"
    return (
        f"{what} cannot be reached: the fit reaches {span} within "
        f"{input_column} {err.limits[0]:.6g} .. {err.limits[1]:.6g} after this "
        "history."
    )


def jump_text(
    plan: SetPoint,
    output: float,
    output_scale: float,
    input_column: str,
    output_column: str,
) -> str | None:
    """Where the plan misses ``output`` by more than :data:`ACCEPT` of the
    range ``output_scale``: the target lies in a jump of the model (a row of
    hysterons switching); the text names the nearest input. None otherwise."""
    if abs(plan.error) <= ACCEPT * abs(output_scale):
        return None
    return (
        f"{output_column} {_g(output)} lies in a jump of the fitted model (a row of "
        f"hysterons switching) for every approach tried; nearest: {input_column} "
        f"{_g(plan.input)} gives {plan.output:.6g}."
    )


def setpoint_summary(
    plan: SetPoint,
    *,
    fit: str,
    history: str,
    input_column: str,
    output_column: str,
    target: float,
    output: float,
    output_scale: float,
    notes: Sequence[str] = (),
    length: float | None = None,
    p0c: float | None = None,
) -> dict[str, Any]:
    """The plan as one JSON-ready object (``length``, ``p0c``: of a k1 target).

    ``error_fraction_of_range`` is the plan's error over ``output_scale``.
    """
    summary: dict[str, Any] = {
        "fit": fit,
        "history": history,
        "input_column": input_column,
        "output_column": output_column,
        "target": target,
        "target_kind": "output" if length is None else "k1",
        "target_output": output,
        "input": plan.input,
        "approach": plan.approach,
        "kind": plan.kind,
        "cycle": list(plan.cycle),
        "sequence": list(plan.sequence),
        "predicted_output": plan.output,
        "predicted_std": plan.std,
        "error": plan.error,
        "error_fraction_of_range": plan.error / output_scale,
        "reachable": list(plan.reachable),
        "limits": list(plan.limits),
        "present_input": plan.present_input,
        "present_output": plan.present_output,
        "notes": list(notes),
    }
    if length is not None:
        summary.update(length=length, p0c=p0c)
    return summary


def setpoint_lines(
    plan: SetPoint,
    *,
    input_column: str,
    output_column: str,
    k1: float | None = None,
) -> list[str]:
    """Two lines: what to set and what it gives (1 std), and what is reachable.

    The first names any degaussing cycle or overshoot before the last step,
    the input to set and its approach, the present state and the predicted
    output (``k1``: the target strength [1/m^2] too); the second the outputs
    reachable within the limits and every input to apply.
    """
    i, o = input_column, output_column
    if plan.kind == "cycle":
        first = (
            f"first a degaussing cycle: {i} {_g(plan.cycle[0])}, then "
            f"{_g(plan.cycle[1])}; then "
        )
    elif plan.kind == "overshoot":
        steps = ", then ".join(_g(v) for v in plan.cycle)
        first = f"first {i} {steps} (overshoot); then "
    else:
        first = ""
    std = "" if plan.std is None or math.isnan(plan.std) else f" +- {plan.std:.4g}"
    want = "" if k1 is None else f"k1 {_g(k1)} 1/m^2: "
    lo, hi = plan.reachable
    return [
        f"{first}set {i} to {_g(plan.input)} {plan.approach} (present "
        f"{i} {_g(plan.present_input)}, {o} {plan.present_output:.6g}): "
        f"{want}{o} {plan.output:.8g}{std} (1 std) predicted there",
        f"reachable {o} {lo:.6g} .. {hi:.6g} within {i} "
        f"{plan.limits[0]:.6g} .. {plan.limits[1]:.6g}; inputs to apply: "
        f"{', '.join(_g(v) for v in plan.sequence)}",
    ]


def check_limits(
    spec: StreamSpec, limits: Sequence[float] | None, input_column: str
) -> None:
    """Refuse input ``limits`` that leave no input inside the fit's input range.

    Raises:
        OptionError: for ``--limits``, naming the fit's input range.
    """
    r_lo, r_hi = spec.input_range
    if limits is not None and not (limits[0] < r_hi and limits[1] > r_lo):
        raise OptionError(
            f"{limits[0]:g} {limits[1]:g} leave no {input_column} inside the fit's "
            f"input range [{r_lo:.6g}, {r_hi:.6g}].",
            "--limits",
        )


def plan_history_setpoint(
    spec: StreamSpec,
    data: Path,
    chunks: Iterable[tuple[list[str], np.ndarray]],
    *,
    input_column: str,
    output_column: str,
    target: float,
    output: float,
    limits: Sequence[float] | None = None,
    length: float | None = None,
    p0c: float | None = None,
) -> tuple[SetPoint, list[str]]:
    """:func:`~diffaccel.hysteresis.plan_setpoint` after the history in ``chunks``.

    Args:
        spec: The fit.
        data: The history's CSV file (named in the messages).
        chunks: ``(row texts, inputs)`` of the history in time order
            (:func:`~diffaccel.data.iter_magnet_csv`); each input checked
            against :data:`~diffaccel.data.magnet_stream.MAX_MAGNITUDE`.
        input_column: Name of the input.
        output_column: Name of the output.
        target: The target as given (an output, or k1 with ``length``).
        output: Its output [output units].
        limits: Allowed inputs (default: the fit's input range).
        length: Magnetic length [m] of a k1 target (None: an output target).
        p0c: Reference momentum times c [eV] of a k1 target.

    Returns:
        The plan and the notes on inputs beyond the fit's input range.

    Raises:
        ValueError: an unreachable target (:func:`unreachable_text`), one in a
            jump of the model (:func:`jump_text`), a value beyond the largest
            magnitude, or a history the plan refuses (prefixed ``DATA:``).
    """
    refused: list[FormatError] = []

    def inputs() -> Iterator[np.ndarray]:
        first_row = 1
        for rows, x in chunks:
            try:
                check_magnitude(data, input_column, x, first_row)
            except FormatError as err:  # named already: not prefixed below
                refused.append(err)
                raise
            first_row += len(rows)
            yield x

    k1 = {"length": length, "p0c": p0c} if length is not None else {}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", InputRangeWarning)
        try:
            plan = plan_setpoint(spec, inputs(), output, limits)
        except UnreachableTargetError as err:
            text = unreachable_text(
                err,
                target=target,
                output=output,
                input_column=input_column,
                output_column=output_column,
                **k1,
            )
            raise ValueError(text) from err
        except ValueError as err:
            if refused and err is refused[0]:
                raise
            raise ValueError(f"{data}: {err}") from err
    notes = sorted({str(w.message) for w in caught if w.category is InputRangeWarning})
    jump = jump_text(plan, output, spec.output_scale, input_column, output_column)
    if jump:
        raise ValueError(jump)
    return plan, notes
