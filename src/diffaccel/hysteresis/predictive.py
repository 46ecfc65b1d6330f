"""Fit a magnet's Preisach model with a predictive band; stream long predictions.

:func:`fit_magnet` is the front door used by the CLI, the benchmarks and the
acceptance tests. Choices that cannot be read from physics are made by
validation on the training rows only: the last ``validation_fraction`` of the
training rows is held out, the candidates (symmetric density or not) are
fitted on the rest and scored on them, and the validation residuals calibrate
the predictive band. The chosen model is then refitted on all training rows.
Whether the density is symmetric follows the physics of the input range
(:func:`symmetric_default`) unless the caller says.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor

from diffaccel.dynamics import is_integer
from diffaccel.hysteresis.band import LaplaceBand, laplace_band
from diffaccel.hysteresis.fit import (
    MIN_FIT_POINTS,
    FitResult,
    check_series,
    fit_preisach,
)
from diffaccel.hysteresis.mesh import PreisachMesh
from diffaccel.hysteresis.preisach import PreisachModel
from diffaccel.hysteresis.stream import StreamPredictor

__all__ = [
    "MAX_MESH_SIZE",
    "RANGE_MARGIN",
    "MagnetFit",
    "band_memory_bytes",
    "check_mesh_size",
    "default_input_range",
    "fit_magnet",
    "min_training_rows",
    "predict_stream",
    "symmetric_default",
]

# margin added to the training input range so that nearby inputs stay inside
RANGE_MARGIN = 0.01
# rows held out of the training rows for validation (at least 2)
VALIDATION_FRACTION = 0.25
#: Largest ``mesh_size`` :func:`fit_magnet` takes. Its predictive band
#: (:func:`~diffaccel.hysteresis.band.laplace_band`) works with dense
#: ``(M + 3) x (M + 3)`` float64 matrices of the ``M = n (n + 1) / 2`` hysterons
#: (see :func:`band_memory_bytes`) and diagonalises one (time ~ M^3): 100 cells
#: per axis (5050 hysterons) need ~1.4 GB and tens of seconds; 500 would need
#: ~880 GB. The default (20) and the acceptance benchmark's best sizes are far
#: below it.
MAX_MESH_SIZE = 100
# dense (M + 3)^2 float64 matrices alive at the band's peak (measured: ~6.7)
_BAND_MATRICES = 7


def band_memory_bytes(mesh_size: int) -> int:
    """Peak memory of the predictive band of a triangular mesh [bytes].

    Args:
        mesh_size: Cells per axis ``n`` (``M = n (n + 1) / 2`` hysterons).

    Returns:
        About ``7 * 8 * (M + 3)^2`` bytes (dense float64 matrices).
    """
    m = mesh_size * (mesh_size + 1) // 2
    return _BAND_MATRICES * 8 * (m + 3) ** 2


def check_mesh_size(mesh_size: int) -> None:
    """Refuse a mesh whose predictive band would not fit (see :data:`MAX_MESH_SIZE`).

    Raises:
        ValueError: for ``mesh_size`` beyond ``MAX_MESH_SIZE``, naming the
            hysterons and the memory the band would need.
    """
    if mesh_size > MAX_MESH_SIZE:
        raise ValueError(
            f"mesh_size {mesh_size} is beyond {MAX_MESH_SIZE}: its "
            f"{mesh_size * (mesh_size + 1) // 2:,} hysterons would need "
            f"~{band_memory_bytes(mesh_size) / 1e9:.3g} GB for the predictive "
            f"band (dense hysteron x hysteron matrices); use at most "
            f"{MAX_MESH_SIZE} (default 20)."
        )


def _held_out(n: int, validation_fraction: float) -> int:
    """Rows held out for validation of ``n`` training rows."""
    return max(2, round(validation_fraction * n))


def min_training_rows(validation_fraction: float = VALIDATION_FRACTION) -> int:
    """Fewest training rows :func:`fit_magnet` takes: ``MIN_FIT_POINTS`` left to fit.

    Raises:
        ValueError: unless ``0 <= validation_fraction < 1``.
    """
    if not 0 <= validation_fraction < 1:
        raise ValueError(
            f"validation_fraction must be in [0, 1); got {validation_fraction}."
        )
    n = MIN_FIT_POINTS + 2
    while n - _held_out(n, validation_fraction) < MIN_FIT_POINTS:
        n += 1
    return n


def symmetric_default(input_range: Sequence[float]) -> bool:
    """Whether a density should be symmetric by default: a range centred on 0.

    The symmetry of magnets and soft magnetic materials,
    ``mu(alpha, beta) = mu(-beta, -alpha)``, holds about zero input (zero
    field); a model's symmetry is about the centre of its input range, so the
    two agree when the range is centred on zero (bipolar magnets, B-H loops;
    within 5 % of the range). A unipolar range (e.g. 0 .. 165 A) is not.
    The training rows cannot settle this themselves: for a B-H loop fitted on
    its virgin curve and first descent they never exercise the mirrored
    hysterons (see ``benchmarks/preisach_acceptance.py``).
    """
    vals = [float(v) for v in input_range]
    if len(vals) != 2 or not all(math.isfinite(v) for v in vals):
        raise ValueError(
            f"input_range must be two finite numbers (lo, hi); got {list(input_range)}."
        )
    lo, hi = vals
    return abs(lo + hi) <= 0.05 * (hi - lo)


def default_input_range(
    current: Tensor, initial_state: str = "negative"
) -> tuple[float, float]:
    """Model input range from training inputs [input units].

    The training span plus ``RANGE_MARGIN`` of it on both sides. A magnet that
    starts ``"demagnetized"`` was demagnetized about zero input, which is then
    the centre of its Preisach plane: the range is symmetric about 0,
    ``+-(1 + RANGE_MARGIN) max|u|``.

    Args:
        current: Training inputs [input units], shape ``(T,)``, finite.
        initial_state: The model's initial state kind.

    Returns:
        ``(lo, hi)`` with ``lo < hi``.

    Raises:
        ValueError: if ``current`` is empty or holds NaN or infinite values.
    """
    current = torch.as_tensor(current)
    if current.numel() < 1:
        raise ValueError("current is empty; need at least one training input.")
    if not bool(torch.isfinite(current).all()):
        raise ValueError("current contains NaN or infinite values.")
    lo, hi = float(current.min()), float(current.max())
    if initial_state == "demagnetized":
        top = (1.0 + RANGE_MARGIN) * max(abs(lo), abs(hi), 1e-12)
        return (-top, top)
    pad = RANGE_MARGIN * max(hi - lo, abs(hi), 1e-12)
    return (lo - pad, hi + pad)


@dataclass
class MagnetFit:
    """Outcome of :func:`fit_magnet`.

    Attributes:
        model: The Preisach model fitted on all training rows.
        band: Its predictive band (one standard deviation with noise).
        result: The final :class:`FitResult`.
        symmetric: Whether the chosen density is symmetric.
        validation: ``[{"symmetric", "val_rows", "val_rmse"}]``: rms error
            [output units] on the training rows held out for validation.
        calibration: Band factor measured on the validation rows (>= 1).
        seconds: Wall-clock time of everything [s].
    """

    model: PreisachModel
    band: LaplaceBand
    result: FitResult
    symmetric: bool
    validation: list[dict] = field(default_factory=list)
    calibration: float = 1.0
    seconds: float = 0.0


def _build(mesh_size, input_range, initial_state, symmetric) -> PreisachModel:
    return PreisachModel(
        PreisachMesh.triangular(mesh_size),
        input_range=input_range,
        initial_state=initial_state,
        symmetric=symmetric,
    )


def fit_magnet(
    current: Tensor,
    field: Tensor,
    *,
    mesh_size: int = 20,
    symmetric: bool | None = None,
    initial_state: str = "negative",
    input_range: Sequence[float] | None = None,
    steps: int = 300,
    smoothness: float = 0.0,
    validation_fraction: float = VALIDATION_FRACTION,
    callback: Callable[[int, float], None] | None = None,
) -> MagnetFit:
    """Fit a Preisach model and its predictive band to one training history.

    Args:
        current: Training inputs in time order [input units], shape ``(T,)``.
        field: Training outputs [output units], shape ``(T,)``.
        mesh_size: Cells per axis of the triangular mesh. The default (20)
            had the lowest error on validation rows held out of the training
            rows of the acceptance cases (``benchmarks/preisach_acceptance.py``:
            mean validation rms / straight line 0.41 vs 0.59 for 30 and 0.53
            for 44 cells).
        symmetric: Symmetric density; ``None``: :func:`symmetric_default` of
            the input range.
        initial_state: Magnet state before ``current[0]``.
        input_range: ``(lo, hi)`` [input units]; default
            :func:`default_input_range`. Must hold every training input.
        steps: L-BFGS iterations per fit.
        smoothness: Density roughness penalty (see :func:`fit_preisach`).
        validation_fraction: Share of the last training rows held out to
            choose ``symmetric`` and calibrate the band, in ``[0, 1)``.
        callback: ``callback(step, loss)`` of every fit, in turn.

    Returns:
        A :class:`MagnetFit`.

    Raises:
        ValueError: for bad series (see :func:`fit_preisach`), a ``mesh_size``
            beyond ``MAX_MESH_SIZE`` (the message gives the memory its band
            would need), an input range that misses training inputs, or too
            few rows to validate.
    """
    start = time.perf_counter()
    if not 0 <= validation_fraction < 1:  # also refuses NaN
        raise ValueError(
            f"validation_fraction must be in [0, 1); got {validation_fraction}."
        )
    u, y = check_series(current, field, torch.float64, None)
    rng = tuple(input_range) if input_range is not None else None
    if rng is None:
        rng = default_input_range(u, initial_state)
    # every check that can fail runs before the first fit
    if is_integer(mesh_size):
        check_mesh_size(int(mesh_size))
    _build(mesh_size, rng, initial_state, bool(symmetric)).check_input_range(
        u, "training inputs"
    )
    n_val = _held_out(u.numel(), validation_fraction)
    n_fit = u.numel() - n_val
    if n_fit < MIN_FIT_POINTS:
        raise ValueError(
            f"{u.numel()} training rows leave {n_fit} to fit after holding out "
            f"{n_val} for validation; need at least "
            f"{min_training_rows(validation_fraction)} rows."
        )
    if float(y[:n_fit].max() - y[:n_fit].min()) <= 0:
        raise ValueError("output is constant over the fitted rows; nothing to fit.")
    if float(u[:n_fit].max() - u[:n_fit].min()) <= 0:
        raise ValueError(
            f"input is constant ({float(u[0]):g}) over the fitted rows; a "
            "hysteresis fit needs the input to vary."
        )
    chosen = symmetric_default(rng) if symmetric is None else bool(symmetric)
    model = _build(mesh_size, rng, initial_state, chosen)
    fit_preisach(
        model, u[:n_fit], y[:n_fit], steps=steps, smoothness=smoothness,
        callback=callback,
    )  # fmt: skip
    with torch.no_grad():
        pred = model(u)
    validation = [
        {
            "symmetric": chosen,
            "val_rows": n_val,
            "val_rmse": float((pred[n_fit:] - y[n_fit:]).pow(2).mean().sqrt()),
        }
    ]
    # calibrate the band on the validation rows
    band = laplace_band(model, u[:n_fit], y[:n_fit])
    with torch.no_grad():
        std = band.std(model, u)[n_fit:]
    z = (pred[n_fit:] - y[n_fit:]) / std
    calibration = max(1.0, float(z.pow(2).mean().sqrt()))
    # final fit on all training rows
    model = _build(mesh_size, rng, initial_state, chosen)
    result = fit_preisach(
        model, u, y, steps=steps, smoothness=smoothness, callback=callback
    )
    band = laplace_band(model, u, y, calibration=calibration)
    return MagnetFit(
        model=model,
        band=band,
        result=result,
        symmetric=chosen,
        validation=validation,
        calibration=calibration,
        seconds=time.perf_counter() - start,
    )


def predict_stream(
    model: PreisachModel,
    chunks: Iterable[Tensor],
    band: LaplaceBand | None = None,
    initial_state: str | Tensor | None = None,
) -> Iterator[tuple[Tensor, Tensor | None]]:
    """Predictions along a long history, chunk by chunk, in bounded memory.

    Each chunk's exact hysteron state is carried into the next, so the result
    equals ``model(cat(chunks))`` (and ``band.std`` of it) whatever the chunk
    sizes, with memory set by the largest chunk.

    Args:
        model: A Preisach model.
        chunks: Consecutive input chunks [input units], each shape ``(T_c,)``.
        band: Predictive band of the model, or ``None`` (std not computed).
        initial_state: State before the first chunk; ``None`` is the model's own.

    Yields:
        ``(prediction, std)`` per chunk [output units], shapes ``(T_c,)``;
        ``std`` (float32 sums: relative round-off ~1e-6) is ``None`` without a
        band. Inputs beyond the range warn once
        per chunk (:class:`~diffaccel.hysteresis.InputRangeWarning`).
    """
    if band is not None:
        spec = band.stream_spec(model, initial_state)
    else:
        spec = model.stream_spec(initial_state)
    predictor = StreamPredictor(spec)  # the numpy streaming code, see stream.py
    dtype, device = model.alpha.dtype, model.alpha.device
    for chunk in chunks:
        u = torch.as_tensor(chunk).detach().reshape(-1)
        if u.numel() == 0:
            continue
        pred, std = predictor(u.to(device="cpu", dtype=torch.float64).numpy())
        pred = torch.as_tensor(pred, dtype=dtype, device=device)
        if std is not None:
            std = torch.as_tensor(std, dtype=dtype, device=device)
        yield pred, std


def rms(x: Tensor) -> float:
    """Root mean square of a tensor (``nan`` when empty)."""
    return float(x.pow(2).mean().sqrt()) if x.numel() else math.nan
