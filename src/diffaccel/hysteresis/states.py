"""Hysteron states for time-ordered input sequences: exact relays and a smooth,
rate-independent relaxation.

All functions here work on *normalised* inputs ``u`` in ``[0, 1]`` (the model
maps physical units) and are pure functions of tensors; dtype and device come
from the inputs.

Exact relays. A hysteron ``(alpha, beta)`` is ``+1`` after the input reached
``alpha`` and ``-1`` after it fell to ``beta``; in between it keeps its state:
``s_t = +1 if u_t >= alpha else (-1 if u_t <= beta else s_{t-1})``, starting from
an initial state ``s_{-1}``. Equivalently, at step ``t``

* if the input ever reached ``alpha`` (last time ``L``), the hysteron is up iff
  ``beta < min(u_{L+1..t})`` (an empty minimum is ``+inf``);
* otherwise it is ``s_{-1}`` iff ``beta < min(u_{0..t})``, else ``-1``.

Both conditions depend on ``alpha`` only through ``L`` and on ``beta`` only
through a comparison, so hysterons sharing an ``alpha`` (a mesh row) share
``L`` and the window minimum. :func:`exact_magnetization` uses this to reduce
the Preisach integral to prefix sums of the weights along each row, found by
a beta-level table: cost ``O(T R)`` for ``R`` rows of ``L`` points instead of
``O(T M)``, and no ``(T, M)`` table. :func:`exact_states` builds the full table.

Smooth relays. Within a monotone segment of the input the state of a
hysteron is a function of the input only, anchored at the segment's turning
point ``(u_k, s_k)``: on a rising segment
``s = 1 - (1 - s_k) * sigmoid(-(u - alpha) / w) / sigmoid(-(u_k - alpha) / w)``,
on a falling one
``s = -1 + (1 + s_k) * sigmoid(-(beta - u) / w) / sigmoid(-(beta - u_k) / w)``.
This is continuous at turning points, stays in ``[-1, 1]``, tends to the exact
relay as ``w -> 0`` and is rate independent: a ramp sampled with 2 or 1000
points has the same turning points and hence the same states.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = [
    "RowLayout",
    "StreamTable",
    "demagnetized_state",
    "exact_magnetization",
    "exact_states",
    "smooth_states",
    "stream_codes",
    "stream_final_state",
    "stream_sums",
    "stream_table",
]


class RowLayout:
    """Hysterons grouped into rows of equal ``alpha``, sorted by ``beta``.

    Thresholds are also ranked: ``beta_levels`` holds the sorted distinct betas
    and ``beta_rank[i]`` the position of ``beta[i]`` among them, so that
    ``beta[i] < x`` iff ``beta_rank[i] < searchsorted(beta_levels, x)``.
    ``below[r, j]`` counts the betas of row ``r`` among the ``j`` lowest levels.

    Args:
        alpha: Up thresholds [1], shape ``(M,)``.
        beta: Down thresholds [1], shape ``(M,)``.

    Shapes:
        ``row_alpha``: ``(R,)``; ``index``: ``(R, L)`` hysteron index, padded
        with ``M``; ``row``, ``beta_rank``: ``(M,)``; ``beta_levels``: ``(U,)``;
        ``below``: ``(R, U + 1)``.
    """

    def __init__(self, alpha: Tensor, beta: Tensor) -> None:
        m = alpha.numel()
        dev = alpha.device
        row_alpha, row = torch.unique(alpha, sorted=True, return_inverse=True)
        beta_levels, beta_rank = torch.unique(beta, sorted=True, return_inverse=True)
        order_b = torch.argsort(beta, stable=True)
        order = order_b[torch.argsort(row[order_b], stable=True)]
        counts = torch.bincount(row, minlength=row_alpha.numel())
        starts = torch.cumsum(counts, 0) - counts
        col = torch.empty_like(row)
        col[order] = torch.arange(m, device=dev) - starts[row[order]]
        n_rows, width = row_alpha.numel(), int(counts.max())
        index = torch.full((n_rows, width), m, dtype=torch.long, device=dev)
        index[row, col] = torch.arange(m, device=dev)
        n_levels = beta_levels.numel()
        hist = torch.zeros(n_rows, n_levels, dtype=torch.long, device=dev)
        hist.index_put_((row, beta_rank), torch.ones_like(row), accumulate=True)
        below = F.pad(torch.cumsum(hist, dim=1), (1, 0))
        # position of each (row, level) count inside the row's padded prefix sums
        self.row_alpha = row_alpha
        self.beta_levels = beta_levels.contiguous()
        self.beta_rank = beta_rank
        self.index = index
        self.row = row
        self.below = below

    def to(self, device: torch.device | str | None, dtype: torch.dtype) -> RowLayout:
        """Move in place to ``device``; cast thresholds to ``dtype``; return self."""
        self.row_alpha = self.row_alpha.to(device=device, dtype=dtype)
        self.beta_levels = self.beta_levels.to(device=device, dtype=dtype).contiguous()
        for name in ("beta_rank", "index", "row", "below"):
            setattr(self, name, getattr(self, name).to(device=device))
        return self


def demagnetized_state(alpha: Tensor, beta: Tensor) -> Tensor:
    """States after AC demagnetization about the centre of the range.

    Hysterons below the anti-diagonal ``alpha + beta = 1`` are up, those above it
    down (points on it, to round-off of 1e-9, get 0).

    Args:
        alpha: Up thresholds [1], shape ``(M,)``.
        beta: Down thresholds [1], shape ``(M,)``.

    Returns:
        States in ``{-1, 0, 1}``, shape ``(M,)``.
    """
    d = 1.0 - alpha - beta
    return torch.where(d.abs() <= 1e-9, torch.zeros_like(d), torch.sign(d))


def _row_events(u: Tensor, layout: RowLayout) -> tuple[Tensor, Tensor, Tensor]:
    """Per-row switching summary of exact relays, in beta-level ranks.

    Returns ``reached`` (input has reached the row's alpha), ``window_rank``
    (number of beta levels below the minimum input since the last time it did;
    all ``U`` levels at that step) and ``run_rank`` (number of beta levels below
    the running minimum of the input).

    The window minimum is a segmented running minimum: every step that reaches
    a row's alpha opens a new segment, so ``segment * (U + 2) + (U + 1 - rank)``
    grows with the segment and its running maximum holds, within the current
    segment, ``U + 1`` minus the minimum rank since the segment opened (a
    reaching step counts as rank ``U``). One ``cumsum`` and one ``cummax`` over
    ``(B, R, T)`` (time last, contiguous), no range-minimum table.

    Shapes:
        ``u``: ``(B, T)``; returns ``(B, R, T)``, ``(B, R, T)``, ``(B, T)``.
    """
    n_levels = layout.beta_levels.numel()
    # number of beta levels strictly below each input; monotone in u, so the
    # minimum over a window commutes with it
    # int32 scans are ~10x faster than int64 ones on CPU; keys stay below
    # T * (U + 2), so int64 only for very long sequences
    small = u.shape[-1] * (n_levels + 2) < 2**31 - 1
    idx = torch.int32 if small else torch.int64
    rank = torch.searchsorted(
        layout.beta_levels, u.contiguous(), side="left", out_int32=small
    )
    up = u.unsqueeze(1) >= layout.row_alpha.unsqueeze(-1)  # (B, R, T)
    segment = torch.cumsum(up, dim=-1, dtype=idx)  # reaching steps so far, per row
    reached = segment > 0
    inv_rank = torch.where(up, 1, (n_levels + 1 - rank).unsqueeze(1)).to(idx)
    offset = segment * (n_levels + 2)
    best = (offset + inv_rank).cummax(dim=-1).values - offset
    window_rank = (n_levels + 1 - best).long()
    run_rank = rank.cummin(dim=1).values.long()
    return reached, window_rank, run_rank


def _flatten_batch(u: Tensor) -> tuple[Tensor, tuple[int, ...]]:
    batch = tuple(u.shape[:-1])
    return u.reshape(-1, u.shape[-1]), batch


def exact_states(
    u: Tensor,
    alpha: Tensor,
    beta: Tensor,
    initial: Tensor,
    layout: RowLayout | None = None,
    last: bool = False,
) -> Tensor:
    """States of exact relay hysterons along input sequences.

    Args:
        u: Normalised inputs [1], shape ``(*B, T)``, time along the last axis.
        alpha: Up thresholds [1], shape ``(M,)``.
        beta: Down thresholds [1], shape ``(M,)``.
        initial: States before the first step, in ``[-1, 1]``, shape ``(M,)`` or
            ``(*B, M)``.
        layout: Precomputed :class:`RowLayout` of ``(alpha, beta)``.
        last: Return only the states after the last step, shape ``(*B, M)``.

    Returns:
        States in ``[-1, 1]``, shape ``(*B, T, M)`` (``+-1`` except hysterons
        never switched, which keep ``initial``).

    Shapes:
        See Args/Returns.
    """
    layout = layout if layout is not None else RowLayout(alpha, beta)
    u2, batch = _flatten_batch(u)
    reached, window_rank, run_rank = _row_events(u2, layout)
    if last:
        reached, window_rank = reached[..., -1:], window_rank[..., -1:]
        run_rank = run_rank[:, -1:]
    r, q = layout.row, layout.beta_rank
    reached, window_rank = reached.transpose(1, 2), window_rank.transpose(1, 2)
    up_after = q < window_rank[..., r]  # (B, T, M)
    init = initial.reshape(-1, 1, initial.shape[-1]) if initial.ndim > 1 else initial
    keep = q < run_rank.unsqueeze(-1)
    one = u2.new_ones(())
    never = torch.where(keep, init.to(u2.dtype), -one)
    s = torch.where(reached[..., r], torch.where(up_after, one, -one), never)
    if last:
        return s.reshape(*batch, alpha.numel())
    return s.reshape(*batch, u.shape[-1], alpha.numel())


def exact_magnetization(
    u: Tensor, layout: RowLayout, weights: Tensor, initial: Tensor
) -> Tensor:
    """Weighted sum of exact relay states, without building the state table.

    For each row the up hysterons are a prefix of its betas, so the row's sum is
    read from prefix sums of the weights, tabulated per beta level.

    Args:
        u: Normalised inputs [1], shape ``(*B, T)``.
        layout: :class:`RowLayout` of the hysterons.
        weights: Hysteron weights (area x density), shape ``(M,)``; gradients
            flow to them.
        initial: States before the first step, shape ``(M,)`` or ``(*B, M)``;
            gradients flow to them.

    Returns:
        ``sum_i weights_i * s_i(t)``, shape ``(*B, T)`` (not normalised).

    Shapes:
        See Args/Returns.
    """
    u2, batch = _flatten_batch(u)
    nb, t = u2.shape
    reached, window_rank, run_rank = _row_events(u2, layout)
    n_rows = layout.index.shape[0]
    zero = weights.new_zeros(1)
    w_pad = torch.cat([weights, zero])[layout.index]  # (R, L)
    w_cum = F.pad(torch.cumsum(w_pad, dim=-1), (1, 0))  # (R, L + 1)
    w_row = w_cum[:, -1:]
    # row sums of weights below each beta level: (R, U + 1)
    w_below = torch.gather(w_cum, 1, layout.below)
    signed = 2.0 * w_below - w_row  # row magnetization if levels < j are up
    up_part = torch.gather(signed, 1, window_rank.transpose(0, 1).reshape(n_rows, -1))
    # hysterons that never switched up: initial state below the running
    # minimum, -1 above it
    k0 = run_rank.reshape(1, -1).expand(n_rows, -1)
    if initial.ndim == 1:
        init_pad = torch.cat([initial.to(weights.dtype), zero])[layout.index]
        s_cum = F.pad(torch.cumsum(w_pad * init_pad, dim=-1), (1, 0))
        never_table = torch.gather(s_cum, 1, layout.below) + w_below - w_row
        never_part = torch.gather(never_table, 1, k0)
    else:
        init2 = initial.reshape(-1, initial.shape[-1]).to(weights.dtype)
        init2 = init2.expand(nb, -1)
        init_pad = torch.cat([init2, init2.new_zeros(nb, 1)], dim=1)[:, layout.index]
        s_cum = F.pad(torch.cumsum(w_pad * init_pad, dim=-1), (1, 0))  # (B, R, L+1)
        s_below = torch.gather(s_cum, 2, layout.below.expand(nb, -1, -1))
        never_table = s_below + w_below - w_row  # (B, R, U + 1)
        k0b = run_rank.unsqueeze(1).expand(nb, n_rows, t)
        never_part = torch.gather(never_table, 2, k0b).permute(1, 0, 2)
        never_part = never_part.reshape(n_rows, -1)
    reached_f = reached.transpose(0, 1).reshape(n_rows, -1)
    m = torch.where(reached_f, up_part, never_part).sum(dim=0)
    return m.view(*batch, t)


def _segment_state(
    rising: Tensor, s_k: Tensor, u_k: Tensor, u: Tensor, alpha: Tensor, beta: Tensor, w
) -> Tensor:
    """Smooth relay state on a monotone segment from turning point ``(u_k, s_k)``."""
    x = (u - alpha) / w
    x_k = (u_k - alpha) / w
    r_up = torch.exp(torch.clamp(F.logsigmoid(-x) - F.logsigmoid(-x_k), max=0.0))
    y = (beta - u) / w
    y_k = (beta - u_k) / w
    r_dn = torch.exp(torch.clamp(F.logsigmoid(-y) - F.logsigmoid(-y_k), max=0.0))
    s_up = 1.0 - (1.0 - s_k) * r_up
    s_dn = -1.0 + (1.0 + s_k) * r_dn
    return torch.where(rising, s_up, s_dn)


def smooth_states(
    u: Tensor,
    alpha: Tensor,
    beta: Tensor,
    initial: Tensor,
    width: float | Tensor,
    start: float | Tensor = 0.0,
) -> Tensor:
    """Rate-independent smooth hysteron states along input sequences.

    The sequence starts from a virtual turning point at input ``start`` with
    states ``initial`` (negative saturation: ``start = 0``; positive: ``1``;
    demagnetized or learned: ``0.5``), then follows ``u``. Direction changes of
    the input (ignoring flat steps) are turning points; on each monotone segment
    the state follows the module formula, continuous at the turning points.

    Args:
        u: Normalised inputs [1], shape ``(*B, T)``.
        alpha: Up thresholds [1], shape ``(M,)``.
        beta: Down thresholds [1], shape ``(M,)``.
        initial: States at the virtual start, shape ``(M,)`` or ``(*B, M)``.
        width: Smoothing width in normalised input units [1], > 0.
        start: Normalised input of the virtual start point [1], scalar or ``(*B,)``.

    Returns:
        States in ``[-1, 1]``, shape ``(*B, T, M)``, differentiable with respect
        to ``u``, ``initial`` and ``width``.

    Shapes:
        See Args/Returns.
    """
    u2, batch = _flatten_batch(u)
    nb, t = u2.shape
    m = alpha.numel()
    start_t = torch.as_tensor(start, dtype=u2.dtype, device=u2.device)
    start_t = start_t.reshape(-1, 1).expand(nb, 1)
    v = torch.cat([start_t, u2], dim=1)  # (B, T + 1)
    d = torch.sign(v[:, 1:] - v[:, :-1]).detach()
    idx = torch.arange(t, device=u2.device).expand(nb, t)
    last = torch.where(d != 0, idx, -1).cummax(dim=1).values
    direction = torch.gather(d, 1, last.clamp(min=0))
    direction = torch.where((last < 0) | (direction == 0), 1.0, direction)
    new_seg = torch.zeros_like(direction, dtype=torch.bool)
    new_seg[:, 1:] = direction[:, 1:] != direction[:, :-1]
    seg = torch.cumsum(new_seg.to(torch.long), dim=1)  # (B, T)
    n_seg = int(seg.max()) + 1
    # turning-point inputs and directions per segment (padded column n_seg dropped)
    target = torch.where(new_seg, seg, n_seg)
    target[:, 0] = 0
    turn_u = u2.new_zeros(nb, n_seg + 1).scatter(1, target, v[:, :-1])[:, :n_seg]
    turn_u = torch.cat([start_t, turn_u[:, 1:]], dim=1)
    turn_dir = direction.new_ones(nb, n_seg + 1).scatter(1, target, direction)
    rising_k = (turn_dir[:, :n_seg] > 0).unsqueeze(-1)  # (B, K, 1)
    init = initial.reshape(-1, m).to(u2.dtype).expand(nb, m)
    s_turn = [init]
    for k in range(n_seg - 1):
        s_turn.append(
            _segment_state(
                rising_k[:, k],
                s_turn[-1],
                turn_u[:, k : k + 1],
                turn_u[:, k + 1 : k + 2],
                alpha,
                beta,
                width,
            )
        )
    s_turn_t = torch.stack(s_turn, dim=1)  # (B, K, M)
    s_k = torch.gather(s_turn_t, 1, seg.unsqueeze(-1).expand(nb, t, m))
    u_k = torch.gather(turn_u, 1, seg).unsqueeze(-1)
    rising = (direction > 0).unsqueeze(-1)
    s = _segment_state(rising, s_k, u_k, u2.unsqueeze(-1), alpha, beta, width)
    return s.reshape(*batch, t, m)


def stream_codes(u: Tensor, layout: RowLayout) -> Tensor:
    """Situation of every mesh row at every step of one chunk, as table indices.

    At every step each row of the mesh is in one of ``2 (U + 1)`` situations
    (reached or not, and how many of its beta levels are up), so any weighted
    sum of the states is a lookup per row in a table of
    :func:`stream_table`, summed over rows. Row ``r``'s code is
    ``r W + U + 1 + c`` (``W = 2 U + 3``) with ``c`` in ``[1, U + 1]`` once
    its alpha was reached in the chunk (``U + 1 - c`` beta levels up: those
    below the minimum since the last reach) and ``c`` in ``[-U - 1, -1]``
    before (the ``-c - 1`` levels below the chunk's running minimum keep their
    state, the others are down).

    One ``cumsum`` and one ``cummax`` over ``(R, T)`` int32 keys (as in
    :func:`_row_events`), no other table: the key
    ``(segment - 1) (U + 2) + (U + 1 - rank)`` is negative until the row's
    alpha is first reached, so its running maximum minus the segment offset
    is ``c`` itself.

    Args:
        u: Normalised inputs [1] of one chunk, shape ``(T,)``, inside ``[0, 1]``.
        layout: :class:`RowLayout` of the hysterons.

    Returns:
        Codes, shape ``(R, T)``, int32 (int64 for chunks beyond ~2^31 / U rows).
    """
    n_levels = layout.beta_levels.numel()
    t = u.numel()
    small = (t + 1) * (n_levels + 2) < 2**31 - 1
    idx = torch.int32 if small else torch.int64
    u = u.contiguous()
    rank = torch.searchsorted(layout.beta_levels, u, side="left", out_int32=small)
    inv = (n_levels + 1 - rank).to(idx)  # (T,) in [1, U + 1]
    up = u.unsqueeze(0) >= layout.row_alpha.unsqueeze(1)  # (R, T)
    seg = torch.cumsum(up, dim=1, dtype=idx).sub_(1)  # reaches so far, minus 1
    key = torch.where(up, torch.ones((), dtype=idx), inv)
    del up
    key.add_(seg, alpha=n_levels + 2)
    code = key.cummax(dim=1).values
    del key
    code.sub_(seg.clamp_(min=0), alpha=n_levels + 2)
    width = 2 * n_levels + 3
    base = torch.arange(code.shape[0], dtype=idx, device=u.device) * width
    return code.add_((base + n_levels + 1).unsqueeze(1))


class StreamTable:
    """Row sums of weighted states for every code of :func:`stream_codes`.

    ``table[code, k]`` for fixed weight vectors: the part for rows already
    reached depends on the weights only and is built once; the part for rows
    not yet reached depends on the states before the chunk and is refreshed by
    :meth:`update` (cheap: ``O(K M)``).

    Args:
        layout: :class:`RowLayout` of the hysterons.
        weights: Weight vectors, shape ``(K, M)``.
        dtype: dtype of the table (default: that of ``weights``).

    Shapes:
        :meth:`update` returns ``(R (2 U + 3), K)``.
    """

    def __init__(
        self, layout: RowLayout, weights: Tensor, dtype: torch.dtype | None = None
    ) -> None:
        n_k = weights.shape[0]
        n_rows, n_levels = layout.below.shape[0], layout.below.shape[1] - 1
        self.layout = layout
        self.below = layout.below.expand(n_k, -1, -1)
        pad = weights.new_zeros(n_k, 1)
        self.w_pad = torch.cat([weights, pad], dim=1)[:, layout.index]  # (K, R, L)
        w_cum = F.pad(torch.cumsum(self.w_pad, dim=-1), (1, 0))  # (K, R, L + 1)
        w_row = w_cum[..., -1:]
        w_below = torch.gather(w_cum, 2, self.below)  # (K, R, U + 1)
        self.w_rest = w_below - w_row
        signed = 2.0 * w_below - w_row
        width = 2 * n_levels + 3
        self.table = weights.new_zeros(n_rows, width, n_k, dtype=dtype or weights.dtype)
        self.table[:, n_levels + 2 :] = signed.flip(-1).permute(1, 2, 0)
        self.n_levels = n_levels

    def update(self, initial: Tensor) -> Tensor:
        """The table for a chunk that starts from states ``initial``, shape ``(M,)``."""
        init = initial.to(self.w_pad.dtype)
        init_pad = torch.cat([init, init.new_zeros(1)])[self.layout.index]  # (R, L)
        s_cum = F.pad(torch.cumsum(self.w_pad * init_pad, dim=-1), (1, 0))
        never = torch.gather(s_cum, 2, self.below) + self.w_rest
        self.table[:, : self.n_levels + 1] = never.flip(-1).permute(1, 2, 0)
        return self.table.view(-1, self.table.shape[2])


def stream_table(layout: RowLayout, weights: Tensor, initial: Tensor) -> Tensor:
    """Row sums of weighted states for every code of :func:`stream_codes`.

    Args:
        layout: :class:`RowLayout` of the hysterons.
        weights: Weight vectors, shape ``(K, M)``.
        initial: States before the chunk, shape ``(M,)``.

    Returns:
        ``table[code, k]``, shape ``(R (2 U + 3), K)``, dtype of ``weights``.
    """
    return StreamTable(layout, weights).update(initial)


def stream_final_state(last: Tensor, layout: RowLayout, initial: Tensor) -> Tensor:
    """Hysteron states after a chunk from its last codes.

    Args:
        last: Codes of the chunk's last step, ``stream_codes(...)[:, -1]``,
            shape ``(R,)``.
        layout: :class:`RowLayout` of the hysterons.
        initial: States before the chunk, shape ``(M,)``.

    Returns:
        States in ``[-1, 1]``, shape ``(M,)``, dtype of ``initial``.
    """
    n_levels = layout.beta_levels.numel()
    width = 2 * n_levels + 3
    rows = torch.arange(last.numel(), device=last.device)
    c = (last - n_levels - 1 - width * rows)[layout.row]
    q = layout.beta_rank
    one = initial.new_ones(())
    up_after = torch.where(q < n_levels + 1 - c, one, -one)  # reached
    stays = torch.where(q < -c - 1, initial, -one)  # never reached
    return torch.where(c > 0, up_after, stays)


def stream_sums(code: Tensor, table: Tensor) -> Tensor:
    """Sum over rows of ``table[code]`` for one weight vector.

    Args:
        code: Output of :func:`stream_codes`, shape ``(R, T)``.
        table: Output of :func:`stream_table` with ``K = 1``, shape ``(R W, 1)``.

    Returns:
        Shape ``(T,)``, dtype of ``table`` (summed in it).
    """
    picked = table[:, 0].index_select(0, code.reshape(-1))
    return picked.view(code.shape).sum(dim=0)


def exact_stream_step(
    u: Tensor,
    layout: RowLayout,
    weights: Tensor,
    initial: Tensor,
    extra: Tensor | None = None,
) -> tuple[Tensor, Tensor | None, Tensor]:
    """Weighted sums of exact relay states along one chunk, and the state after it.

    One pass over the chunk (:func:`stream_codes`) serves the model's weights,
    further weight vectors (the directions of a predictive band) and the final
    state, so that a long history can be streamed chunk by chunk in bounded
    memory: feed the returned state as ``initial`` of the next chunk.

    Args:
        u: Normalised inputs [1] of one chunk, shape ``(T,)``, inside ``[0, 1]``.
        layout: :class:`RowLayout` of the hysterons.
        weights: Weights (any sign), shape ``(M,)``; summed in their dtype.
        initial: States before the chunk, in ``[-1, 1]``, shape ``(M,)``.
        extra: Further weight vectors, shape ``(K, M)``, summed in float32
            (relative round-off ~1e-7: meant for standard deviations).

    Returns:
        ``(sums, extra_sums, final)``: ``sums[t] = sum_i weights_i s_i(t)``,
        shape ``(T,)``; the same for ``extra``, shape ``(K, T)`` (``None``
        without ``extra``); the states after the last step, shape ``(M,)``.

    Shapes:
        See Args/Returns.
    """
    code = stream_codes(u, layout)
    init = initial.to(weights.dtype)
    sums = stream_sums(code, stream_table(layout, weights.unsqueeze(0), init))
    extra_sums = None
    if extra is not None:
        tab = stream_table(layout, extra, initial.to(extra.dtype))
        bag = F.embedding_bag(code.T.contiguous(), tab.to(torch.float32), mode="sum")
        extra_sums = bag.T.to(extra.dtype)
    return sums, extra_sums, stream_final_state(code[:, -1], layout, init)
