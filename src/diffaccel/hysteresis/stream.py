"""Long input histories through a fitted Preisach model, chunk by chunk (numpy only).

The streamed evaluation of a fitted model needs no gradients, so it is written
once, on numpy arrays: :class:`StreamPredictor` runs a :class:`StreamSpec` (the
frozen numbers of a model and its predictive band, made by
:func:`~diffaccel.hysteresis.predictive.stream_spec` or read from a fit folder)
over consecutive chunks, carrying the exact hysteron state from one chunk to the
next. ``PreisachModel`` training and ``predict_stream`` use the same functions
(``RowLayout`` is built by :func:`row_layout`; ``predict_stream`` and
``LaplaceBand.std`` run a :class:`StreamPredictor`), and ``diffaccel hysteresis
predict`` runs it without importing torch.

Exact relays as in :mod:`diffaccel.hysteresis.states`: at every step each row of
the mesh (hysterons of equal ``alpha``, sorted by ``beta``) is in one of
``2 (U + 1)`` situations for ``U`` distinct betas (reached in the chunk or not,
and how many of its beta levels are up), so any weighted sum of the states is a
lookup per row in a table (:class:`StreamTable`), summed over rows.

Inputs beyond the model's input range saturate (every hysteron switched) while
the linear term continues; they warn (:class:`InputRangeWarning`).
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, fields
from typing import NamedTuple

import numpy as np

__all__ = [
    "RANGE_TOL",
    "InputRangeWarning",
    "StreamPredictor",
    "StreamSpec",
    "StreamTable",
    "predict_chunks",
    "row_layout",
    "stream_codes",
    "stream_final_state",
    "warn_outside_range",
]

# tolerance on normalised inputs outside [0, 1] (round-off of the affine map)
RANGE_TOL = 1e-9


class InputRangeWarning(UserWarning):
    """Inputs beyond a model's input range, predicted as saturated."""


def warn_outside_range(
    u_min: float,
    u_max: float,
    below: float,
    above: float,
    input_range: tuple[float, float],
    stacklevel: int = 2,
) -> None:
    """Warn (:class:`InputRangeWarning`) if inputs lie beyond the input range.

    Args:
        u_min: Smallest input [input units].
        u_max: Largest input [input units].
        below: How far the smallest normalised input lies below 0 [1].
        above: How far the largest normalised input lies above 1 [1].
        input_range: ``(lo, hi)`` [input units].
        stacklevel: As for :func:`warnings.warn`, counted from the caller.
    """
    if below <= RANGE_TOL and above <= RANGE_TOL:
        return
    lo, hi = input_range
    far = max(below, above)
    warnings.warn(
        f"inputs reach {u_min:.6g} .. {u_max:.6g}, up to "
        f"{far * (hi - lo):.4g} ({100 * far:.3g} % of the range) outside the "
        f"model's input range [{lo:.6g}, {hi:.6g}]; predicted as saturated "
        "(every hysteron switched) plus the linear term.",
        InputRangeWarning,
        stacklevel=stacklevel + 1,
    )


class Rows(NamedTuple):
    """Hysterons grouped into rows of equal ``alpha``, sorted by ``beta``.

    ``beta_levels`` holds the sorted distinct betas and ``beta_rank[i]`` the
    position of ``beta[i]`` among them, so that ``beta[i] < x`` iff
    ``beta_rank[i] < searchsorted(beta_levels, x)``. ``below[r, j]`` counts the
    betas of row ``r`` among the ``j`` lowest levels.

    Shapes:
        ``row_alpha``: ``(R,)``; ``index``: ``(R, L)`` hysteron index, padded
        with ``M``; ``row``, ``beta_rank``: ``(M,)``; ``beta_levels``: ``(U,)``;
        ``below``: ``(R, U + 1)``.
    """

    row_alpha: np.ndarray
    beta_levels: np.ndarray
    beta_rank: np.ndarray
    index: np.ndarray
    row: np.ndarray
    below: np.ndarray


def row_layout(alpha: np.ndarray, beta: np.ndarray) -> Rows:
    """:class:`Rows` of hysterons with thresholds ``alpha``, ``beta`` [1], ``(M,)``."""
    alpha, beta = np.asarray(alpha), np.asarray(beta)
    m = alpha.size
    row_alpha, row = np.unique(alpha, return_inverse=True)
    beta_levels, beta_rank = np.unique(beta, return_inverse=True)
    row, beta_rank = row.reshape(-1), beta_rank.reshape(-1)
    order = np.lexsort((beta, row))  # by row, then beta, then index (stable)
    counts = np.bincount(row, minlength=row_alpha.size)
    starts = np.cumsum(counts) - counts
    col = np.empty(m, dtype=np.int64)
    col[order] = np.arange(m) - starts[row[order]]
    index = np.full((row_alpha.size, int(counts.max())), m, dtype=np.int64)
    index[row, col] = np.arange(m)
    hist = np.zeros((row_alpha.size, beta_levels.size), dtype=np.int64)
    np.add.at(hist, (row, beta_rank), 1)
    below = np.pad(np.cumsum(hist, axis=1), ((0, 0), (1, 0)))
    return Rows(row_alpha, beta_levels, beta_rank, index, row, below)


def stream_codes(un: np.ndarray, layout: Rows) -> np.ndarray:
    """Situation of every mesh row at every step of one chunk, as table indices.

    Row ``r``'s code is ``r W + U + 1 + c`` (``W = 2 U + 3``) with ``c`` in
    ``[1, U + 1]`` once its alpha was reached in the chunk (``U + 1 - c`` beta
    levels up: those below the minimum since the last reach) and ``c`` in
    ``[-U - 1, -1]`` before (the ``-c - 1`` levels below the chunk's running
    minimum keep their state, the others are down).

    One cumulative sum and one cumulative maximum over ``(R, T)`` integer
    keys: ``(segment - 1) (U + 2) + (U + 1 - rank)`` is negative until the
    row's alpha is first reached, and its running maximum minus the segment
    offset is ``c`` itself.

    Args:
        un: Normalised inputs [1] of one chunk, shape ``(T,)``, inside ``[0, 1]``.
        layout: :class:`Rows` of the hysterons.

    Returns:
        Codes, shape ``(R, T)``, int32 (int64 for chunks beyond ~2^31 / U rows).
    """
    n_levels = layout.beta_levels.size
    idx = np.int32 if (un.size + 1) * (n_levels + 2) < 2**31 - 1 else np.int64
    rank = np.searchsorted(layout.beta_levels, un, side="left")
    inv = (n_levels + 1 - rank).astype(idx)  # (T,) in [1, U + 1]
    up = un[None, :] >= layout.row_alpha[:, None]  # (R, T)
    seg = np.cumsum(up, axis=1, dtype=idx)  # reaches so far
    seg -= 1
    key = np.where(up, idx(1), inv[None, :])
    del up
    step = idx(n_levels + 2)
    key += seg * step
    code = np.maximum.accumulate(key, axis=1)
    del key
    np.maximum(seg, 0, out=seg)
    seg *= step
    code -= seg
    width = 2 * n_levels + 3
    base = np.arange(code.shape[0], dtype=idx) * idx(width) + idx(n_levels + 1)
    code += base[:, None]
    return code


class StreamTable:
    """Row sums of weighted states for every code of :func:`stream_codes`.

    ``table[code, k]`` for fixed weight vectors: the part for rows already
    reached depends on the weights only and is built once; the part for rows
    not yet reached depends on the states before the chunk and is refreshed by
    :meth:`update` (cheap: ``O(K M)``).

    Args:
        layout: :class:`Rows` of the hysterons.
        weights: Weight vectors, shape ``(K, M)``.
        dtype: dtype of the table (default: that of ``weights``).

    Shapes:
        :meth:`update` returns ``(R (2 U + 3), K)``.
    """

    def __init__(
        self, layout: Rows, weights: np.ndarray, dtype: np.dtype | None = None
    ) -> None:
        n_k = weights.shape[0]
        n_rows, n_levels = layout.below.shape[0], layout.below.shape[1] - 1
        self.layout = layout
        pad = np.zeros((n_k, 1), dtype=weights.dtype)
        self.w_pad = np.concatenate([weights, pad], axis=1)[:, layout.index]
        w_cum = _cumsum0(self.w_pad)  # (K, R, L + 1)
        w_row = w_cum[..., -1:]
        w_below = np.take_along_axis(w_cum, layout.below[None], axis=2)
        self.w_rest = w_below - w_row  # (K, R, U + 1)
        signed = 2.0 * w_below - w_row
        width = 2 * n_levels + 3
        self.table = np.zeros((n_rows, width, n_k), dtype=dtype or weights.dtype)
        self.table[:, n_levels + 2 :] = signed[..., ::-1].transpose(1, 2, 0)
        self.n_levels = n_levels

    def update(self, initial: np.ndarray) -> np.ndarray:
        """The table for a chunk that starts from states ``initial``, shape ``(M,)``."""
        init = np.append(initial.astype(self.w_pad.dtype), 0.0)[self.layout.index]
        s_cum = _cumsum0(self.w_pad * init)
        never = np.take_along_axis(s_cum, self.layout.below[None], axis=2)
        never += self.w_rest
        self.table[:, : self.n_levels + 1] = never[..., ::-1].transpose(1, 2, 0)
        return self.table.reshape(-1, self.table.shape[2])


def _cumsum0(x: np.ndarray) -> np.ndarray:
    """Cumulative sum along the last axis with a leading zero."""
    out = np.zeros((*x.shape[:-1], x.shape[-1] + 1), dtype=x.dtype)
    np.cumsum(x, axis=-1, out=out[..., 1:])
    return out


def stream_final_state(
    last: np.ndarray, layout: Rows, initial: np.ndarray
) -> np.ndarray:
    """Hysteron states after a chunk from its last codes.

    Args:
        last: Codes of the chunk's last step, ``stream_codes(...)[:, -1]``,
            shape ``(R,)``.
        layout: :class:`Rows` of the hysterons.
        initial: States before the chunk, shape ``(M,)``.

    Returns:
        States in ``[-1, 1]``, shape ``(M,)``, dtype of ``initial``.
    """
    n_levels = layout.beta_levels.size
    width = 2 * n_levels + 3
    rows = np.arange(last.size)
    c = (last.astype(np.int64) - n_levels - 1 - width * rows)[layout.row]
    q = layout.beta_rank
    up_after = np.where(q < n_levels + 1 - c, 1.0, -1.0)  # reached
    stays = np.where(q < -c - 1, initial, -1.0)  # never reached
    return np.where(c > 0, up_after, stays).astype(initial.dtype)


def _row_sums(code: np.ndarray, table: np.ndarray) -> np.ndarray:
    """``sum_r table[code[r, t], :]``, shape ``(T, K)``, summed in the table's dtype.

    A sparse product: one row of ``R`` ones per step (rows summed in order).
    """
    from scipy.sparse import csr_array  # ~0.1 s; only streamed bands need it

    n_rows, t = code.shape
    ones = np.ones(code.size, dtype=table.dtype)
    indptr = np.arange(0, code.size + 1, n_rows, dtype=code.dtype)
    pick = csr_array((ones, code.T.ravel(), indptr), shape=(t, table.shape[0]))
    return pick @ table


_ARRAYS = (
    "alpha",
    "beta",
    "weights",
    "initial",
    "band_affine",
    "band_weights",
)


@dataclass(frozen=True)
class StreamSpec:
    """The numbers of a fitted Preisach model (and band) that streaming needs.

    The output is ``output_loc + output_scale * (offset + slope u_n + scale m)``
    with ``u_n = (u - lo) / (hi - lo)`` and ``m = sum_i weights_i s_i`` (weights
    normalised to sum 1); the band's standard deviation is
    ``output_scale * calibration * sqrt(|a_0 + a_1 clip(u_n) + sum_i W_i s_i|^2 +
    noise_std^2)`` over its ``K`` directions (see
    :class:`~diffaccel.hysteresis.LaplaceBand`).

    Attributes:
        input_range: ``(lo, hi)`` [input units].
        alpha: Up thresholds [1], shape ``(M,)``.
        beta: Down thresholds [1], shape ``(M,)``.
        weights: Normalised hysteron weights, shape ``(M,)``.
        initial: States before the first input, shape ``(M,)``.
        offset: Normalised output offset.
        slope: Normalised output per normalised input.
        scale: Normalised output per unit magnetization.
        output_loc: Output location [output units].
        output_scale: Output scale [output units].
        band_affine: Band's affine part ``(a_0, a_1)`` per direction, shape
            ``(K, 2)``, or ``None`` (no band).
        band_weights: Band's hysteron weights ``W``, shape ``(K, M)``, or ``None``.
        noise_std: Band's measurement noise [normalised output].
        calibration: Band's calibration factor.
    """

    input_range: tuple[float, float]
    alpha: np.ndarray
    beta: np.ndarray
    weights: np.ndarray
    initial: np.ndarray
    offset: float
    slope: float
    scale: float
    output_loc: float
    output_scale: float
    band_affine: np.ndarray | None = None
    band_weights: np.ndarray | None = None
    noise_std: float = 0.0
    calibration: float = 1.0

    def __post_init__(self) -> None:
        m = np.shape(self.alpha)
        if len(m) != 1 or m[0] < 1:
            raise ValueError(f"alpha needs shape (M,); got {m}.")
        for name in ("beta", "weights", "initial"):
            if np.shape(getattr(self, name)) != m:
                raise ValueError(
                    f"{name} has shape {np.shape(getattr(self, name))}; alpha {m}."
                )
        if (self.band_affine is None) != (self.band_weights is None):
            raise ValueError("band_affine and band_weights go together.")
        if self.band_weights is not None:
            k = np.shape(self.band_weights)[0]
            if np.shape(self.band_weights) != (k, m[0]) or np.shape(
                self.band_affine
            ) != (k, 2):
                raise ValueError(
                    f"band shapes {np.shape(self.band_affine)}, "
                    f"{np.shape(self.band_weights)}; expected (K, 2), (K, {m[0]})."
                )
        lo, hi = self.input_range
        values = [lo, hi, self.offset, self.slope, self.scale]
        values += [self.output_loc, self.output_scale, self.noise_std, self.calibration]
        arrays = [getattr(self, n) for n in _ARRAYS if getattr(self, n) is not None]
        finite = all(np.isfinite(a).all() for a in arrays)
        if not (np.isfinite(values).all() and finite):
            raise ValueError("non-finite model numbers.")
        if not hi > lo:
            raise ValueError(f"input range needs lo < hi; got ({lo}, {hi}).")

    @property
    def has_band(self) -> bool:
        """Whether the spec holds a predictive band."""
        return self.band_weights is not None

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Named float64 arrays (for ``numpy.savez``); :meth:`from_arrays` inverts."""
        out = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if value is not None:
                out[f.name] = np.asarray(value, dtype=np.float64)
        return out

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> StreamSpec:
        """Rebuild from :meth:`to_arrays` (e.g. read back with ``numpy.load``).

        Raises:
            ValueError: for missing, extra or misshaped entries.
        """
        names = {f.name for f in fields(cls)}
        extra = set(arrays) - names
        if extra:
            raise ValueError(f"unknown entries {sorted(extra)}.")
        kw = {}
        for name in names & set(arrays):
            a = np.asarray(arrays[name])
            if a.dtype.kind != "f":
                raise ValueError(f"entry {name!r} is not floating point.")
            if name == "input_range":
                if a.shape != (2,):
                    raise ValueError(f"input_range has shape {a.shape}; expected (2,).")
                kw[name] = (float(a[0]), float(a[1]))
            elif name in _ARRAYS:
                kw[name] = a.astype(np.float64)
            else:
                if a.shape != ():
                    raise ValueError(f"entry {name!r} must be a scalar.")
                kw[name] = float(a)
        try:
            return cls(**kw)
        except TypeError as err:  # a required entry is missing
            raise ValueError(f"incomplete stream spec ({err}).") from None


class StreamPredictor:
    """Predictions of a :class:`StreamSpec` along one long history, chunk by chunk.

    Each call continues from the exact hysteron state left by the previous one,
    so the result equals that of the whole history at once whatever the chunk
    sizes; memory is set by the largest chunk (about ``R`` int32 codes per row).

    Args:
        spec: The model's numbers.
        band_dtype: dtype of the band's sums: ``float32`` (fast; relative
            round-off ~1e-7 of the terms, meant for standard deviations) or
            ``float64``.

    Example:
        >>> spec = StreamSpec((0.0, 1.0), np.array([0.5]), np.array([0.25]),
        ...     np.array([1.0]), np.array([-1.0]), 0.0, 0.0, 1.0, 0.0, 1.0)
        >>> p = StreamPredictor(spec)
        >>> p(np.array([0.6, 0.3]))[0].tolist(), p(np.array([0.2]))[0].tolist()
        ([1.0, 1.0], [-1.0])
    """

    def __init__(self, spec: StreamSpec, band_dtype: type = np.float32) -> None:
        self.spec = spec
        self.layout = row_layout(spec.alpha, spec.beta)
        self.state = np.asarray(spec.initial, dtype=np.float64).copy()
        self._mean = StreamTable(self.layout, spec.weights[None, :])
        self._band = None
        if spec.has_band:
            self._band = StreamTable(self.layout, spec.band_weights, dtype=band_dtype)

    def normalize(self, u: np.ndarray, stacklevel: int = 2) -> np.ndarray:
        """Normalised inputs [1] of ``u`` [input units] (unclipped), checked.

        Raises:
            ValueError: for NaN or infinite inputs.
        """
        lo, hi = self.spec.input_range
        un = (u - lo) / (hi - lo)
        un_min, un_max = float(un.min()), float(un.max())
        if not (np.isfinite(un_min) and np.isfinite(un_max)):
            raise ValueError("inputs contain NaN or infinite values.")
        below, above = -un_min, un_max - 1.0
        if below > RANGE_TOL or above > RANGE_TOL:
            warn_outside_range(
                float(u.min()), float(u.max()), below, above, (lo, hi), stacklevel + 1
            )
        return un

    def __call__(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Predict one chunk and carry the state on.

        Args:
            u: Inputs [input units], shape ``(T,)``, ``T >= 1``.

        Returns:
            ``(prediction, std)`` [output units], shapes ``(T,)``; ``std`` is
            ``None`` without a band. Inputs beyond the range warn.
        """
        s = self.spec
        u = np.asarray(u, dtype=np.float64).reshape(-1)
        un = self.normalize(u)
        un_c = np.clip(un, 0.0, 1.0)  # saturation beyond the range
        code = stream_codes(un_c, self.layout)
        mean_tab = self._mean.update(self.state)[:, 0]
        sums = mean_tab[code].sum(axis=0)
        y = s.offset + s.slope * un + s.scale * sums
        pred = s.output_loc + s.output_scale * y
        std = None
        if self._band is not None:
            tab = self._band.update(self.state)
            proj = _row_sums(code, tab)  # (T, K) in the table's dtype
            a = s.band_affine.astype(tab.dtype)
            proj += a[:, 0]
            proj += un_c.astype(tab.dtype)[:, None] * a[:, 1]
            # the norm accumulated in float64, rounded to the sums' dtype
            norm2 = np.einsum("tk,tk->t", proj, proj, dtype=np.float64)
            norm = np.sqrt(norm2).astype(tab.dtype).astype(np.float64)
            std = s.output_scale * (s.calibration * np.sqrt(norm**2 + s.noise_std**2))
        self.state = stream_final_state(code[:, -1], self.layout, self.state)
        return pred, std


def predict_chunks(
    spec: StreamSpec, chunks: Iterable[np.ndarray], band_dtype: type = np.float32
) -> Iterator[tuple[np.ndarray, np.ndarray | None]]:
    """:class:`StreamPredictor` over consecutive chunks (empty ones skipped).

    Yields:
        ``(prediction, std or None)`` per non-empty chunk [output units].
    """
    predictor = StreamPredictor(spec, band_dtype)
    for chunk in chunks:
        if np.size(chunk):
            yield predictor(chunk)
