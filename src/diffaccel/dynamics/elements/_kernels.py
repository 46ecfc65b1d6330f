"""Per-particle maps shared by several elements (private to ``elements``)."""

from __future__ import annotations

from torch import Tensor


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
    z: Tensor,
    pz: Tensor,
    length: Tensor,
    mu2: Tensor,
) -> tuple[Tensor, Tensor, Tensor]:
    """Exact field-free drift; returns the new ``(x, y, z)``.

    ``x' = px / ps`` with ``ps = sqrt((1 + pz)^2 - px^2 - py^2)`` and
    ``dz = L (beta / beta0 - P / ps)``, both written to avoid cancellation.
    """
    p = 1.0 + pz
    pt2 = px.square() + py.square()
    ps = (p.square() - pt2).sqrt()
    x = x + length * px / ps
    y = y + length * py / ps
    dz = length * (velocity_z_shift(pz, mu2) - pt2 / (ps * (p + ps)))
    return x, y, z + dz


def quad_body_coefficients(
    k: Tensor, length: Tensor, small: float = 1e-4
) -> tuple[Tensor, Tensor, Tensor]:
    """``C, S, C'`` of ``u'' = -k u`` over ``length`` (any sign of ``k``).

    ``C = cos(sqrt(k) L)``, ``S = sin(sqrt(k) L) / sqrt(k)``, ``C' = -k S``;
    hyperbolic for ``k < 0``; a Taylor series where ``|k L^2| < small`` keeps the
    values and their gradients finite at ``k = 0``.
    """
    u = k * length.square()
    is_small = u.abs() < small
    u_safe = u.where(~is_small, u.new_ones(()))
    r = u_safe.abs().sqrt()
    pos = u_safe > 0
    c_big = r.cos().where(pos, r.cosh())
    s_over = (r.sin() / r).where(pos, r.sinh() / r)  # S / L
    # Taylor series: C = 1 - u/2 + u^2/24 - u^3/720, S/L = 1 - u/6 + u^2/120 - u^3/5040
    c_small = 1.0 - u / 2.0 * (1.0 - u / 12.0 * (1.0 - u / 30.0))
    s_small = 1.0 - u / 6.0 * (1.0 - u / 20.0 * (1.0 - u / 42.0))
    c = c_small.where(is_small, c_big)
    s = length * s_small.where(is_small, s_over)
    return c, s, -k * s


def quad_body(
    x: Tensor,
    px: Tensor,
    y: Tensor,
    py: Tensor,
    z: Tensor,
    pz: Tensor,
    k1: Tensor,
    length: Tensor,
    mu2: Tensor,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Chromatic thick quadrupole body in the paraxial approximation.

    Each particle sees ``k = k1 / (1 + pz)``; with ``x' = px / (1 + pz)`` the
    transverse motion is the thick-lens solution, and ``z`` changes by
    ``L (beta / beta0 - 1) - 1/2 int (x'^2 + y'^2) ds`` (integrated analytically).
    Returns the new ``(x, px, y, py, z)``.
    """
    p = 1.0 + pz
    k = k1 / p
    cx, sx, dcx = quad_body_coefficients(k, length)
    cy, sy, dcy = quad_body_coefficients(-k, length)
    xp = px / p
    yp = py / p
    # int x'^2 ds = k x0^2 (L - C S) / 2 - k x0 x0' S^2 + x0'^2 (L + C S) / 2
    ix = (
        k * x.square() * (length - cx * sx) / 2.0
        - k * x * xp * sx.square()
        + xp.square() * (length + cx * sx) / 2.0
    )
    iy = (
        -k * y.square() * (length - cy * sy) / 2.0
        + k * y * yp * sy.square()
        + yp.square() * (length + cy * sy) / 2.0
    )
    z = z + length * velocity_z_shift(pz, mu2) - (ix + iy) / 2.0
    x_new = cx * x + sx * xp
    px_new = p * dcx * x + cx * px
    y_new = cy * y + sy * yp
    py_new = p * dcy * y + cy * py
    return x_new, px_new, y_new, py_new, z


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
