"""Input checks shared by the public entry points of ``diffaccel.dynamics``."""

from __future__ import annotations

import torch
from torch import Tensor


def check_particles(particles: Tensor, *, check_finite: bool = True) -> Tensor:
    """Check that ``particles`` is a floating tensor shaped ``(..., N, 6)``."""
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
    if check_finite and not bool(torch.isfinite(particles).all()):
        bad = (~torch.isfinite(particles)).sum().item()
        raise ValueError(
            f"particles contain {bad} NaN or infinite coordinate(s); "
            "remove or fix them before tracking."
        )
    return particles


def as_p0c(p0c: Tensor | float, like: Tensor) -> Tensor:
    """``p0c`` [eV] as a tensor of ``like``'s dtype and device; must be > 0."""
    t = torch.as_tensor(p0c, dtype=like.dtype, device=like.device)
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
