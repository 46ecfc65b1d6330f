"""Conversions between Bmad coordinates and other particle formats (pure arrays).

Bmad (ours): ``(x [m], px = Px/P0, y [m], py = Py/P0, z = -beta c (t - t0) [m],
pz = (P - P0)/P0)`` about the reference momentum ``p0c`` [eV].

cheetah (0.8.4): ``(x, px, y, py, tau, delta)`` with the same transverse columns,
``tau = c (t - t0) = -z / beta`` [m] and ``delta = (E - E0) / p0c``; cheetah
describes the reference by its total energy ``E0`` [eV] (see :func:`p0c_to_energy`).

openPMD-beamphysics (``ParticleGroup``): ``x, y, z`` [m], ``px, py, pz`` [eV/c]
(momentum components), ``t`` [s], ``weight`` [C] (macro-charge). Conversions here
describe particles at a fixed longitudinal position ``s`` (all ``z`` equal), as at
a screen; the HDF5 reading and writing lives in ``diffaccel.data``.

Shapes: ``(..., N, 6)`` for coordinate tensors, ``(..., N)`` for openPMD columns.
Results are in the input dtype; half-precision particles (float16, bfloat16)
are converted in float32 and give float32 (a momentum of 43e6 eV/c is beyond
float16's largest number).
"""

from __future__ import annotations

import torch
from torch import Tensor

from diffaccel.dynamics._validate import as_p0c, check_particles, compute_dtype
from diffaccel.dynamics.constants import SPEED_OF_LIGHT
from diffaccel.dynamics.species import ELECTRON, Species

__all__ = [
    "ELEMENTARY_CHARGE",
    "bmad_to_cheetah",
    "bmad_to_openpmd",
    "cheetah_to_bmad",
    "energy_to_p0c",
    "openpmd_to_bmad",
    "p0c_to_energy",
]

#: Elementary charge [C].
ELEMENTARY_CHARGE = 1.602176634e-19

_OPENPMD_KEYS = ("x", "px", "y", "py", "z", "pz", "t")


def p0c_to_energy(p0c: Tensor | float, species: Species = ELECTRON) -> Tensor:
    """Total energy ``E0 = sqrt(p0c^2 + (m c^2)^2)`` [eV] of the reference."""
    p0c = (
        torch.as_tensor(p0c, dtype=torch.float64)
        if not isinstance(p0c, Tensor)
        else p0c
    )
    p0c = as_p0c(p0c, p0c)
    return (p0c.square() + species.mass_ev**2).sqrt()


def energy_to_p0c(energy: Tensor | float, species: Species = ELECTRON) -> Tensor:
    """Reference momentum ``p0c = sqrt(E0^2 - (m c^2)^2)`` [eV] from total energy."""
    e = (
        energy
        if isinstance(energy, Tensor)
        else torch.as_tensor(energy, dtype=torch.float64)
    )
    if not bool((e > species.mass_ev).all()):
        raise ValueError(
            f"Total energy must exceed the rest energy {species.mass_ev} eV of "
            f"{species.name}s; got {e.detach().cpu().tolist()} eV."
        )
    return (e.square() - species.mass_ev**2).sqrt()


def _gamma_beta(p: Tensor, mass: float) -> tuple[Tensor, Tensor]:
    """Energy ``E`` [eV] and velocity ``beta`` for momenta ``p`` [eV/c]."""
    e = (p.square() + mass**2).sqrt()
    return e, p / e


def bmad_to_cheetah(
    particles: Tensor, p0c: Tensor | float, species: Species = ELECTRON
) -> Tensor:
    """Bmad ``(x, px, y, py, z, pz)`` -> cheetah ``(x, px, y, py, tau, delta)``.

    Args:
        particles: Bmad coordinates ``(..., N, 6)``.
        p0c: Reference momentum times c [eV], scalar or ``(...,)``.
        species: Particle species (sets the mass).

    Returns:
        cheetah coordinates ``(..., N, 6)`` (cheetah 0.8.4 adds a seventh column
        of ones itself).

    Example:
        >>> p = torch.tensor([[0.0, 0.0, 0.0, 0.0, 1e-3, 1e-2]], dtype=torch.float64)
        >>> back = cheetah_to_bmad(bmad_to_cheetah(p, 1e8), 1e8)
        >>> torch.allclose(back, p, rtol=0, atol=1e-15)
        True
    """
    check_particles(particles)
    particles = particles.to(compute_dtype(particles))  # float16: p0c overflows
    p0c = as_p0c(p0c, particles).unsqueeze(-1)
    z, pz = particles[..., 4], particles[..., 5]
    e, beta = _gamma_beta((1.0 + pz) * p0c, species.mass_ev)
    e0 = (p0c.square() + species.mass_ev**2).sqrt()
    tau = -z / beta
    delta = (e - e0) / p0c
    return torch.cat((particles[..., :4], tau.unsqueeze(-1), delta.unsqueeze(-1)), -1)


def cheetah_to_bmad(
    particles: Tensor, p0c: Tensor | float, species: Species = ELECTRON
) -> Tensor:
    """cheetah ``(x, px, y, py, tau, delta)`` -> Bmad ``(x, px, y, py, z, pz)``.

    Args:
        particles: cheetah coordinates ``(..., N, 6)`` or ``(..., N, 7)`` (the
            seventh column of ones is dropped).
        p0c: Reference momentum times c [eV]; from a cheetah beam's energy use
            :func:`energy_to_p0c`.
        species: Particle species (sets the mass).
    """
    if particles.dim() >= 2 and particles.shape[-1] == 7:
        particles = particles[..., :6]
    check_particles(particles, check_momentum=False)  # delta: checked below
    particles = particles.to(compute_dtype(particles))
    p0c = as_p0c(p0c, particles).unsqueeze(-1)
    tau, delta = particles[..., 4], particles[..., 5]
    e0 = (p0c.square() + species.mass_ev**2).sqrt()
    e = e0 + delta * p0c
    if not bool((e > species.mass_ev).all()):
        raise ValueError("delta gives particle energies below the rest energy.")
    p = (e.square() - species.mass_ev**2).sqrt()
    z = -(p / e) * tau
    pz = (p - p0c) / p0c
    return torch.cat((particles[..., :4], z.unsqueeze(-1), pz.unsqueeze(-1)), -1)


def bmad_to_openpmd(
    particles: Tensor,
    p0c: Tensor | float,
    species: Species = ELECTRON,
    *,
    s: float = 0.0,
    t_ref: float = 0.0,
    total_charge: float | None = None,
) -> dict[str, Tensor]:
    """Bmad coordinates -> openPMD-beamphysics columns at position ``s``.

    Args:
        particles: Bmad coordinates ``(..., N, 6)``.
        p0c: Reference momentum times c [eV].
        species: Particle species.
        s: Longitudinal position of the particles [m] (the openPMD ``z``).
        t_ref: Arrival time of the reference particle [s].
        total_charge: Bunch charge [C] (magnitude), shared equally; default one
            species charge per macro-particle.

    Returns:
        ``{"x", "px", "y", "py", "z", "pz", "t", "weight"}``, each ``(..., N)``,
        in m, eV/c, s and C.
    """
    check_particles(particles)
    particles = particles.to(compute_dtype(particles))
    p0c = as_p0c(p0c, particles).unsqueeze(-1)
    x, px, y, py, z, pz = particles.unbind(-1)
    p = (1.0 + pz) * p0c
    px_ev, py_ev = px * p0c, py * p0c
    pl2 = p.square() - px_ev.square() - py_ev.square()
    if not bool((pl2 > 0).all()):
        raise ValueError(
            "Some particles have |(px, py)| >= 1 + pz (no forward motion)."
        )
    _, beta = _gamma_beta(p, species.mass_ev)
    n = particles.shape[-2]
    if total_charge is None:
        w = abs(species.charge) * ELEMENTARY_CHARGE
    else:
        w = abs(float(total_charge)) / n
    return {
        "x": x,
        "px": px_ev,
        "y": y,
        "py": py_ev,
        "z": torch.full_like(x, float(s)),
        "pz": pl2.sqrt(),
        "t": t_ref - z / (beta * SPEED_OF_LIGHT),
        "weight": torch.full_like(x, w),
    }


def openpmd_to_bmad(
    columns: dict[str, Tensor],
    p0c: Tensor | float | None = None,
    species: Species = ELECTRON,
    *,
    t_ref: float | None = None,
) -> tuple[Tensor, Tensor]:
    """openPMD-beamphysics columns (at one ``z``) -> Bmad coordinates.

    Args:
        columns: ``x, px, y, py, z, pz, t`` (``weight`` is ignored), each
            ``(..., N)`` in m, eV/c and s; all ``z`` must be equal (particles at a
            fixed position, as at a screen).
        p0c: Reference momentum times c [eV]; default the mean total momentum.
        species: Particle species.
        t_ref: Reference arrival time [s]; default the mean of ``t``.

    Returns:
        ``(particles (..., N, 6), p0c)``.

    Raises:
        ValueError: for a missing column or particles at different ``z``.
    """
    missing = [k for k in _OPENPMD_KEYS if k not in columns]
    if missing:
        raise ValueError(
            f"openPMD columns missing: {missing}; need {list(_OPENPMD_KEYS)}."
        )
    c = {k: torch.as_tensor(columns[k]) for k in _OPENPMD_KEYS}
    if not bool(torch.isclose(c["z"], c["z"][..., :1], rtol=0, atol=1e-12).all()):
        raise ValueError(
            "openPMD particles must share one z (fixed-s, as at a screen); "
            "these are at different z, e.g. a fixed-time snapshot. Drift them first."
        )
    p = (c["px"].square() + c["py"].square() + c["pz"].square()).sqrt()
    if p0c is None:
        p0c = p.mean(-1)
    p0c = as_p0c(p0c, p)
    t_ref_t = c["t"].mean(-1, keepdim=True) if t_ref is None else t_ref
    _, beta = _gamma_beta(p, species.mass_ev)
    p0 = p0c.unsqueeze(-1)
    particles = torch.stack(
        (
            c["x"],
            c["px"] / p0,
            c["y"],
            c["py"] / p0,
            -beta * SPEED_OF_LIGHT * (c["t"] - t_ref_t),
            p / p0 - 1.0,
        ),
        dim=-1,
    )
    check_particles(particles)
    return particles, p0c
