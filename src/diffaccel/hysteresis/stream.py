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
``2 (U + 1)`` situations for ``U`` distinct betas (reached or not, and how many
of its beta levels are up), coded by :func:`stream_codes` (a chunk continues
from the codes of the previous one), so any weighted sum of the states is a
lookup per row in a table built once (:func:`stream_table`), summed over rows;
:class:`RowGroups` merges rows into fewer, larger tables.

Inputs beyond the model's input range saturate (every hysteron switched) while
the linear term continues; they warn (:class:`InputRangeWarning`), and
:func:`outside_input_range` tells which they are. There the band's standard
deviation is that of the same linear model, so it widens with the uncertainty
of the slope (and offset); the assumption that no hysteron lies beyond the
range is the model's, and no part of the band.
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
    "RowGroups",
    "StreamPredictor",
    "StreamSpec",
    "outside_input_range",
    "permute_rows",
    "predict_chunks",
    "row_layout",
    "start_codes",
    "stream_codes",
    "stream_final_state",
    "stream_table",
    "warn_outside_range",
]

# tolerance on normalised inputs outside [0, 1] (round-off of the affine map)
RANGE_TOL = 1e-9


class InputRangeWarning(UserWarning):
    """Inputs beyond a model's input range, predicted as saturated."""


def outside_input_range(u: np.ndarray, input_range: tuple[float, float]) -> np.ndarray:
    """Which inputs lie beyond the input range (as :class:`InputRangeWarning` counts).

    Args:
        u: Inputs [input units], shape ``(T,)``.
        input_range: ``(lo, hi)`` [input units].

    Returns:
        Boolean, shape ``(T,)``: ``True`` where ``u`` lies more than
        ``RANGE_TOL`` of the range's width below ``lo`` or above ``hi``.

    Example:
        >>> outside_input_range(np.array([-1.0, 0.0, 5.0, 10.0, 10.5]), (0.0, 10.0))
        array([ True, False, False, False,  True])
    """
    lo, hi = input_range
    un = (np.asarray(u, dtype=np.float64) - lo) / (hi - lo)
    return (un < -RANGE_TOL) | (un > 1.0 + RANGE_TOL)


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


def permute_rows(layout: Rows, order: np.ndarray) -> Rows:
    """The same hysterons with the mesh rows in ``order`` (``(R,)``, a permutation)."""
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    return layout._replace(
        row_alpha=layout.row_alpha[order],
        index=layout.index[order],
        below=layout.below[order],
        row=rank[layout.row],
    )


def start_codes(layout: Rows) -> np.ndarray:
    """Codes (:func:`stream_codes`) before the first input: nothing reached yet,
    every hysteron in its initial state, shape ``(R,)``."""
    return _code_base(layout) - (layout.beta_levels.size + 1)


def stream_codes(
    un: np.ndarray, layout: Rows, last: np.ndarray | None = None
) -> np.ndarray:
    """Situation of every mesh row at every step of one chunk, as table indices.

    Row ``r``'s code is ``r W + U + 1 + c`` (``W = 2 U + 3``) with ``c`` in
    ``[1, U + 1]`` once its alpha was reached (``U + 1 - c`` beta levels up:
    those below the minimum input since the last reach) and ``c`` in
    ``[-U - 1, -1]`` before (the ``-c - 1`` levels below the running minimum
    since the start of the history keep their initial state, the others are
    down). The chunk continues from ``last``, the codes of the previous chunk's
    last step, so codes (and their tables, :func:`stream_table`) mean the same
    in every chunk: the codes carry the hysteron state
    (:func:`stream_final_state`).

    One cumulative sum and one cumulative maximum over ``(R, T)`` integer keys:
    ``(segment - 1) (U + 2) + (U + 1 - rank)`` is negative until the row's
    alpha is first reached, and its running maximum minus the segment offset
    is ``c`` itself.

    Args:
        un: Normalised inputs [1] of one chunk, shape ``(T,)``, inside ``[0, 1]``.
        layout: :class:`Rows` of the hysterons.
        last: Codes of the previous step, shape ``(R,)``; ``None`` is the
            start of the history (:func:`start_codes`).

    Returns:
        Codes, shape ``(R, T)``, int32 (int64 for chunks beyond ~2^31 / U rows).
    """
    n_levels = layout.beta_levels.size
    last = start_codes(layout) if last is None else last
    base = _code_base(layout)
    never = last.astype(np.int64) < base  # c < 0: not reached before the chunk
    idx = np.int32 if (un.size + 1) * (n_levels + 2) < 2**31 - 1 else np.int64
    step = idx(n_levels + 2)
    rank = np.searchsorted(layout.beta_levels, un, side="left")
    inv = (n_levels + 1 - rank).astype(idx)  # (T,) in [1, U + 1]
    up = un[None, :] >= layout.row_alpha[:, None]  # (R, T)
    offset = np.cumsum(up, axis=1, dtype=idx)  # reaches in the chunk
    offset *= step
    key = np.where(up, idx(1), inv[None, :])
    del up
    # keys of rows never reached are one segment (step) higher than in the
    # docstring above, so that the chunk's reaches alone set the offset
    key += offset
    # the carried situation is the running maximum before the first step
    first = (last.astype(np.int64) - base + never * int(step)).astype(idx)
    np.maximum(key[:, 0], first, out=key[:, 0])
    np.maximum.accumulate(key, axis=1, out=key)
    # code = key - max(segment, 0) step + base, segment = reaches - never
    np.maximum(offset, (never * step).astype(idx)[:, None], out=offset)
    offset -= base.astype(idx)[:, None]
    key -= offset
    return key


def _code_base(layout: Rows, dtype: type = np.int64) -> np.ndarray:
    """``r W + U + 1`` per row: code minus ``c``, shape ``(R,)``."""
    n_levels = layout.beta_levels.size
    width = 2 * n_levels + 3
    base = np.arange(layout.row_alpha.size, dtype=dtype) * dtype(width)
    return base + dtype(n_levels + 1)


def stream_table(
    layout: Rows, weights: np.ndarray, initial: np.ndarray, dtype: type | None = None
) -> np.ndarray:
    """Row sums of weighted states for every code of :func:`stream_codes`.

    Args:
        layout: :class:`Rows` of the hysterons.
        weights: Weight vectors, shape ``(K, M)``.
        initial: States before the history, shape ``(M,)``.
        dtype: dtype of the table (default: that of ``weights``); the entries
            are computed in the dtype of ``weights``.

    Returns:
        ``table[code, k] = sum_{i in row} weights_ki s_i``, shape
        ``(R (2 U + 3), K)``.
    """
    n_k = weights.shape[0]
    n_rows, n_levels = layout.below.shape[0], layout.below.shape[1] - 1
    pad = np.zeros((n_k, 1), dtype=weights.dtype)
    w_pad = np.concatenate([weights, pad], axis=1)[:, layout.index]  # (K, R, L)
    below = layout.below[None]
    w_cum = _cumsum0(w_pad)  # (K, R, L + 1)
    w_row = w_cum[..., -1:]
    w_below = np.take_along_axis(w_cum, below, axis=2)  # (K, R, U + 1)
    signed = 2.0 * w_below - w_row  # reached: levels below j up, the rest down
    init = np.append(initial.astype(weights.dtype), 0.0)[layout.index]  # (R, L)
    s_cum = _cumsum0(w_pad * init)
    # never reached: levels below k keep their initial state, the rest down
    never = np.take_along_axis(s_cum, below, axis=2) + w_below - w_row
    width = 2 * n_levels + 3
    table = np.zeros((n_rows, width, n_k), dtype=dtype or weights.dtype)
    table[:, : n_levels + 1] = never[..., ::-1].transpose(1, 2, 0)
    table[:, n_levels + 2 :] = signed[..., ::-1].transpose(1, 2, 0)
    return table.reshape(-1, n_k)


def _cumsum0(x: np.ndarray) -> np.ndarray:
    """Cumulative sum along the last axis with a leading zero."""
    out = np.zeros((*x.shape[:-1], x.shape[-1] + 1), dtype=x.dtype)
    np.cumsum(x, axis=-1, out=out[..., 1:])
    return out


def stream_final_state(
    last: np.ndarray, layout: Rows, initial: np.ndarray
) -> np.ndarray:
    """Hysteron states from the codes of one step.

    Args:
        last: Codes of one step, e.g. ``stream_codes(...)[:, -1]``, shape ``(R,)``.
        layout: :class:`Rows` of the hysterons.
        initial: States before the history, shape ``(M,)``.

    Returns:
        States in ``[-1, 1]``, shape ``(M,)``, dtype of ``initial``.
    """
    n_levels = layout.beta_levels.size
    c = (last.astype(np.int64) - _code_base(layout))[layout.row]
    q = layout.beta_rank
    up_after = np.where(q < n_levels + 1 - c, 1.0, -1.0)  # reached
    stays = np.where(q < -c - 1, initial, -1.0)  # never reached
    return np.where(c > 0, up_after, stays).astype(initial.dtype)


class RowGroups:
    """Mesh rows merged into groups, so that a weighted sum is fewer lookups.

    A row of ``L`` hysterons is in one of only ``A = 2 (L + 1)`` distinct
    situations (how many of its own hysterons are up, reached or not), whatever
    its code. Rows whose numbers of situations multiply to at most ``cap``
    share one table (the sums of their entries for every combination), so that
    a weighted sum over the mesh takes one lookup per group instead of one per
    row (e.g. 990 hysterons in 87 rows: 30 groups at ``cap = 2048``).

    Args:
        layout: :class:`Rows` of the hysterons.
        cap: Most combinations per group.

    Attributes:
        layout: ``layout`` with its rows in group order (use it for the codes).
        starts: First row of each group, shape ``(G,)``.
    """

    def __init__(self, layout: Rows, cap: int = 2048) -> None:
        n_rows, n1 = layout.below.shape
        n_levels = n1 - 1
        length = layout.below[:, -1]
        sizes = 2 * (length + 1)
        members: list[list[int]] = []
        product: list[int] = []
        for r in np.argsort(-sizes, kind="stable").tolist():  # best fit decreasing
            fits = [g for g in range(len(members)) if product[g] * sizes[r] <= cap]
            if fits:
                g = max(fits, key=lambda g: product[g])
                members[g].append(r)
                product[g] *= int(sizes[r])
            else:
                members.append([r])
                product.append(int(sizes[r]))
        order = np.array([r for m in members for r in m])
        self.layout = permute_rows(layout, order)
        self.starts = np.cumsum([0] + [len(m) for m in members[:-1]])
        self.sizes = sizes[order]
        # situation id of every (row, code position); position U + 1 is unused
        below = self.layout.below
        width = 2 * n_levels + 3
        ids = np.zeros((n_rows, width), dtype=np.int64)
        ids[:, : n_levels + 1] = below[:, ::-1]  # never reached, k = U - p
        ids[:, n_levels + 2 :] = self.sizes[:, None] // 2 + below[:, ::-1]
        self._ids = ids
        self._used = np.ones(width, dtype=bool)
        self._used[n_levels + 1] = False
        stride = np.ones(n_rows, dtype=np.int64)
        offset = np.zeros(n_rows, dtype=np.int64)
        self._groups = []
        total = 0
        for g, start in enumerate(self.starts.tolist()):
            rows = list(range(start, start + len(members[g])))
            for i in reversed(range(len(rows) - 1)):
                stride[rows[i]] = stride[rows[i + 1]] * self.sizes[rows[i + 1]]
            offset[rows[0]] = total
            total += int(np.prod(self.sizes[rows]))
            self._groups.append(rows)
        self.n_entries = total
        self.rowmap = (ids * stride[:, None] + offset[:, None]).reshape(-1)
        self._rowmap: dict = {}
        counts = np.array([len(m) for m in members])
        self._later = [np.flatnonzero(counts > i) for i in range(1, counts.max())]

    def table(self, table: np.ndarray, dtype: type | None = None) -> np.ndarray:
        """Group tables from a row table of :func:`stream_table` (same layout).

        Entries are summed over a group's rows in the dtype of ``table``.

        Returns:
            Shape ``(n_entries, K)``.
        """
        n_rows = self.layout.row_alpha.size
        n_k = table.shape[1]
        full = table.reshape(n_rows, -1, n_k)
        out = []
        for rows in self._groups:
            joint = np.zeros((1, n_k), dtype=table.dtype)
            for r in rows:
                per = np.zeros((self.sizes[r], n_k), dtype=table.dtype)
                per[self._ids[r, self._used]] = full[r, self._used]
                joint = (joint[:, None, :] + per[None, :, :]).reshape(-1, n_k)
            out.append(joint)
        return np.concatenate(out).astype(dtype or table.dtype)

    def codes(self, code: np.ndarray) -> np.ndarray:
        """Group codes from row codes of :func:`stream_codes`, ``(R, T) -> (G, T)``."""
        rowmap = self._rowmap.get(code.dtype)
        if rowmap is None:
            rowmap = self._rowmap[code.dtype] = self.rowmap.astype(code.dtype)
        picked = rowmap[code]
        out = picked[self.starts]
        # add the i-th row of every group that has one (5x faster than reduceat)
        for i, groups in enumerate(self._later, start=1):
            out[groups] += picked[self.starts[groups] + i]
        return out


def _row_sums(code: np.ndarray, table: np.ndarray) -> np.ndarray:
    """``sum_g table[code[g, t], :]``, shape ``(T, K)``, summed in the table's dtype.

    A sparse product: one row of ``G`` ones per step (summed in order).
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
_SCALARS = (
    "offset",
    "slope",
    "scale",
    "output_loc",
    "output_scale",
    "noise_std",
    "calibration",
)


@dataclass(frozen=True)
class StreamSpec:
    """The numbers of a fitted Preisach model (and band) that streaming needs.

    The output is ``output_loc + output_scale * (offset + slope u_n + scale m)``
    with ``u_n = (u - lo) / (hi - lo)`` and ``m = sum_i weights_i s_i`` (weights
    normalised to sum 1); the band's standard deviation is
    ``output_scale * calibration * sqrt(|a_0 + a_1 u_n + sum_i W_i s_i|^2 +
    noise_std^2)`` over its ``K`` directions (the same unclipped ``u_n`` as the
    output's linear term: beyond the range the band widens with the slope's
    uncertainty; see
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
        if not (np.isfinite(lo) and np.isfinite(hi)):
            raise ValueError(f"non-finite input_range ({lo}, {hi}).")
        for name in _SCALARS + _ARRAYS:
            value = getattr(self, name)
            if value is not None and not np.isfinite(value).all():
                raise ValueError(f"non-finite {name}.")
        if not hi > lo:
            raise ValueError(f"input range needs lo < hi; got ({lo}, {hi}).")
        if not self.noise_std >= 0:
            raise ValueError(f"noise_std must be >= 0; got {self.noise_std}.")
        if not self.calibration >= 1:
            raise ValueError(f"calibration must be >= 1; got {self.calibration}.")
        if (np.asarray(self.weights) < 0).any():
            raise ValueError(
                f"weights must be >= 0; got {float(np.min(self.weights))}."
            )

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

    def __init__(
        self, spec: StreamSpec, band_dtype: type = np.float32, cap: int = 2048
    ) -> None:
        self.spec = spec
        self._groups = RowGroups(row_layout(spec.alpha, spec.beta), cap)
        self.layout = self._groups.layout
        self._last = start_codes(self.layout)
        initial = np.asarray(spec.initial, dtype=np.float64)
        mean = stream_table(self.layout, spec.weights[None, :], initial)
        self._mean = self._groups.table(mean)[:, 0]
        self._band = None
        if spec.has_band:
            band = stream_table(self.layout, spec.band_weights, initial)
            self._band = self._groups.table(band, dtype=band_dtype)

    @property
    def state(self) -> np.ndarray:
        """Hysteron states after the inputs so far, shape ``(M,)``."""
        initial = np.asarray(self.spec.initial, dtype=np.float64)
        return stream_final_state(self._last, self.layout, initial)

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
            ``None`` without a band. Inputs beyond the range warn; there the
            prediction is saturated plus the linear term, and ``std`` includes
            the linear term's uncertainty at the (unclipped) input, not that of
            the saturation itself.
        """
        s = self.spec
        u = np.asarray(u, dtype=np.float64).reshape(-1)
        un = self.normalize(u)
        un_c = np.clip(un, 0.0, 1.0)  # saturation beyond the range
        code = stream_codes(un_c, self.layout, self._last)
        self._last = code[:, -1].copy()
        code = self._groups.codes(code)  # (G, T)
        sums = self._mean[code].sum(axis=0)
        y = s.offset + s.slope * un + s.scale * sums
        pred = s.output_loc + s.output_scale * y
        std = None
        if self._band is not None:
            proj = _row_sums(code, self._band)  # (T, K) in the table's dtype
            a = s.band_affine.astype(self._band.dtype)
            proj += a[:, 0]
            # the unclipped input, as in the prediction's linear term
            proj += un.astype(self._band.dtype)[:, None] * a[:, 1]
            # the norm accumulated in float64, rounded to the sums' dtype
            norm2 = np.einsum("tk,tk->t", proj, proj, dtype=np.float64)
            norm = np.sqrt(norm2).astype(self._band.dtype).astype(np.float64)
            std = s.output_scale * (s.calibration * np.sqrt(norm**2 + s.noise_std**2))
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
