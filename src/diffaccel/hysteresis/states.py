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

from diffaccel.hysteresis.stream import row_layout

__all__ = [
    "RowLayout",
    "demagnetized_state",
    "exact_magnetization",
    "exact_states",
    "smooth_states",
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
        # built once per mesh, on the host, by the one implementation that
        # streaming uses too (diffaccel.hysteresis.stream.row_layout)
        rows = row_layout(alpha.detach().cpu().numpy(), beta.detach().cpu().numpy())
        dev = alpha.device
        self.row_alpha = torch.as_tensor(rows.row_alpha, device=dev)
        self.beta_levels = torch.as_tensor(rows.beta_levels, device=dev).contiguous()
        self.beta_rank = torch.as_tensor(rows.beta_rank, device=dev)
        self.index = torch.as_tensor(rows.index, device=dev)
        self.row = torch.as_tensor(rows.row, device=dev)
        self.below = torch.as_tensor(rows.below, device=dev)

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
