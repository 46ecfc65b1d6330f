"""Setting a magnet: the input that brings a fitted Preisach model to a target output.

numpy only, on the numbers ``diffaccel hysteresis predict`` streams (a
:class:`~diffaccel.hysteresis.stream.StreamSpec`), so that the answer is the one
``predict`` gives at the returned input after the same history.

Exact relays. After a history the hysteron states are ``s``; one more step to
input ``u`` sets ``s_i = +1`` where ``u >= alpha_i``, ``-1`` where
``u <= beta_i`` and leaves the rest, whichever way the input moves. Between
consecutive thresholds ``alpha_i``, ``beta_i`` the states are therefore
constant and the output ``output_loc + output_scale (offset + slope u_n + scale
m)`` is affine in ``u``; at the thresholds it jumps. :func:`solve_step` inverts
this piecewise affine response exactly (no smoothing: a smooth relaxation of the
relays, as :func:`~diffaccel.hysteresis.invert_preisach` used with
``smooth=True``, lands up to the smoothing width away from what exact relays
give). A target inside a jump cannot be reached in one step from that state;
:func:`plan_setpoint` then tries other approaches: a standardising
(degaussing) cycle to the input limits first, or an overshoot that turns back.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from diffaccel.hysteresis.stream import StreamPredictor, StreamSpec

__all__ = [
    "SET_TOL",
    "SetPoint",
    "StepSolution",
    "UnreachableTargetError",
    "field_for_k1",
    "plan_setpoint",
    "solve_step",
    "step_response",
    "step_states",
]

#: Output tolerance of an exact hit, as a fraction of ``output_scale`` (the
#: training output range of a fitted model); the solution is exact to round-off
#: (~1e-15) inside an affine piece.
SET_TOL = 1e-9
# margin [normalised input] kept from a threshold inside an affine piece, so
# that round-off of the input cannot switch a relay at the solution
_EDGE = 1e-11


class UnreachableTargetError(ValueError):
    """A target output outside the outputs reachable within the input limits.

    Attributes:
        reachable: ``(lowest, highest)`` reachable output [output units].
        limits: ``(lo, hi)`` input limits [input units].
    """

    def __init__(
        self, message: str, reachable: tuple[float, float], limits: tuple[float, float]
    ) -> None:
        super().__init__(message)
        self.reachable = reachable
        self.limits = limits


@dataclass(frozen=True)
class StepSolution:
    """Outcome of :func:`solve_step`, one entry per target.

    Attributes:
        input: Next input [input units], shape ``(K,)``; for a target not hit,
            the input whose output comes nearest.
        output: Output after that step (exact relays) [output units], ``(K,)``.
        reached: Whether ``output`` equals the target within the tolerance,
            ``(K,)`` bool.
        reachable: ``(lowest, highest)`` output of one step from the state
            within the limits [output units].
    """

    input: np.ndarray
    output: np.ndarray
    reached: np.ndarray
    reachable: tuple[float, float]


def _norm(spec: StreamSpec, u: np.ndarray) -> np.ndarray:
    lo, hi = spec.input_range
    return (np.asarray(u, dtype=np.float64) - lo) / (hi - lo)


def step_states(spec: StreamSpec, state: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Hysteron states after one more step from ``state`` to each input ``u``.

    Args:
        spec: The model's numbers.
        state: Hysteron states before the step, shape ``(M,)``.
        u: Inputs [input units], shape ``(K,)``.

    Returns:
        States, shape ``(K, M)`` (exact relays; inputs beyond the input range
        saturate).
    """
    un = np.clip(_norm(spec, u).reshape(-1, 1), 0.0, 1.0)
    s = np.asarray(state, dtype=np.float64)[None, :]
    return np.where(un >= spec.alpha, 1.0, np.where(un <= spec.beta, -1.0, s))


def _output(spec: StreamSpec, un: np.ndarray, m: np.ndarray) -> np.ndarray:
    y = spec.offset + spec.slope * un + spec.scale * m
    return spec.output_loc + spec.output_scale * y


def step_response(spec: StreamSpec, state: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Output after one more step from ``state`` to each input ``u`` (exact relays).

    Args:
        spec: The model's numbers.
        state: Hysteron states before the step, shape ``(M,)``.
        u: Inputs [input units], shape ``(K,)``.

    Returns:
        Outputs [output units], shape ``(K,)``.
    """
    u = np.asarray(u, dtype=np.float64).reshape(-1)
    m = step_states(spec, state, u) @ spec.weights
    return _output(spec, _norm(spec, u), m)


def _limits(spec: StreamSpec, limits: Sequence[float] | None) -> tuple[float, float]:
    lo, hi = spec.input_range
    if limits is None:
        return lo, hi
    vals = [float(v) for v in limits]
    if len(vals) != 2 or not all(math.isfinite(v) for v in vals):
        raise ValueError(
            f"limits must be two finite numbers (lo, hi); got {list(limits)}."
        )
    lo_l, hi_l = max(vals[0], lo), min(vals[1], hi)
    if not lo_l < hi_l:
        raise ValueError(
            f"limits ({vals[0]:.6g}, {vals[1]:.6g}) leave no inputs inside the "
            f"model's input range [{lo:.6g}, {hi:.6g}]; expected lo < hi overlapping "
            "it."
        )
    return lo_l, hi_l


def solve_step(
    spec: StreamSpec,
    state: np.ndarray,
    target: np.ndarray | float,
    limits: Sequence[float] | None = None,
    present: float | None = None,
    tol: float = SET_TOL,
) -> StepSolution:
    """Inputs whose one step from ``state`` gives each target output exactly.

    The response is affine between consecutive thresholds (see the module
    notes): each piece is solved in closed form, the thresholds and limits
    themselves are candidates too, and every answer is checked by evaluating
    :func:`step_response` at it. Where several inputs hit a target (a response
    that is not monotone) the one nearest ``present`` is kept.

    Args:
        spec: The model's numbers.
        state: Hysteron states before the step, shape ``(M,)``.
        target: Target outputs [output units], scalar or ``(K,)``.
        limits: ``(lo, hi)`` allowed inputs [input units], clipped to the
            model's input range (default: that range).
        present: Present input [input units], to break ties; ``None``: the
            lowest input.
        tol: Tolerance of a hit as a fraction of ``output_scale``.

    Returns:
        A :class:`StepSolution`.

    Raises:
        ValueError: for non-finite targets or limits outside the input range.
    """
    t = np.asarray(target, dtype=np.float64).reshape(-1)
    if not np.isfinite(t).all():
        raise ValueError("target contains NaN or infinite values.")
    lo_l, hi_l = _limits(spec, limits)
    lo, hi = spec.input_range
    width = hi - lo
    ln, hn = (lo_l - lo) / width, (hi_l - lo) / width
    thr = np.unique(np.concatenate([spec.alpha, spec.beta]))
    thr = thr[(thr > ln) & (thr < hn)]
    edges = np.concatenate([[ln], thr, [hn]])  # (J + 1,) normalised
    # every hysteron's state on each open piece (J, M): the state at its middle
    mids = 0.5 * (edges[:-1] + edges[1:])
    s = np.asarray(state, dtype=np.float64)[None, :]
    mid_c = mids[:, None]
    states = np.where(mid_c >= spec.alpha, 1.0, np.where(mid_c <= spec.beta, -1.0, s))
    base = _output(spec, np.zeros_like(mids), states @ spec.weights)  # (J,)
    gain = spec.output_scale * spec.slope  # output per normalised input
    margin = np.minimum(_EDGE, 0.25 * np.diff(edges))
    a, b = edges[:-1] + margin, edges[1:] - margin
    y_a, y_b = base + gain * a, base + gain * b
    y_lo, y_hi = np.minimum(y_a, y_b), np.maximum(y_a, y_b)
    # candidate inputs: per piece the closed-form solution clamped to it, and
    # the piece edges (thresholds and limits) as they are
    tc = t[:, None]
    if gain != 0:
        u_piece = np.clip((tc - base) / gain, a, b)
    else:
        u_piece = np.broadcast_to(mids, (t.size, mids.size))
    phys_edges = lo + edges * width
    phys_edges[0], phys_edges[-1] = lo_l, hi_l
    y_edges = step_response(spec, state, phys_edges)
    cand_u = np.concatenate(
        [lo + u_piece * width, np.broadcast_to(phys_edges, (t.size, edges.size))],
        axis=1,
    )
    cand_y = np.concatenate(
        [
            np.clip(tc, y_lo, y_hi),
            np.broadcast_to(y_edges, (t.size, edges.size)),
        ],
        axis=1,
    )
    miss = np.abs(cand_y - tc)
    scale = abs(spec.output_scale) * tol
    ref = lo_l if present is None else float(present)
    # nearest output first; among hits, the input nearest the present one
    hit = miss <= scale
    key = np.where(hit, np.abs(cand_u - ref), np.inf)
    best_hit = key.argmin(axis=1)
    best_near = miss.argmin(axis=1)
    rows = np.arange(t.size)
    pick = np.where(hit.any(axis=1), best_hit, best_near)
    u_out = np.clip(cand_u[rows, pick], lo_l, hi_l)
    y_out = step_response(spec, state, u_out)
    reached = np.abs(y_out - t) <= scale
    reachable = (
        float(min(y_lo.min(), y_edges.min())),
        float(max(y_hi.max(), y_edges.max())),
    )
    return StepSolution(u_out, y_out, reached, reachable)


@dataclass(frozen=True)
class SetPoint:
    """How to set a magnet to a target output, from :func:`plan_setpoint`.

    Attributes:
        target: Target output [output units].
        input: Input to set last [input units].
        approach: ``"from below"`` (the last step rises to ``input``),
            ``"from above"`` (it falls) or ``"stay"`` (``input`` is the present
            input and the target its present output).
        cycle: Inputs to apply before the last step, in order [input units]:
            empty for a single step from the present state; ``(hi, lo)`` or
            ``(lo, hi)`` (the input limits) for a standardising (degaussing)
            cycle; one input for an overshoot that turns back.
        kind: ``"direct"``, ``"cycle"`` or ``"overshoot"`` (what ``cycle`` is).
        output: Output predicted after the whole sequence (the streamed
            prediction ``hysteresis predict`` makes) [output units].
        std: Predictive standard deviation there [output units], ``None``
            without a band.
        reachable: ``(lowest, highest)`` output reachable within the limits
            [output units].
        limits: ``(lo, hi)`` input limits used [input units].
        present_input: Last input of the history [input units].
        present_output: Output predicted after the history [output units].
        tolerance: Largest accepted ``|output - target|`` [output units].
    """

    target: float
    input: float
    approach: str
    cycle: tuple[float, ...]
    kind: str
    output: float
    std: float | None
    reachable: tuple[float, float]
    limits: tuple[float, float]
    present_input: float
    present_output: float
    tolerance: float

    @property
    def sequence(self) -> tuple[float, ...]:
        """Every input to apply after the history, in order [input units]."""
        return (*self.cycle, self.input)

    @property
    def error(self) -> float:
        """``output - target`` [output units]."""
        return self.output - self.target


def _chunks(history: np.ndarray | Iterable[np.ndarray]) -> Iterable[np.ndarray]:
    if isinstance(history, np.ndarray):
        return [history.reshape(-1)]
    return history


def _apply(spec: StreamSpec, state: np.ndarray, inputs: Sequence[float]) -> np.ndarray:
    for v in inputs:
        state = step_states(spec, state, np.array([v]))[0]
    return state


def plan_setpoint(
    spec: StreamSpec,
    history: np.ndarray | Iterable[np.ndarray],
    target: float,
    limits: Sequence[float] | None = None,
    tol: float = SET_TOL,
) -> SetPoint:
    """Plan the inputs that bring the output to ``target`` after ``history``.

    Approaches, in order, the first whose streamed prediction hits the target
    is kept:

    1. one step from the present state (``"from below"`` or ``"from above"``);
    2. a standardising (degaussing) cycle to the input limits, ``hi`` then
       ``lo``, then up to the input; or ``lo`` then ``hi``, then down to it
       (a full cycle between the limits of the input range wipes the memory of
       the history);
    3. an overshoot: one input past the target's input, then back (from the
       present state, then after each cycle), overshoots tried nearest first.

    Only a target inside a jump of every one of these responses (a model
    without a linear term, or one hysteron worth more than the linear term
    across a mesh cell) is not hit; the nearest output is then returned.

    Args:
        spec: The model's numbers (with its band, for ``std``), e.g. from
            :func:`~diffaccel.hysteresis.load_stream_fit`.
        history: Inputs applied so far from the model's initial state [input
            units]: a 1-D array or an iterable of consecutive 1-D chunks (a
            long CSV streamed); at least one input.
        target: Target output [output units].
        limits: ``(lo, hi)`` allowed inputs [input units], clipped to the
            model's input range (default: that range).
        tol: Tolerance of a hit as a fraction of ``output_scale``.

    Returns:
        A :class:`SetPoint`; compare ``abs(error) <= tolerance`` to know
        whether the target was hit.

    Raises:
        UnreachableTargetError: if the target lies outside the outputs
            reachable within the limits (the message names that interval).
        ValueError: for an empty history, a non-finite target or limits
            outside the input range.
    """
    target = float(target)
    if not math.isfinite(target):
        raise ValueError(f"target must be a finite number; got {target}.")
    if not (math.isfinite(tol) and tol > 0):
        raise ValueError(f"tol must be a positive finite number; got {tol!r}.")
    lo_l, hi_l = _limits(spec, limits)
    predictor = StreamPredictor(spec)
    present_in, present_out, n_rows = math.nan, math.nan, 0
    for chunk in _chunks(history):
        x = np.asarray(chunk, dtype=np.float64).reshape(-1)
        if x.size == 0:
            continue
        pred, _ = predictor(x)
        present_in, present_out, n_rows = float(x[-1]), float(pred[-1]), n_rows + x.size
    if n_rows == 0:
        raise ValueError("history is empty; give at least one input applied so far.")
    state = predictor.state
    scale = abs(spec.output_scale) * tol

    def attempt(prefix: tuple[float, ...]):
        s = _apply(spec, state, prefix)
        before = prefix[-1] if prefix else present_in
        return s, before, solve_step(spec, s, target, (lo_l, hi_l), before, tol)

    kinds = [((), "direct"), ((hi_l, lo_l), "cycle"), ((lo_l, hi_l), "cycle")]
    tried = [attempt(prefix) for prefix, _ in kinds]
    lowest = min(r[2].reachable[0] for r in tried)
    highest = max(r[2].reachable[1] for r in tried)
    if target < lowest - scale or target > highest + scale:
        raise UnreachableTargetError(
            f"target {target:.6g} is outside the outputs reachable within the input "
            f"limits [{lo_l:.6g}, {hi_l:.6g}]: [{lowest:.6g}, {highest:.6g}].",
            (lowest, highest),
            (lo_l, hi_l),
        )
    chosen = None
    for (prefix, kind), (_, _, sol) in zip(kinds, tried, strict=True):
        if bool(sol.reached[0]):
            chosen = (prefix, kind, float(sol.input[0]))
            break
    if chosen is None:  # the target sits in a jump: overshoot and turn back
        turns = _turning_points(spec, lo_l, hi_l)
        for (prefix, _), (s0, _, sol0) in zip(kinds, tried, strict=True):
            near = float(sol0.input[0])
            for p in turns[np.argsort(np.abs(turns - near), kind="stable")]:
                s = _apply(spec, s0, (float(p),))
                sol = solve_step(spec, s, target, (lo_l, hi_l), float(p), tol)
                if bool(sol.reached[0]) and float(sol.input[0]) != float(p):
                    chosen = ((*prefix, float(p)), "overshoot", float(sol.input[0]))
                    break
            if chosen is not None:
                break
    if chosen is None:  # nothing hits: the nearest one-step output
        sol = tried[0][2]
        chosen = ((), "direct", float(sol.input[0]))
    prefix, kind, u = chosen
    # the answer is what the streamed prediction gives after the same history
    check = copy.copy(predictor)
    pred, std = check(np.asarray((*prefix, u), dtype=np.float64))
    before = prefix[-1] if prefix else present_in
    approach = "from below" if u > before else "from above" if u < before else "stay"
    return SetPoint(
        target=target,
        input=u,
        approach=approach,
        cycle=tuple(prefix),
        kind=kind,
        output=float(pred[-1]),
        std=None if std is None else float(std[-1]),
        reachable=(lowest, highest),
        limits=(lo_l, hi_l),
        present_input=present_in,
        present_output=present_out,
        tolerance=scale,
    )


def _turning_points(spec: StreamSpec, lo_l: float, hi_l: float) -> np.ndarray:
    """Inputs in the middle of each piece between thresholds within the limits."""
    lo, hi = spec.input_range
    width = hi - lo
    ln, hn = (lo_l - lo) / width, (hi_l - lo) / width
    thr = np.unique(np.concatenate([spec.alpha, spec.beta]))
    edges = np.concatenate([[ln], thr[(thr > ln) & (thr < hn)], [hn]])
    return lo + 0.5 * (edges[:-1] + edges[1:]) * width


# [m/s], exact; diffaccel.dynamics.SPEED_OF_LIGHT, kept here so that setting a
# magnet runs without torch
_SPEED_OF_LIGHT = 299_792_458.0


def field_for_k1(k1: float, length: float, p0c: float, charge_e: float = 1.0) -> float:
    """Integrated gradient that gives a quadrupole strength: ``k1 L B rho``.

    The calibration of :class:`~diffaccel.hysteresis.HystereticMagnet`:
    ``k1 = G / (L B rho)`` with ``B rho = p0c / (c |q|)``.

    Args:
        k1: Normalised gradient [1/m^2].
        length: Magnetic length [m], > 0.
        p0c: Reference momentum times c [eV], > 0.
        charge_e: Particle charge [e] (its magnitude is used).

    Returns:
        Integrated gradient ``G`` [T].

    Raises:
        ValueError: for a non-finite ``k1`` or a length, ``p0c`` or charge that
            is not positive and finite.
    """
    vals = {"k1": k1, "length": length, "p0c": p0c, "charge_e": charge_e}
    for name, v in vals.items():
        if not math.isfinite(float(v)):
            raise ValueError(f"{name} must be finite; got {v}.")
    for name in ("length", "p0c"):
        if not float(vals[name]) > 0:
            raise ValueError(f"{name} must be > 0; got {vals[name]}.")
    if float(charge_e) == 0:
        raise ValueError("charge_e must be non-zero.")
    brho = float(p0c) / (_SPEED_OF_LIGHT * abs(float(charge_e)))
    return float(k1) * float(length) * brho
