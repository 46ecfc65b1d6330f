"""Synthetic hysteretic magnet and measurement protocol, for demos and tests.

The magnet is a :class:`PreisachModel` with a known density: a ridge along the
diagonal of the Preisach plane (narrow hysterons dominate, as in soft iron) that
fades towards high fields, plus a weak uniform floor. The protocol mimics the
SLAC LCLS-II quadrupole measurements: a major loop, minor loops and an
alternating "memory trial" sequence, all starting from negative saturation.

:func:`symmetric_magnet` builds magnets with a known *symmetric* density
(``mu(alpha, beta) = mu(-beta, -alpha)`` about zero input), and
:func:`bipolar_quadrupole_case` and :func:`bh_loop_case` draw the acceptance
cases of ``benchmarks/preisach_acceptance.py`` from them: random magnets (one
per seed) plus noise, in the shape of a bipolar quadrupole cycle and of a
soft-iron B-H loop.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from diffaccel.hysteresis.mesh import PreisachMesh
from diffaccel.hysteresis.preisach import PreisachModel

__all__ = [
    "MU0",
    "bh_loop_case",
    "bipolar_quadrupole_case",
    "soft_iron_loop",
    "symmetric_magnet",
    "synthetic_magnet",
    "synthetic_measurement",
    "synthetic_protocol",
]

#: Vacuum permeability [T m / A].
MU0 = 4e-7 * math.pi
_SHAPES = ("tanh", "atan", "erf")


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


def symmetric_magnet(
    half_range: float,
    ridge: float,
    spread: float,
    floor: float,
    slope: float,
    scale: float,
    full_scale: float,
    offset: float = 0.0,
    initial_state: str = "negative",
    n: int = 40,
    dtype: torch.dtype = torch.float64,
) -> PreisachModel:
    """A Preisach magnet with a known density symmetric about zero input.

    Density ``exp(-(w / ridge)^2 / 2) exp(-(c / spread)^2 / 2) + floor`` with
    ``w = alpha - beta`` and ``c`` the distance of ``(alpha + beta) / 2`` from
    the centre, on ``[-half_range, half_range]``: narrow hysterons dominate and
    switch near zero field, as in soft iron.

    Args:
        half_range: The magnet's own input range is ``+-half_range`` [input units].
        ridge: Width of the density across the diagonal [1, normalised].
        spread: Width along the diagonal [1, normalised].
        floor: Uniform part of the density [1].
        slope: Linear (reversible) term [normalised output per full range].
        scale: Hysteretic part [normalised output].
        full_scale: Output normalisation [output units].
        offset: Output offset [normalised output].
        initial_state: Its initial state kind.
        n: Cells per axis of its mesh.
        dtype: Floating dtype.

    Returns:
        The model, symmetric by construction (``model.symmetric`` is True).
    """
    mesh = PreisachMesh.triangular(n=n, dtype=dtype)
    model = PreisachModel(
        mesh,
        input_range=(-half_range, half_range),
        initial_state=initial_state,
        symmetric=True,
        dtype=dtype,
    )
    width = mesh.alpha - mesh.beta
    centre = 0.5 * (mesh.alpha + mesh.beta) - 0.5
    density = (
        torch.exp(-0.5 * (width / ridge) ** 2)
        * torch.exp(-0.5 * (centre / spread) ** 2)
        + floor
    )
    with torch.no_grad():
        model.density = density
        model.output_loc.fill_(0.0)
        model.output_scale.fill_(full_scale)
        model.slope.fill_(slope)
        model.scale.fill_(scale)
        model.offset.fill_(offset)
    return model


def _uniform(gen: torch.Generator, lo: float, hi: float) -> float:
    return lo + (hi - lo) * float(torch.rand((), generator=gen, dtype=torch.float64))


def bipolar_quadrupole_case(
    seed: int = 0, i_max: float = 6.0, step: float = 1.0
) -> tuple[Tensor, Tensor, int, PreisachModel]:
    """A bipolar quadrupole cycled ``-i_max -> +i_max -> -i_max``, with noise.

    The magnet (drawn from ``seed``) saturates beyond ``1.1 .. 1.5 i_max``, its
    hysteresis is 2-8 % of full scale and the noise 1e-4 to 5e-4 of full
    scale. With the defaults: 25 points, the first 17 (the ascending branch and
    four points back down) for fitting, the last 8 to predict.

    Returns:
        ``(current [A] (T,), field [T m] (T,), n_train, true magnet)``; the
        magnet starts saturated negative (``initial_state="negative"``).
    """
    gen = torch.Generator().manual_seed(seed)
    magnet = symmetric_magnet(
        half_range=i_max * _uniform(gen, 1.1, 1.5),
        ridge=_uniform(gen, 0.05, 0.2),
        spread=_uniform(gen, 0.2, 0.6),
        floor=_uniform(gen, 0.005, 0.05),
        slope=1.0,
        scale=_uniform(gen, 0.02, 0.08),
        full_scale=_uniform(gen, 0.5, 2.0),
        offset=-0.5,
    )
    up = torch.arange(-i_max, i_max + 0.5 * step, step, dtype=torch.float64)
    current = torch.cat([up, up.flip(0)[1:]])
    with torch.no_grad():
        field = magnet(current)
    noise = _uniform(gen, 1e-4, 5e-4) * float(magnet.output_scale)
    field = field + noise * torch.randn(field.shape, generator=gen, dtype=field.dtype)
    n_train = up.numel() + 4
    return current, field, n_train, magnet


def bh_loop_case(
    seed: int = 0, h_max: float = 1.0, points: int = 15
) -> tuple[Tensor, Tensor, int, PreisachModel]:
    """A soft-iron B-H loop from the demagnetized state, with noise.

    Virgin curve ``0 -> h_max`` and first descent ``h_max -> 0`` (``2 points +
    1`` rows, for fitting), then the negative half ``0 -> -h_max -> 0`` (``2
    points`` rows, to predict). The sample (drawn from ``seed``) saturates
    beyond ``1.1 .. 1.6 h_max``; its reversible part is 2-10 % of the
    hysteretic one and the noise 1e-3 to 3e-3 of the loop's range.

    Returns:
        ``(H [A/m] (T,), B [T] (T,), n_train, true sample)``; the sample starts
        demagnetized (``initial_state="demagnetized"``).
    """
    gen = torch.Generator().manual_seed(1000 + seed)
    magnet = symmetric_magnet(
        half_range=h_max * _uniform(gen, 1.1, 1.6),
        ridge=_uniform(gen, 0.03, 0.1),
        spread=_uniform(gen, 0.1, 0.3),
        floor=_uniform(gen, 0.002, 0.02),
        slope=_uniform(gen, 0.02, 0.1),
        scale=1.0,
        full_scale=1.5,
        initial_state="demagnetized",
    )
    up = torch.linspace(0.0, h_max, points + 1, dtype=torch.float64)
    current = torch.cat([up, up.flip(0)[1:], -up[1:], -up.flip(0)[1:]])
    with torch.no_grad():
        field = magnet(current)
    noise = _uniform(gen, 1e-3, 3e-3) * float(field.max() - field.min())
    field = field + noise * torch.randn(field.shape, generator=gen, dtype=field.dtype)
    return current, field, 2 * points + 1, magnet


def _branch(x: Tensor, shape: str) -> Tensor:
    """Sigmoid ``S(x)`` in ``(-1, 1)`` with ``S(0) = 0`` and slope 1 at 0."""
    if shape == "tanh":
        return torch.tanh(x)
    if shape == "atan":  # slow approach to saturation, 1 - 2 / (pi x)
        return (2.0 / math.pi) * torch.atan(0.5 * math.pi * x)
    if shape == "erf":
        return torch.erf(0.5 * math.sqrt(math.pi) * x)
    raise ValueError(f"shape must be one of {_SHAPES}; got {shape!r}.")


def soft_iron_loop(
    h_max: float = 1e5,
    coercive: float = 1e-3,
    width: float = 0.5,
    js: float = 1.8,
    shape: str = "tanh",
    points: int = 120,
    spacing: float = 8.0,
    noise: float = 1e-4,
    seed: int = 0,
) -> tuple[Tensor, Tensor, int]:
    """A B-H major loop of a soft magnetic material, not made by a Preisach model.

    The ascending branch is ``B_up(H) = js * S((H - Hc) / w) + MU0 * H`` and the
    descending one its mirror image ``B_dn(H) = -B_up(-H)``, with ``Hc =
    coercive * 2 h_max`` (the coercive field as a fraction of the range of
    ``H``), ``w = width * Hc`` and ``S`` a sigmoid (``"tanh"``, ``"atan"``:
    approach to saturation as ``1 - a / H``, or ``"erf"``). Rows, in time
    order: the ascending branch from negative remanence ``H = 0`` up to
    ``h_max`` (``points + 1`` rows, the training rows), then the descending
    branch ``h_max -> -h_max`` and the ascending branch back to ``0``. ``H`` is
    sampled as ``h_max sinh(spacing k / points) / sinh(spacing)``: dense near
    zero, spanning ``log10(sinh(spacing) / sinh(spacing / points))`` orders of
    magnitude (4.3 with the defaults, 5.1 with ``spacing=10``), on the same
    ``|H|`` grid on every branch.

    Args:
        h_max: Largest field [A/m].
        coercive: Coercive field as a fraction of the range ``2 h_max`` [1].
        width: Width of the switching region in units of the coercive field [1].
        js: Saturation polarisation [T].
        shape: Sigmoid of the branches.
        points: Steps per half branch.
        spacing: Grid stretch (0 < spacing; larger: denser near zero).
        noise: Gaussian noise on ``B`` as a fraction of ``2 js`` [1].
        seed: Seed of the noise.

    Returns:
        ``(H [A/m] (T,), B [T] (T,), n_train)`` with ``T = 4 points + 1`` and
        ``n_train = points + 1``.
    """
    if shape not in _SHAPES:
        raise ValueError(f"shape must be one of {_SHAPES}; got {shape!r}.")
    f = torch.float64
    k = torch.arange(points + 1, dtype=f)
    grid = h_max * torch.sinh(spacing * k / points) / math.sinh(spacing)
    hc = coercive * 2.0 * h_max
    w = width * hc

    def up(h: Tensor) -> Tensor:
        return js * _branch((h - hc) / w, shape) + MU0 * h

    asc = grid
    desc = torch.cat([grid.flip(0)[1:], -grid[1:]])
    back = -grid.flip(0)[1:]
    h = torch.cat([asc, desc, back])
    b = torch.cat([up(asc), -up(-desc), up(back)])
    gen = torch.Generator().manual_seed(seed)
    b = b + noise * 2.0 * js * torch.randn(b.shape, generator=gen, dtype=f)
    return h, b, points + 1
