"""Transverse deflecting (crab) cavity: streaks the bunch by its z position."""

from __future__ import annotations

import math

from torch import Tensor

from diffaccel.dynamics.constants import SPEED_OF_LIGHT
from diffaccel.dynamics.elements._kernels import (
    affine_identity,
    exact_drift,
    is_zero,
    lab_frame_map,
)
from diffaccel.dynamics.elements.drift import drift_matrix
from diffaccel.dynamics.elements.element import Coords, Element, bcast
from diffaccel.dynamics.species import ELECTRON, Species

__all__ = ["TransverseDeflectingCavity"]


class TransverseDeflectingCavity(Element):
    """Transverse deflecting (crab) cavity: drift(L/2), thin RF kick, drift(L/2).

    Bmad's crab cavity, as cheetah 0.8.4 tracks it. In the cavity frame the kick
    is horizontal: with ``a = -q voltage / p0c`` (``q`` in units of e; ``+V/p0c``
    for electrons), ``k = 2 pi frequency / c`` and the RF phase each particle
    sees, ``phi = phase + k z / beta`` (``beta`` the particle's own velocity,
    ``z = -beta c t``),

    - ``px += a sin(phi)``;
    - its energy changes by ``dE / p0c = a k x cos(phi)`` (Panofsky-Wenzel),
      which sets the new ``pz``; ``z`` is rescaled by ``beta_new / beta_old``.

    ``phase = 0`` is the zero crossing (pure streak, no centroid kick); for
    electrons particles at the head (``z > 0``) are kicked to ``+x`` at tilt 0.
    ``tilt`` rolls the cavity: ``0`` streaks horizontally (couples z to x-px),
    ``pi / 2`` vertically (couples z to y-py).

    Args:
        name: Element name.
        length: Length [m], >= 0.
        voltage: Peak deflecting voltage [V].
        frequency: RF frequency [Hz], >= 0.
        phase: RF phase [rad] (cheetah's ``phase`` is this divided by 2 pi).
        tilt: Roll about the beam axis [rad].

    Shapes:
        ``track``: ``(*K, N, 6) -> (*K, N, 6)``; ``transfer_map``: ``(*K, 7, 7)``.
        The map's offset column holds the centroid kick ``a sin(phase)``.

    Example:
        >>> tdc = TransverseDeflectingCavity("T1", 0.5, 1e6, 2.856e9)
        >>> tdc.transfer_map(1e9)[1, 4].item() > 0  # px grows with z (electrons)
        True
    """

    param_names = ("length", "voltage", "frequency", "phase", "tilt")
    optional_params = ("tilt",)
    nonnegative_params = (("length", "m"), ("frequency", "Hz"))

    def __init__(
        self,
        name: str,
        length: Tensor | float = 0.0,
        voltage: Tensor | float = 0.0,
        frequency: Tensor | float = 0.0,
        phase: Tensor | float = 0.0,
        tilt: Tensor | float = 0.0,
    ) -> None:
        super().__init__(
            name,
            length=length,
            voltage=voltage,
            frequency=frequency,
            phase=phase,
            tilt=tilt,
        )

    @staticmethod
    def _strength(
        voltage: Tensor, frequency: Tensor, p0c: Tensor, species: Species
    ) -> tuple[Tensor, Tensor]:
        """``a = -q V / p0c`` and ``k = 2 pi f / c`` [1/m]."""
        a = -species.charge * voltage.to(p0c) / p0c
        k = 2 * math.pi * frequency.to(p0c) / SPEED_OF_LIGHT
        return a, k

    def track_columns(self, coords: Coords, p0c: Tensor, species: Species) -> Coords:
        """Unchecked column tracking (see :meth:`Element.track_columns`)."""
        like = coords[0]
        a, k = self._strength(self.voltage, self.frequency, p0c, species)
        a, k = a.unsqueeze(-1), k.unsqueeze(-1)
        half = bcast(self.length, like) / 2
        phase = bcast(self.phase, like)
        mu2 = (species.mass_ev / p0c).square().unsqueeze(-1)
        return self._in_element_frame(
            coords, lambda c: _kick_between_drifts(c, a, k, phase, half, mu2)
        )

    def transfer_map(self, p0c: Tensor | float, species: Species = ELECTRON) -> Tensor:
        """Affine map about the reference orbit, shape ``(*K, 7, 7)``.

        The product of the first-order maps of the half drifts and of the kick
        about the reference orbit (``px += a sin(phase)``, ``dpx/dz = dpz/dx =
        a k cos(phase) / beta0``); the Jacobian of :meth:`track` at ``u = 0``
        when ``sin(phase) = 0``. Never exact for images when the voltage is
        non-zero (see :meth:`linear_map_is_exact`).
        """
        length, voltage, frequency, phase, tilt, p0c = self._map_params(
            p0c, *self.param_names
        )
        a, k = self._strength(voltage, frequency, p0c, species)
        mu2 = (species.mass_ev / p0c).square()
        beta0 = (1.0 + mu2).rsqrt()
        d = drift_matrix(length / 2, p0c, species)
        kick = affine_identity(length.shape, length)
        slope = a * k * phase.cos() / beta0
        kick[..., 1, 4] = slope
        kick[..., 5, 0] = slope
        kick[..., 1, 6] = a * phase.sin()
        return lab_frame_map(d @ kick @ d, tilt)

    def linear_map_is_exact(self, monochromatic: bool) -> bool:
        """Only when switched off (``sin(k z)`` and the energy kick are nonlinear)."""
        return is_zero(self.voltage) and (monochromatic or is_zero(self.length))


def _kick_between_drifts(
    coords: Coords, a: Tensor, k: Tensor, phase: Tensor, half: Tensor, mu2: Tensor
) -> Coords:
    """Cavity-frame body: drift ``half``, thin RF kick, drift ``half``."""
    x, px, y, py, z, pz = coords
    x, y, z = exact_drift(x, px, y, py, z, pz, half, mu2)
    p = 1.0 + pz
    energy = (p.square() + mu2).sqrt()  # E / p0c
    beta = p / energy
    rf = phase + k * z / beta
    px = px + a * rf.sin()
    d_energy = a * k * x * rf.cos()
    energy_new = energy + d_energy
    p_new = (energy_new.square() - mu2).sqrt()
    # p_new - p without cancellation: (E_new^2 - E^2) / (p_new + p)
    pz = pz + d_energy * (energy_new + energy) / (p_new + p)
    z = z * (p_new / energy_new) / beta
    x, y, z = exact_drift(x, px, y, py, z, pz, half, mu2)
    return x, px, y, py, z, pz
