"""Fit a magnet's Preisach model with a predictive band; stream long predictions.

:func:`fit_magnet` is the front door used by the CLI, the benchmarks and the
acceptance tests. Choices that cannot be read from physics are made by
validation on the training rows only: the last ``validation_fraction`` of the
training rows is held out, the candidates (symmetric density or not) are
fitted on the rest and scored on them, and the validation residuals calibrate
the predictive band. The chosen model is then refitted on all training rows.
Whether the density is symmetric follows the physics of the training rows
(:func:`symmetric_default`, :func:`changes_sign`) unless the caller says.

The mesh is regular in a warped input (:func:`adaptive_warp`) that places a
share of its thresholds where the training output changes, so that a coercive
field far below the input range (soft iron: ``1e-3`` of it) spans many cells;
the share is chosen from :data:`MESH_ADAPT_CANDIDATES` on validation rows held
out *inside* the training history, every fourth row, which score how well
each mesh interpolates where the data switch (see ``docs/methods/preisach_fit.md``).
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor

from diffaccel.dynamics import is_integer
from diffaccel.hysteresis.band import BandFallbackWarning, LaplaceBand, laplace_band
from diffaccel.hysteresis.fit import (
    MIN_FIT_POINTS,
    FitResult,
    check_series,
    fit_preisach,
)
from diffaccel.hysteresis.mesh import PreisachMesh, Warp
from diffaccel.hysteresis.preisach import PreisachModel
from diffaccel.hysteresis.stream import StreamPredictor

__all__ = [
    "MAX_MESH_SIZE",
    "MESH_ADAPT_CANDIDATES",
    "RANGE_MARGIN",
    "MagnetFit",
    "adaptive_warp",
    "band_memory_bytes",
    "changes_sign",
    "check_mesh_size",
    "default_input_range",
    "fit_magnet",
    "min_training_rows",
    "parse_mesh_adapt",
    "predict_stream",
    "symmetric_default",
]

# margin added to the training input range so that nearby inputs stay inside
RANGE_MARGIN = 0.01
# rows held out of the training rows for validation (at least 2)
VALIDATION_FRACTION = 0.25
#: Shares of the mesh placed where the training output changes
#: (:func:`adaptive_warp`) tried by :func:`fit_magnet`; 0 is the regular mesh.
MESH_ADAPT_CANDIDATES = (0.0, 0.8, 0.95)
# knots of an adaptive warp (at most) and their least spacing [1]
_MAX_KNOTS = 512
_KNOT_GAP = 1e-9
# every this many training rows, one is held out to choose the mesh warp
_INTERLEAVE = 4
# a warp replaces the regular mesh only if its validation rms is below this
# fraction of the regular mesh's (the regular mesh wins near-ties)
_WARP_GAIN = 0.9
# an output changes sign when it reaches this share of max|output| on both sides
_SIGN_CHANGE = 0.05
# share of validation rows the calibrated band holds within 2 std (at least)
_COVER = 0.9
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


def parse_mesh_adapt(text: str) -> float | str:
    """The ``mesh_adapt`` of :func:`fit_magnet` from text: ``"auto"`` or a share.

    Raises:
        ValueError: unless ``"auto"`` or a number in ``[0, 1)``.
    """
    if text == "auto":
        return text
    try:
        share = float(text)
    except ValueError:
        share = math.nan
    if not 0.0 <= share < 1.0:
        raise ValueError(f"expected 'auto' or a number in [0, 1); got {text!r}.")
    return share


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


def changes_sign(current: Tensor, field: Tensor) -> bool:
    """Whether training inputs and outputs both change sign (symmetric physics).

    A soft magnetic material or a bipolar magnet has ``mu(alpha, beta) =
    mu(-beta, -alpha)`` about zero input; its training rows show it when the
    output takes both signs by more than 5 % of ``max|output|`` (more than
    the remanent field and noise of a unipolar magnet near zero current) and
    the input reaches both sides of zero, where an input within
    ``RANGE_MARGIN`` of ``max|input|`` of zero counts as reaching it (a B-H
    branch that starts at remanence, ``H = 0``).

    Args:
        current: Training inputs [input units], shape ``(T,)``.
        field: Training outputs [output units], shape ``(T,)``.
    """
    u = torch.as_tensor(current, dtype=torch.float64)
    y = torch.as_tensor(field, dtype=torch.float64)
    if u.numel() == 0 or y.numel() == 0:
        return False
    tol = RANGE_MARGIN * float(u.abs().max())
    return (
        float(u.min()) <= tol
        and float(u.max()) >= -tol
        and float(y.min()) < -_SIGN_CHANGE * float(y.abs().max())
        and float(y.max()) > _SIGN_CHANGE * float(y.abs().max())
    )


def default_input_range(
    current: Tensor, initial_state: str = "negative", centred: bool = False
) -> tuple[float, float]:
    """Model input range from training inputs [input units].

    The training span plus ``RANGE_MARGIN`` of it on both sides. A magnet that
    starts ``"demagnetized"`` was demagnetized about zero input, which is then
    the centre of its Preisach plane: the range is symmetric about 0,
    ``+-(1 + RANGE_MARGIN) max|u|``; so is the range of a symmetric density
    (``centred``), whose symmetry holds about zero input.

    Args:
        current: Training inputs [input units], shape ``(T,)``, finite.
        initial_state: The model's initial state kind.
        centred: Centre the range on zero input.

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
    if initial_state == "demagnetized" or centred:
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
        mesh_adapt: Share of the mesh placed where the training output
            changes (:func:`adaptive_warp`); 0 for the regular mesh.
        mesh_validation: ``[{"mesh_adapt", "val_rows", "val_rmse"}]``: rms
            [output units] of each candidate mesh on the interleaved
            validation rows (empty when the mesh was given).
        band_fallback: Why the band (of the validation fit or the final one)
            is not the plain Laplace band; ``None`` when it is.
    """

    model: PreisachModel
    band: LaplaceBand
    result: FitResult
    symmetric: bool
    validation: list[dict] = field(default_factory=list)
    calibration: float = 1.0
    seconds: float = 0.0
    mesh_adapt: float = 0.0
    mesh_validation: list[dict] = field(default_factory=list)
    band_fallback: str | None = None


def adaptive_warp(
    un: Tensor, field: Tensor, share: float, symmetric: bool = False
) -> Warp:
    """Mesh warp that gives ``share`` of the mesh to where the training output changes.

    ``t(u) = share * C(u) + (1 - share) * u`` with ``C`` the cumulative
    output change along the input: each step ``k`` of the training history
    adds ``|y_k - y_(k-1)|``, spread evenly over the inputs between ``u_(k-1)``
    and ``u_k``, normalised to ``C(1) = 1``. A mesh regular in ``t`` then has
    its thresholds dense where the output switches (for soft iron, near the
    coercive field) and the rest spread evenly. For a symmetric density the
    change is mirrored, ``C(u) -> (C(u) + 1 - C(1 - u)) / 2``, so the mesh stays
    mirror symmetric.

    Args:
        un: Normalised training inputs [1], shape ``(T,)`` (clipped to [0, 1]).
        field: Training outputs [output units], shape ``(T,)``.
        share: Share of the mesh placed by the output change, in ``[0, 1)``.
        symmetric: Mirror the change about ``u = 0.5``.

    Returns:
        Knots ``(u, t)`` for :func:`~diffaccel.hysteresis.mesh.warp_input`
        (at most ``_MAX_KNOTS`` of them).
    """
    import numpy as np

    x = np.clip(torch.as_tensor(un).detach().cpu().double().numpy(), 0.0, 1.0)
    y = torch.as_tensor(field).detach().cpu().double().numpy()
    lo, hi = np.minimum(x[:-1], x[1:]), np.maximum(x[:-1], x[1:])
    mass = np.abs(np.diff(y))
    keep = (hi > lo) & (mass > 0)
    lo, hi, mass = lo[keep], hi[keep], mass[keep]
    top = 0.5 if symmetric else 1.0
    knots = np.unique(
        np.concatenate([[0.0, top], np.minimum(x, 1.0 - x) if symmetric else x])
    )
    knots = knots[knots <= top]
    if knots.size > _MAX_KNOTS:
        knots = np.unique(
            np.concatenate(
                [[0.0, top], np.quantile(knots, np.linspace(0, 1, _MAX_KNOTS))]
            )
        )
    knots = knots[np.concatenate([[True], np.diff(knots) > _KNOT_GAP])]
    knots[-1] = top

    def cdf(z: np.ndarray) -> np.ndarray:
        if mass.size == 0:
            return z
        frac = np.clip((z[:, None] - lo[None, :]) / (hi - lo)[None, :], 0.0, 1.0)
        return (frac * mass[None, :]).sum(1) / mass.sum()

    c = cdf(knots)
    if symmetric:  # on [0, 0.5]; the upper half is its mirror image
        c = 0.5 * (c + 1.0 - cdf(1.0 - knots))
    t = share * c + (1.0 - share) * knots
    t[0] = 0.0
    if symmetric:
        t[-1] = 0.5
        knots = np.concatenate([knots, 1.0 - knots[-2::-1]])
        t = np.concatenate([t, 1.0 - t[-2::-1]])
    t[-1] = 1.0
    return (tuple(knots.tolist()), tuple(t.tolist()))


def _build(
    mesh_size, input_range, initial_state, symmetric, warp=None, odd=None
) -> PreisachModel:
    lo, hi = (float(v) for v in input_range)
    return PreisachModel(
        PreisachMesh.triangular(mesh_size, warp=warp),
        input_range=input_range,
        initial_state=initial_state,
        symmetric=symmetric,
        mesh_warp=warp,
        odd=bool(symmetric) and lo + hi == 0.0 if odd is None else bool(odd),
    )


def _band(model, u, y, notes: list[str], what: str, calibration: float = 1.0):
    """:func:`laplace_band`, its fallback recorded in ``notes`` (not warned)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", BandFallbackWarning)
        band = laplace_band(model, u, y, calibration=calibration)
    if band.fallback is not None:
        notes.append(f"{what}: {band.fallback}")
    return band


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
    mesh_adapt: float | str = "auto",
    odd: bool | None = None,
) -> MagnetFit:
    """Fit a Preisach model and its predictive band to one training history.

    Steps: (1) symmetry and input range from the training rows; (2) the mesh:
    a mesh with each share of :data:`MESH_ADAPT_CANDIDATES` placed where the
    training output changes (:func:`adaptive_warp`) is fitted to the training
    rows with every fourth row left out of the objective (the history stays
    whole; half the L-BFGS iterations) and scored by its rms on those rows;
    the lowest wins, an adaptive mesh only if it beats the regular one by
    10 %; (3) the chosen model is fitted to the first ``1 -
    validation_fraction`` of the rows, scored on the rest, and those residuals
    calibrate the band (the factor makes the band hold the validation
    residuals: at least the rms of ``residual / std`` and at least half the
    90th percentile of ``|residual| / std``); (4) the final fit on all
    training rows and its band, with the validation rms added in quadrature
    as a model-discrepancy term (the training rows' noise understates the
    error of a forecast: on the SLAC quadrupole the held-out rows' error is
    about twice the validation rows'): ``std^2 = calibration^2 (parameter
    variance + noise^2) + val_rmse^2``. The band never aborts the fit
    (:func:`~diffaccel.hysteresis.band.laplace_band` falls back instead); a
    fallback raises one :class:`~diffaccel.hysteresis.band.BandFallbackWarning`
    and is named in ``band_fallback``.

    Args:
        current: Training inputs in time order [input units], shape ``(T,)``.
        field: Training outputs [output units], shape ``(T,)``.
        mesh_size: Cells per axis of the triangular mesh. The default (20)
            had the lowest error on validation rows held out of the training
            rows of the acceptance cases (``benchmarks/preisach_acceptance.py``:
            mean validation rms / straight line 0.41 vs 0.59 for 30 and 0.53
            for 44 cells).
        symmetric: Symmetric density; ``None``: symmetric when
            :func:`symmetric_default` of the input range says so or the
            training inputs and outputs both change sign (:func:`changes_sign`).
            A symmetric density gets an input range centred on zero by
            default.
        initial_state: Magnet state before ``current[0]``.
        input_range: ``(lo, hi)`` [input units]; default
            :func:`default_input_range` (centred on zero for a symmetric
            density). Must hold every training input.
        steps: L-BFGS iterations per fit.
        smoothness: Density roughness penalty (see :func:`fit_preisach`).
        validation_fraction: Share of the last training rows held out to
            calibrate the band, in ``[0, 1)``.
        callback: ``callback(step, loss)`` of every fit, in turn.
        mesh_adapt: Share of the mesh in ``[0, 1)`` placed where the training
            output changes (0: regular mesh), or ``"auto"`` (default) to
            choose on validation rows as above.
        odd: Odd output about zero input (:class:`PreisachModel` ``odd``:
            no fitted offset); ``None`` (default): odd when the density is
            symmetric and the input range centred on zero. ``True`` needs both.

    Returns:
        A :class:`MagnetFit`.

    Raises:
        ValueError: for bad series (see :func:`fit_preisach`), a ``mesh_size``
            beyond ``MAX_MESH_SIZE`` (the message gives the memory its band
            would need), an input range that misses training inputs, a
            ``mesh_adapt`` outside ``[0, 1)``, or too few rows to validate.
    """
    start = time.perf_counter()
    if not 0 <= validation_fraction < 1:  # also refuses NaN
        raise ValueError(
            f"validation_fraction must be in [0, 1); got {validation_fraction}."
        )
    auto = isinstance(mesh_adapt, str)
    if auto and mesh_adapt != "auto":
        raise ValueError(f"mesh_adapt must be a number or 'auto'; got {mesh_adapt!r}.")
    if not auto:
        mesh_adapt = float(mesh_adapt)
        if not 0.0 <= mesh_adapt < 1.0:  # also refuses NaN
            raise ValueError(f"mesh_adapt must be in [0, 1); got {mesh_adapt}.")
    u, y = check_series(current, field, torch.float64, None)
    rng = tuple(input_range) if input_range is not None else None
    plain = default_input_range(u, initial_state)
    if symmetric is None:
        chosen = symmetric_default(rng if rng is not None else plain) or changes_sign(
            u, y
        )
    else:
        chosen = bool(symmetric)
    if rng is None:
        rng = default_input_range(u, initial_state, centred=chosen)
    if odd and not (chosen and float(rng[0]) + float(rng[1]) == 0.0):
        raise ValueError(
            "odd=True needs a symmetric density and an input range centred on 0; "
            f"got symmetric={chosen}, input_range {list(rng)}."
        )
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
    un = (u - rng[0]) / (rng[1] - rng[0])

    def warp_of(share: float) -> Warp | None:
        return adaptive_warp(un, y, share, chosen) if share > 0 else None

    mesh_validation: list[dict] = []
    if auto:
        held = torch.arange(u.numel()) % _INTERLEAVE == _INTERLEAVE - 1
        scores = []
        for share in MESH_ADAPT_CANDIDATES:
            model = _build(mesh_size, rng, initial_state, chosen, warp_of(share), odd)
            fit_preisach(
                model, u, y, steps=max(1, steps // 2), smoothness=smoothness,
                callback=callback, loss_rows=~held,
            )  # fmt: skip
            with torch.no_grad():
                err = (model(u) - y)[held]
            val = float(err.pow(2).mean().sqrt())
            scores.append((val, share))
            mesh_validation.append(
                {"mesh_adapt": share, "val_rows": int(held.sum()), "val_rmse": val}
            )
        regular = scores[0][0]
        best = min(scores[1:], key=lambda sc: sc[0])
        mesh_adapt = best[1] if best[0] < _WARP_GAIN * regular else 0.0
    warp = warp_of(mesh_adapt)
    notes: list[str] = []
    model = _build(mesh_size, rng, initial_state, chosen, warp, odd)
    fit_preisach(
        model, u[:n_fit], y[:n_fit], steps=steps, smoothness=smoothness,
        callback=callback,
    )  # fmt: skip
    with torch.no_grad():
        pred = model(u)
    validation = [
        {
            "symmetric": chosen,
            "mesh_adapt": mesh_adapt,
            "val_rows": n_val,
            "val_rmse": float((pred[n_fit:] - y[n_fit:]).pow(2).mean().sqrt()),
        }
    ]
    # calibrate the band on the validation rows
    band = _band(model, u[:n_fit], y[:n_fit], notes, "validation fit")
    with torch.no_grad():
        std = band.std(model, u)[n_fit:]
    z = ((pred[n_fit:] - y[n_fit:]) / std).abs()
    calibration = max(
        1.0,
        float(z.pow(2).mean().sqrt()),
        0.5 * float(torch.quantile(z, _COVER)),
    )
    # final fit on all training rows
    model = _build(mesh_size, rng, initial_state, chosen, warp, odd)
    result = fit_preisach(
        model, u, y, steps=steps, smoothness=smoothness, callback=callback
    )
    band = _band(model, u, y, notes, "final fit", calibration=calibration)
    # model discrepancy: the validation rms, added in quadrature to the band
    # (std^2 = calibration^2 (parameter variance + noise^2) + discrepancy^2)
    discrepancy = validation[0]["val_rmse"] / float(model.output_scale)
    fallback_note = band.fallback
    noise = math.sqrt(float(band.noise_std) ** 2 + (discrepancy / calibration) ** 2)
    band = LaplaceBand(band.directions, noise, calibration=calibration)
    band.fallback = fallback_note
    fallback = "; ".join(notes) if notes else None
    if fallback is not None:
        warnings.warn(fallback + ".", BandFallbackWarning, stacklevel=2)
    return MagnetFit(
        model=model,
        band=band,
        result=result,
        symmetric=chosen,
        validation=validation,
        calibration=calibration,
        seconds=time.perf_counter() - start,
        mesh_adapt=mesh_adapt,
        mesh_validation=mesh_validation,
        band_fallback=fallback,
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
