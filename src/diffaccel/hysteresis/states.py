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
``searchsorted``: cost ``O(T R log L)`` for ``R`` rows of ``L`` points instead of
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
    "demagnetized_state",
    "exact_magnetization",
    "exact_states",
    "smooth_states",
]


class RowLayout:
    """Hysterons grouped into rows of equal ``alpha``, sorted by ``beta``.

    Args:
        alpha: Up thresholds [1], shape ``(M,)``.
        beta: Down thresholds [1], shape ``(M,)``.

    Shapes:
        ``row_alpha``: ``(R,)``; ``row_beta``: ``(R, L)`` padded with ``+inf``;
        ``index``: ``(R, L)`` hysteron index, padded with ``M``; ``row``: ``(M,)``.
    """

    def __init__(self, alpha: Tensor, beta: Tensor) -> None:
        m = alpha.numel()
        row_alpha, row = torch.unique(alpha, sorted=True, return_inverse=True)
        order_b = torch.argsort(beta, stable=True)
        order = order_b[torch.argsort(row[order_b], stable=True)]
        counts = torch.bincount(row, minlength=row_alpha.numel())
        starts = torch.cumsum(counts, 0) - counts
        col = torch.empty_like(row)
        col[order] = torch.arange(m, device=alpha.device) - starts[row[order]]
        n_rows, width = row_alpha.numel(), int(counts.max())
        index = torch.full((n_rows, width), m, dtype=torch.long, device=alpha.device)
        index[row, col] = torch.arange(m, device=alpha.device)
        row_beta = torch.full(
            (n_rows, width), float("inf"), dtype=beta.dtype, device=beta.device
        )
        row_beta[row, col] = beta
        self.row_alpha = row_alpha
        self.row_beta = row_beta.contiguous()
        self.index = index
        self.row = row

    def to(self, device: torch.device | str | None, dtype: torch.dtype) -> RowLayout:
        """Move in place to ``device``; cast thresholds to ``dtype``; return self."""
        self.row_alpha = self.row_alpha.to(device=device, dtype=dtype)
        self.row_beta = self.row_beta.to(device=device, dtype=dtype).contiguous()
        self.index = self.index.to(device=device)
        self.row = self.row.to(device=device)
        return self


def demagnetized_state(alpha: Tensor, beta: Tensor) -> Tensor:
    """States after AC demagnetisation about the centre of the range.

    Hysterons below the anti-diagonal ``alpha + beta = 1`` are up, those above it
    down (points on it get 0).

    Args:
        alpha: Up thresholds [1], shape ``(M,)``.
        beta: Down thresholds [1], shape ``(M,)``.

    Returns:
        States in ``{-1, 0, 1}``, shape ``(M,)``.
    """
    return torch.sign(1.0 - alpha - beta)


def _window_min(u: Tensor, lo: Tensor) -> Tensor:
    """Minimum of ``u[b, lo..t]`` for every ``t``, ``+inf`` where ``lo > t``.

    Sparse-table range minimum: exact, ``O(T log T)`` to build.

    Shapes:
        ``u``: ``(B, T)``; ``lo``: ``(B, T, R)`` long; result ``(B, T, R)``.
    """
    b, t = u.shape
    levels = [u]
    span = 1
    while 2 * span <= t:
        prev = levels[-1]
        nxt = torch.minimum(prev[:, : t - span], prev[:, span:])
        levels.append(F.pad(nxt, (0, span), value=float("inf")))
        span *= 2
    table = torch.stack(levels, dim=1).reshape(b, -1)  # (B, J * T)
    hi = torch.arange(t, device=u.device).view(1, t, 1)
    length = hi - lo + 1
    empty = length <= 0
    length = length.clamp(min=1)
    j = torch.floor(torch.log2(length.to(torch.float64))).to(torch.long)
    j = torch.minimum(j, torch.as_tensor(len(levels) - 1, device=u.device))
    lo_c = lo.clamp(min=0, max=t - 1)
    second = (hi - (1 << j) + 1).clamp(min=0)
    flat_shape = (b, -1)
    a = torch.gather(table, 1, (j * t + lo_c).reshape(flat_shape))
    c = torch.gather(table, 1, (j * t + second).reshape(flat_shape))
    out = torch.minimum(a, c).view(lo.shape)
    return out.masked_fill(empty, float("inf"))


def _row_events(u: Tensor, row_alpha: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Per-row switching summary of exact relays.

    Returns ``reached`` (input has reached the row's alpha), ``window_min``
    (minimum since the last time it did, ``+inf`` if none) and ``run_min``
    (running minimum of the input).

    Shapes:
        ``u``: ``(B, T)``; returns ``(B, T, R)``, ``(B, T, R)``, ``(B, T)``.
    """
    t = u.shape[-1]
    idx = torch.arange(t, device=u.device).view(1, t, 1)
    up = u.unsqueeze(-1) >= row_alpha
    last = torch.where(up, idx, -1).cummax(dim=1).values
    reached = last >= 0
    wmin = _window_min(u, last + 1)
    run_min = u.cummin(dim=1).values
    return reached, wmin, run_min


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
    reached, wmin, run_min = _row_events(u2, layout.row_alpha)
    if last:
        reached, wmin, run_min = reached[:, -1:], wmin[:, -1:], run_min[:, -1:]
    r = layout.row
    up_after = beta < wmin[..., r]  # (B, T, M)
    init = initial.reshape(-1, 1, initial.shape[-1]) if initial.ndim > 1 else initial
    keep = beta < run_min.unsqueeze(-1)
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
    reached, wmin, run_min = _row_events(u2, layout.row_alpha)
    n_rows = layout.row_beta.shape[0]
    zero = weights.new_zeros(1)
    w_pad = torch.cat([weights, zero])[layout.index]  # (R, L)
    w_cum = F.pad(torch.cumsum(w_pad, dim=-1), (1, 0))  # (R, L + 1)
    w_row = w_cum[:, -1]
    # number of betas below the window minimum, per row
    q = wmin.permute(2, 0, 1).reshape(n_rows, -1).contiguous()
    k_up = torch.searchsorted(layout.row_beta, q.to(layout.row_beta.dtype))
    up_part = 2.0 * torch.gather(w_cum, 1, k_up) - w_row[:, None]  # (R, B*T)
    # hysterons never switched up: initial state if beta < running min, else -1
    q0 = run_min.reshape(1, -1).expand(n_rows, -1).contiguous()
    k0 = torch.searchsorted(layout.row_beta, q0.to(layout.row_beta.dtype))
    below = torch.gather(w_cum, 1, k0)
    if initial.ndim == 1:
        init_pad = torch.cat([initial.to(weights.dtype), zero])[layout.index]
        s_cum = F.pad(torch.cumsum(w_pad * init_pad, dim=-1), (1, 0))
        kept = torch.gather(s_cum, 1, k0)
    else:
        init2 = initial.reshape(-1, initial.shape[-1]).to(weights.dtype)
        init2 = init2.expand(nb, -1)
        init_pad = torch.cat([init2, init2.new_zeros(nb, 1)], dim=1)[:, layout.index]
        s_cum = F.pad(torch.cumsum(w_pad * init_pad, dim=-1), (1, 0))  # (B, R, L+1)
        k0b = k0.view(n_rows, nb, t).permute(1, 0, 2)  # (B, R, T)
        kept = torch.gather(s_cum, 2, k0b).permute(1, 0, 2).reshape(n_rows, -1)
    never_part = kept - (w_row[:, None] - below)
    reached_f = reached.permute(2, 0, 1).reshape(n_rows, -1)
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
    demagnetised or learned: ``0.5``), then follows ``u``. Direction changes of
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
