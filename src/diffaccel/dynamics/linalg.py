"""Linear algebra that gives the same answer on every call."""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["lstsq"]


def lstsq(a: Tensor, b: Tensor) -> Tensor:
    """Least-squares solution ``x`` of ``a x = b``, the same on every call.

    On the CPU torch's default driver (``gelsy``, pivoted QR) is not
    reproducible: the same float64 inputs give different last bits from call
    to call (measured with torch 2.13 + MKL), and a rank-deficient system a
    different solution. A seeded reconstruction then started from a different
    Gaussian guess on a two-setting 6D file (its pz variance 6.6e-6 or 6.3e-6)
    and ended elsewhere. The SVD driver ``gelsd`` is reproducible and returns
    the minimum-norm solution, its rank cut at the default tolerance; other
    devices keep their one driver (``gels``, full rank only).

    Shapes:
        ``a (..., M, N)``, ``b (..., M, K)`` -> ``(..., N, K)``.

    Raises:
        ValueError: if ``a`` or ``b`` holds NaN or infinite values (LAPACK
            would print its own error and torch fail an internal assert).
    """
    if not (bool(torch.isfinite(a).all()) and bool(torch.isfinite(b).all())):
        raise ValueError("least squares: the system holds NaN or infinite values.")
    if a.device.type == "cpu":
        return torch.linalg.lstsq(a, b, driver="gelsd").solution
    return torch.linalg.lstsq(a, b).solution
