"""Synthetic hysteretic magnet and measurement protocol, for demos and tests.

The magnet is a :class:`PreisachModel` with a known density: a ridge along the
diagonal of the Preisach plane (narrow hysterons dominate, as in soft iron) that
fades towards high fields, plus a weak uniform floor. The protocol mimics the
SLAC LCLS-II quadrupole measurements: a major loop, minor loops and an
alternating "memory trial" sequence, all starting from negative saturation.
"""

from __future__ import annotations

import torch
from torch import Tensor

from diffaccel.hysteresis.mesh import PreisachMesh
from diffaccel.hysteresis.preisach import PreisachModel

__all__ = ["synthetic_magnet", "synthetic_measurement", "synthetic_protocol"]


def synthetic_magnet(
    i_max: float = 10.0,
    n: int = 30,
    field_per_amp: float = 0.03,
    hysteresis_fraction: float = 0.02,
    dtype: torch.dtype = torch.float64,
) -> PreisachModel:
    """A Preisach magnet with a known density, current range ``[0, i_max]``.

    Args:
        i_max: Maximum current [A].
        n: Cells per axis of the triangular mesh.
        field_per_amp: Linear transfer function [T m / A].
        hysteresis_fraction: Hysteretic part relative to the full-scale field [1].
        dtype: Floating dtype.

    Returns:
        The model, ready to use (no fitting needed).
    """
    mesh = PreisachMesh.triangular(n=n, dtype=dtype)
    model = PreisachModel(mesh, input_range=(0.0, i_max), dtype=dtype)
    width = mesh.alpha - mesh.beta
    centre = 0.5 * (mesh.alpha + mesh.beta)
    density = torch.exp(-0.5 * (width / 0.15) ** 2) * torch.exp(-1.5 * centre) + 0.02
    full = field_per_amp * i_max
    with torch.no_grad():
        model.density = density
        model.output_loc.fill_(0.0)
        model.output_scale.fill_(full)
        model.slope.fill_(1.0)
        model.scale.fill_(hysteresis_fraction)
        model.offset.fill_(hysteresis_fraction)  # field 0 at negative saturation
    return model


def synthetic_protocol(
    i_max: float = 10.0, dtype: torch.dtype = torch.float64
) -> Tensor:
    """Currents of a SLAC-like measurement protocol [A], shape ``(T,)``, T = 106.

    Major loop 0 -> i_max -> 0 in 10 % steps, minor loop 50 % -> 60 % -> 40 % ->
    50 % in 2 % steps, and the memory trial 0, 0.9, 0.1, 0.8, ... 0.5 of i_max.
    """
    f = torch.float64
    up = torch.linspace(0.0, 1.0, 11, dtype=f)
    major = torch.cat([up, up.flip(0)[1:]])
    minor = torch.cat(
        [
            torch.linspace(0.0, 0.5, 6, dtype=f)[1:],
            torch.linspace(0.5, 0.6, 6, dtype=f)[1:],
            torch.linspace(0.6, 0.4, 11, dtype=f)[1:],
            torch.linspace(0.4, 0.5, 6, dtype=f)[1:],
            torch.linspace(0.5, 0.0, 26, dtype=f)[1:],
        ]
    )
    trial = torch.tensor([0.0, 0.9, 0.1, 0.8, 0.2, 0.7, 0.3, 0.6, 0.4, 0.5], dtype=f)
    ramp_down = torch.linspace(0.5, 0.0, 6, dtype=f)[1:]
    again = torch.cat([up[1:], up.flip(0)[1:]])
    seq = torch.cat([major, minor, trial, ramp_down, again])
    return (seq * i_max).to(dtype)


def synthetic_measurement(
    i_max: float = 10.0,
    noise: float = 1e-4,
    seed: int = 0,
    dtype: torch.dtype = torch.float64,
) -> tuple[Tensor, Tensor, PreisachModel]:
    """Noisy field measurements of the synthetic magnet along the synthetic protocol.

    Args:
        i_max: Maximum current [A].
        noise: Gaussian field noise relative to full scale [1].
        seed: Seed of the noise generator.
        dtype: Floating dtype.

    Returns:
        ``(current [A] (T,), field [T m] (T,), true model)``.

    Example:
        >>> current, field, magnet = synthetic_measurement()
        >>> current.shape, field.shape
        (torch.Size([106]), torch.Size([106]))
    """
    model = synthetic_magnet(i_max=i_max, dtype=dtype)
    current = synthetic_protocol(i_max, dtype=dtype)
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        field = model(current)
    full = float(model.output_scale)
    field = field + noise * full * torch.randn(field.shape, generator=gen, dtype=dtype)
    return current, field, model
