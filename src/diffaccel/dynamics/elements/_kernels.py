"""Per-particle maps shared by several elements (private to ``elements``).

All functions work on the six coordinate columns ``(x, px, y, py, z, pz)``, each a
tensor broadcastable to ``(*K, N)``; keeping columns apart lets a coordinate that
an element does not change (``pz`` in magnets) stay unexpanded.
"""

from __future__ import annotations

import weakref
from collections.abc import Sequence

import torch
from torch import Tensor

#: ``z`` may be None where nothing downstream needs it (``Element.reads_z``).
Coords = tuple[Tensor, Tensor, Tensor, Tensor, Tensor | None, Tensor]

# |u| below which d(sin sqrt(u) / sqrt(u))/du uses its Taylor series (the closed
# form (C - S) / (2u) cancels there). Series error at 1e-2: ~1e-15 relative.
_SERIES_LIMIT = 1e-2


def velocity_z_shift(pz: Tensor, mu2: Tensor) -> Tensor:
    """``beta / beta0 - 1`` of each particle, computed without cancellation.

    Args:
        pz: Relative momentum deviation dP/P0.
        mu2: ``(m c^2 / p0c)^2``.
    """
    p = 1.0 + pz
    e = (p.square() + mu2).sqrt()
    e0 = (1.0 + mu2).sqrt()
    return mu2 * pz * (2.0 + pz) / (e * (p * e0 + e))


def exact_drift(
    x: Tensor,
    px: Tensor,
    y: Tensor,
    py: Tensor,
    z: Tensor | None,
    pz: Tensor,
    length: Tensor,
    mu2: Tensor,
) -> tuple[Tensor, Tensor, Tensor | None]:
    """Exact field-free drift; returns the new ``(x, y, z)``.

    ``x' = px / ps`` with ``ps = sqrt((1 + pz)^2 - px^2 - py^2)`` and
    ``dz = L (beta / beta0 - P / ps)``, both written to avoid cancellation.
    ``z`` None (not needed downstream) is not computed.
    """
    p = 1.0 + pz
    pt2 = px.square() + py.square()
    ps = (p.square() - pt2).sqrt()
    step = length / ps
    x = torch.addcmul(x, px, step)
    y = torch.addcmul(y, py, step)
    if z is None:
        return x, y, None
    dz = length * velocity_z_shift(pz, mu2) - pt2 * step / (p + ps)
    return x, y, z + dz


class _FocusingFunctions(torch.autograd.Function):
    """``C(u) = cos sqrt(u)``, ``s(u) = sin sqrt(u) / sqrt(u)`` at ``u`` and ``-u``.

    Hyperbolic for negative arguments. The forward pass is exact for every ``u``
    (including 0); the backward pass uses ``C' = -s/2`` and
    ``s' = (C - s) / (2u)``, with a Taylor series near ``u = 0``.
    """

    @staticmethod
    def forward(ctx, u: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:  # type: ignore[override]
        tiny = torch.finfo(u.dtype).tiny ** 0.5
        r = u.abs().clamp(min=tiny).sqrt()
        inv = r.reciprocal()
        cos_r, cosh_r = r.cos(), r.cosh()
        sinc_r, sinhc_r = r.sin() * inv, r.sinh() * inv
        pos = u >= 0
        c_plus = torch.where(pos, cos_r, cosh_r)
        s_plus = torch.where(pos, sinc_r, sinhc_r)
        c_minus = torch.where(pos, cosh_r, cos_r)
        s_minus = torch.where(pos, sinhc_r, sinc_r)
        ctx.save_for_backward(u, c_plus, s_plus, c_minus, s_minus)
        return c_plus, s_plus, c_minus, s_minus

    @staticmethod
    def backward(ctx, g_cp: Tensor, g_sp: Tensor, g_cm: Tensor, g_sm: Tensor) -> Tensor:  # type: ignore[override]
        u, c_plus, s_plus, c_minus, s_minus = ctx.saved_tensors
        ds_plus = sinc_derivative(u, c_plus, s_plus)
        ds_minus = -sinc_derivative(-u, c_minus, s_minus)
        return 0.5 * (g_cm * s_minus - g_cp * s_plus) + g_sp * ds_plus + g_sm * ds_minus


def sinc_derivative(u: Tensor, c: Tensor, s: Tensor) -> Tensor:
    """``ds/du`` of ``s(u) = sin sqrt(u) / sqrt(u)`` given ``C(u)`` and ``s(u)``.

    ``(C - s) / (2u)``, with its Taylor series near ``u = 0`` where the closed
    form cancels.
    """
    small = u.abs() < _SERIES_LIMIT
    u_safe = torch.where(small, torch.ones_like(u), u)
    # s'(v) = -1/6 + v/60 - v^2/1680 + v^3/90720 - ...
    series = -1 / 6 + u * (1 / 60 - u * (1 / 1680 - u / 90720))
    return torch.where(small, series, (c - s) * (0.5 / u_safe))


def focusing_functions(u: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``(C(u), s(u), C(-u), s(-u))``: ``C = cos sqrt(u)``, ``s = sin sqrt(u)/sqrt(u)``.

    For ``u = k L^2`` the thick-lens map of ``x'' = -k x`` over ``L`` is
    ``[[C, L s], [-k L s, C]]``; ``-u`` gives the other transverse plane.
    """
    return _FocusingFunctions.apply(u)


def quad_body(
    coords: Coords, k1: Tensor, length: Tensor, mu2: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor | None]:
    """Chromatic thick quadrupole body in the paraxial approximation.

    Each particle sees ``k = k1 / (1 + pz)``; with ``x' = px / (1 + pz)`` the
    transverse motion is the thick-lens solution, and ``z`` changes by
    ``L (beta / beta0 - 1) - 1/2 int (x'^2 + y'^2) ds`` (integrated analytically:
    ``int x'^2 = [L (k x^2 + x'^2) + C S (x'^2 - k x^2)] / 2 - k x x' S^2``).
    Returns the new ``(x, px, y, py, z)`` (``z`` None if given None).
    """
    x, px, y, py, z, pz = coords
    inv_p = 1.0 / (1.0 + pz)
    k = k1 * inv_p
    c_x, s_x, c_y, s_y = focusing_functions(k * length.square())
    s_x = s_x * length
    s_y = s_y * length
    xp = px * inv_p
    yp = py * inv_p
    if z is not None:  # (None: not needed downstream)
        z = _quad_z(z, x, xp, y, yp, pz, k, length, (c_x, s_x, c_y, s_y), mu2)
    x_new = c_x * x + s_x * xp
    px_new = c_x * px - k1 * s_x * x
    y_new = c_y * y + s_y * yp
    py_new = c_y * py + k1 * s_y * y
    return x_new, px_new, y_new, py_new, z


def _quad_z(
    z: Tensor,
    x: Tensor,
    xp: Tensor,
    y: Tensor,
    yp: Tensor,
    pz: Tensor,
    k: Tensor,
    length: Tensor,
    focusing: tuple[Tensor, Tensor, Tensor, Tensor],
    mu2: Tensor,
) -> Tensor:
    """The new ``z`` of :func:`quad_body` (``focusing``: ``C, L s`` of x and y)."""
    c_x, s_x, c_y, s_y = focusing
    a_x = k * x.square()
    b_x = xp.square()
    a_y = -k * y.square()
    b_y = yp.square()
    i_x = (
        0.5 * (length * (a_x + b_x) + c_x * s_x * (b_x - a_x))
        - k * x * xp * s_x.square()
    )
    i_y = (
        0.5 * (length * (a_y + b_y) + c_y * s_y * (b_y - a_y))
        + k * y * yp * s_y.square()
    )
    return z + length * velocity_z_shift(pz, mu2) - 0.5 * (i_x + i_y)


class _StackColumns(torch.autograd.Function):
    """``torch.stack`` of broadcast columns whose backward drops all-zero grads.

    A column whose incoming gradient is exactly zero (e.g. ``z`` when only a
    screen image of ``x, y`` is differentiated) gets ``None``, so autograd skips
    the chain of operations that produced it. The result is unchanged. Only
    on the CPU: elsewhere the test would read the device once per column.
    """

    @staticmethod
    def forward(ctx, *cols: Tensor) -> Tensor:  # type: ignore[override]
        ctx.shapes = [c.shape for c in cols]
        return torch.stack(torch.broadcast_tensors(*cols), dim=-1)

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        grads: list[Tensor | None] = []
        for i, shape in enumerate(ctx.shapes):
            g = grad[..., i]
            # a column's gradient that is all zero becomes None (less work
            # upstream); testing it reads the device, so only on the CPU
            if not ctx.needs_input_grad[i] or (
                cheap_reads(g) and not bool(g.detach().any())
            ):
                grads.append(None)
            else:
                grads.append(g.sum_to_size(shape))
        return tuple(grads)


def stack_columns(coords: Sequence[Tensor]) -> Tensor:
    """Stack six broadcastable columns into particles ``(*K, N, 6)``.

    Columns that are still the ``unbind`` views of one contiguous ``(..., 6)``
    tensor are returned as that tensor, without a copy.
    """
    base = coords[0]._base
    if (
        base is not None
        and base.dim() >= 1
        and base.shape[-1] == 6
        and base.is_contiguous()
        and all(
            c._base is base
            and c.shape == base.shape[:-1]
            and c.storage_offset() == base.storage_offset() + i
            for i, c in enumerate(coords)
        )
    ):
        return base
    return _StackColumns.apply(*coords)


def cheap_reads(t: Tensor) -> bool:
    """Whether reading ``t``'s values on the host is cheap (no device sync)."""
    return t.device.type == "cpu"


def none_true(mask: Tensor) -> bool:
    """True if ``mask`` holds no True and reading it costs no device sync.

    False off the CPU (the caller then takes the path that handles both).
    """
    return cheap_reads(mask) and not bool(mask.any())


#: ``id(tensor) -> (weak reference, version, answer)`` of :func:`is_zero` off
#: the CPU (an entry leaves when its tensor is freed).
_ZERO_MEMO: dict[int, tuple[weakref.ref, int, bool]] = {}


def is_zero(value: Tensor) -> bool:
    """True if ``value`` is a constant exactly zero (never for trainable tensors).

    Off the CPU the answer is remembered for that very tensor object and its
    version counter (an in-place change makes it ask again): an element's
    offsets and roll are asked at every pass, and each answer reads the device.
    """
    if value.requires_grad:
        return False
    if cheap_reads(value) or value.is_inference():  # (no version counter)
        return not bool(value.detach().any())
    key = id(value)
    memo = _ZERO_MEMO.get(key)
    if memo is not None and memo[0]() is value and memo[1] == value._version:
        return memo[2]
    answer = not bool(value.detach().any())
    ref = weakref.ref(value, lambda _, key=key: _ZERO_MEMO.pop(key, None))
    _ZERO_MEMO[key] = (ref, value._version, answer)
    return answer


def to_element_frame(
    x: Tensor, px: Tensor, y: Tensor, py: Tensor, dx: Tensor, dy: Tensor, tilt: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Lab -> element frame: subtract offsets ``(dx, dy)`` then roll by ``tilt``."""
    c, s = tilt.cos(), tilt.sin()
    x, y = x - dx, y - dy
    return c * x + s * y, c * px + s * py, -s * x + c * y, -s * px + c * py


def to_lab_frame(
    x: Tensor, px: Tensor, y: Tensor, py: Tensor, dx: Tensor, dy: Tensor, tilt: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Element -> lab frame: the inverse of :func:`to_element_frame`."""
    c, s = tilt.cos(), tilt.sin()
    return c * x - s * y + dx, c * px - s * py, s * x + c * y + dy, s * px + c * py


def roll_matrix(tilt: Tensor) -> Tensor:
    """Affine map ``(*K, 7, 7)`` of the lab -> element roll by ``tilt`` [rad]."""
    c, s = tilt.cos(), tilt.sin()
    rot = affine_identity(tilt.shape, tilt)
    for i in (0, 1):
        rot[..., i, i] = c
        rot[..., i, i + 2] = s
        rot[..., i + 2, i] = -s
        rot[..., i + 2, i + 2] = c
    return rot


def lab_frame_map(
    r: Tensor, tilt: Tensor, dx: Tensor | None = None, dy: Tensor | None = None
) -> Tensor:
    """An element-frame affine map ``r (*K, 7, 7)`` seen from the lab frame.

    ``roll(tilt)^T r roll(tilt)``, then shifted by the offsets ``(dx, dy)`` [m]
    of the element (if given): the map of :func:`to_element_frame`, ``r`` and
    :func:`to_lab_frame` in turn.
    """
    rot = roll_matrix(tilt)
    out = rot.transpose(-1, -2) @ r @ rot
    if dx is None and dy is None:
        return out
    shift = affine_identity(out.shape[:-2], out)
    if dx is not None:
        shift[..., 0, 6] = dx
    if dy is not None:
        shift[..., 2, 6] = dy
    return shift @ out


def affine_identity(shape: Sequence[int], like: Tensor) -> Tensor:
    """A fresh identity affine map ``(*shape, 7, 7)`` in the dtype of ``like``."""
    eye = torch.eye(7, dtype=like.dtype, device=like.device)
    return eye.expand(*shape, 7, 7).clone()
