"""A reconstructed beam as an openPMD-beamphysics ``ParticleGroup``."""

from __future__ import annotations

from typing import Any

from diffaccel.data.particles_io import particle_group
from diffaccel.reconstruction.ensemble import Reconstruction

__all__ = ["to_particle_group"]


def to_particle_group(
    result: Reconstruction,
    n_particles: int = 100_000,
    *,
    charge_C: float = 1e-12,
    seed: int = 0,
) -> Any:
    """Sample a reconstruction and return the particles as a ``ParticleGroup``.

    The particles are ``result.sample(n_particles, seed=seed)`` (the ensemble
    mixture, Bmad coordinates) at the reconstruction point, with the reference
    momentum and species of the first training scan's forward model; the
    ``ParticleGroup`` is the one openPMD-beamphysics reads from the
    ``particles.h5`` that ``diffaccel reconstruct`` writes for them.

    Args:
        result: A trained (or loaded) reconstruction.
        n_particles: Particles to draw (>= 2).
        charge_C: Total bunch charge [C] (> 0), shared equally.
        seed: Seed of the sampling.

    Returns:
        A ``beamphysics.ParticleGroup`` (SI units: m, eV/c, s, C).

    Raises:
        ImportError: if openPMD-beamphysics is not installed
            (``pip install diffaccel[pmd]``).
    """
    forward = result.forward
    particles = result.sample(n_particles, seed=seed)
    return particle_group(particles, forward.p0c, forward.species, charge_C)
