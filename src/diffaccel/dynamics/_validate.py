"""Input checks shared by the public entry points of ``diffaccel.dynamics``."""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from contextvars import ContextVar

import numpy as np
import torch
from torch import Tensor

_FINITE_CHECKS: ContextVar[bool] = ContextVar("diffaccel_finite_checks", default=True)


@contextmanager
def finite_checks(enabled: bool) -> Iterator[None]:
    """Turn the NaN/infinity checks of particles, scan settings and screen
    positions on or off.

    Each check reads a value back from the device (a host synchronisation on a
    GPU, which a CUDA graph cannot capture). Training turns them off on GPUs
    for the particles it generates itself; a non-finite loss still stops it
    (read every ``report_every`` steps). Shape, dtype and ``p0c`` checks stay.
    """
    token = _FINITE_CHECKS.set(enabled)
    try:
        yield
    finally:
        _FINITE_CHECKS.reset(token)


def finite_checks_enabled() -> bool:
    """Whether the NaN/infinity checks run (see :func:`finite_checks`)."""
    return _FINITE_CHECKS.get()


def is_integer(value: object) -> bool:
    """Whether ``value`` is an integer (Python or NumPy), not a bool."""
    return isinstance(value, numbers.Integral) and not isinstance(
        value, bool | np.bool_
    )


def is_real(value: object) -> bool:
    """Whether ``value`` is a finite real number (Python or NumPy), not a bool."""
    return (
        isinstance(value, numbers.Real)
        and not isinstance(value, bool | np.bool_)
        and math.isfinite(value)
    )


def broadcast_shapes(*shapes: Sequence[int]) -> torch.Size:
    """The broadcast of ``shapes``, as ``torch.broadcast_shapes``.

    Without its first call's import of sympy (about 0.5 s of every process
    that tracks). Raises RuntimeError, as torch does, if they do not broadcast.
    """
    ndim = max((len(s) for s in shapes), default=0)
    out = [1] * ndim
    for shape in shapes:
        for i, d in enumerate(shape, ndim - len(shape)):
            if d == 1 or d == out[i]:
                continue
            if out[i] != 1:
                raise RuntimeError(
                    f"shapes {[tuple(s) for s in shapes]} do not broadcast."
                )
            out[i] = d
    return torch.Size(out)


def check_particles(
    particles: Tensor, *, check_finite: bool = True, check_momentum: bool = True
) -> Tensor:
    """Check that ``particles`` is a floating tensor shaped ``(..., N, 6)``.

    With ``check_finite`` (and :func:`finite_checks` on) also that every
    coordinate is finite and, with ``check_momentum``, that every ``pz > -1``
    (a positive momentum), in one device read.
    """
    if not isinstance(particles, Tensor):
        raise TypeError(
            f"particles must be a torch.Tensor shaped (..., N, 6); "
            f"got {type(particles).__name__}."
        )
    if particles.dim() < 2 or particles.shape[-1] != 6:
        raise ValueError(
            "particles must be shaped (..., N, 6) with Bmad coordinates "
            f"(x, px, y, py, z, pz); got shape {tuple(particles.shape)}."
        )
    if not particles.is_floating_point():
        raise ValueError(
            f"particles must have a floating dtype; got {particles.dtype}."
        )
    if check_finite and finite_checks_enabled():
        # one device read for both checks; the details only on failure
        ok = torch.isfinite(particles).all()
        if check_momentum:
            ok = ok & (particles[..., 5] > -1).all()
        if bool(ok):
            return particles
        bad = (~torch.isfinite(particles)).sum().item()
        if bad:
            raise ValueError(
                f"particles contain {bad} NaN or infinite coordinate(s); "
                "remove or fix them before tracking."
            )
        slow = int((particles[..., 5] <= -1).sum().item())
        raise ValueError(
            f"particles contain {slow} particle(s) with pz <= -1 (zero or negative "
            "momentum; pz = dP/P0); remove or fix them."
        )
    return particles


def as_p0c(p0c: Tensor | float, like: Tensor) -> Tensor:
    """``p0c`` [eV] as a tensor of ``like``'s dtype and device; must be > 0.

    A Python number is checked on the host and filled on the device (no copy
    from the host, no device read); a tensor is checked where it lives.
    """
    dtype = getattr(p0c, "dtype", None)
    if (
        p0c is None
        or isinstance(p0c, str | bytes | bool | np.bool_ | complex)
        or (isinstance(p0c, Tensor) and (p0c.is_complex() or dtype == torch.bool))
        or (isinstance(p0c, np.ndarray) and dtype.kind not in "iuf")
    ):
        raise ValueError(
            "p0c (reference momentum times c) must be a real number or tensor "
            f"[eV]; got {dtype or type(p0c).__name__} {p0c!r}."
        )
    if isinstance(p0c, numbers.Real) and not isinstance(p0c, int | float):
        p0c = float(p0c)  # numpy scalars
    if isinstance(p0c, int | float):
        if not (math.isfinite(p0c) and p0c > 0):
            raise ValueError(
                f"p0c (reference momentum times c) must be finite and > 0 eV; "
                f"got {p0c!r} eV."
            )
        return torch.full((), float(p0c), dtype=like.dtype, device=like.device)
    try:
        t = torch.as_tensor(p0c, dtype=like.dtype, device=like.device)
    except (TypeError, ValueError, RuntimeError) as err:
        raise ValueError(
            "p0c (reference momentum times c) must be a real number or tensor "
            f"[eV]; got {type(p0c).__name__} {p0c!r} ({err})."
        ) from err
    if not bool(torch.isfinite(t).all()) or not bool((t > 0).all()):
        raise ValueError(
            f"p0c (reference momentum times c) must be finite and > 0 eV; "
            f"got {t.detach().cpu().tolist()} eV."
        )
    return t


def check_nonnegative(name: str, value: Tensor, owner: str) -> None:
    """Raise if any element of ``value`` is negative or not finite."""
    v = value.detach()
    if not bool(torch.isfinite(v).all()):
        raise ValueError(f"{owner}: {name} must be finite; got {v.cpu().tolist()}.")
    if bool((v < 0).any()):
        raise ValueError(f"{owner}: {name} must be >= 0; got {v.cpu().tolist()}.")


def check_finite(name: str, value: Tensor, owner: str) -> None:
    """Raise if any element of ``value`` is NaN or infinite."""
    v = value.detach()
    if not bool(torch.isfinite(v).all()):
        raise ValueError(f"{owner}: {name} must be finite; got {v.cpu().tolist()}.")


def as_real_tensor(
    value: object,
    name: str,
    *,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    """``value`` (tensor, array, number or nested list) as a real tensor.

    Complex and boolean values are refused rather than cast (a cast drops the
    imaginary part, or reads True as 1), as the tracking API refuses them.

    Args:
        value: The input.
        name: Its name in the message (e.g. ``"inputs"``).
        dtype: Floating dtype to return (default: the value's own).
        device: Device to return it on.

    Raises:
        ValueError: naming ``name`` and the dtype for complex, boolean, text or
            other non-numeric input.

    Example:
        >>> as_real_tensor([1, 2], "u", dtype=torch.float64).dtype
        torch.float64
        >>> as_real_tensor(torch.tensor([True]), "u")
        Traceback (most recent call last):
        ...
        ValueError: u must be real numbers; got torch.bool (booleans are not cast).
    """
    if isinstance(value, str | bytes):
        raise ValueError(f"{name} must be real numbers; got the text {value!r}.")
    if isinstance(value, np.ndarray) and value.dtype.kind not in "iuf":
        raise ValueError(_not_real(name, f"numpy {value.dtype}"))
    if isinstance(value, bool | np.bool_ | complex | np.complexfloating):
        raise ValueError(_not_real(name, type(value).__name__))
    if not isinstance(value, Tensor):
        try:
            probe = torch.as_tensor(value)  # its dtype says bool or complex
            if not (probe.is_complex() or probe.dtype == torch.bool):
                # straight to ``dtype``: Python floats are exact in float64
                probe = torch.as_tensor(value, dtype=dtype, device=device)
        except (TypeError, ValueError, RuntimeError) as err:
            raise ValueError(
                f"{name} must be real numbers; got {type(value).__name__} ({err})."
            ) from None
        value = probe
    if value.is_complex() or value.dtype == torch.bool:
        raise ValueError(_not_real(name, str(value.dtype)))
    if dtype is None and device is None:
        return value
    return value.to(dtype=dtype or value.dtype, device=device or value.device)


def _not_real(name: str, got: str) -> str:
    kind = "booleans" if "bool" in got else "complex numbers"
    return f"{name} must be real numbers; got {got} ({kind} are not cast)."


def compute_dtype(particles: Tensor) -> torch.dtype:
    """Dtype of results computed from ``particles``: float32 for half
    precision (float16, bfloat16: too few digits for moments of ~1e-9 m rad),
    else their own."""
    if particles.dtype in (torch.float16, torch.bfloat16):
        return torch.float32
    return particles.dtype
