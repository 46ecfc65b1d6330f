"""Transverse deflecting (crab) cavity: streaks the bunch by its z position."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from diffaccel.dynamics._validate import as_p0c, check_nonnegative
from diffaccel.dynamics.constants import SPEED_OF_LIGHT
from diffaccel.dynamics.elements._kernels import (
    exact_drift,
    is_zero,
    roll_matrix,
    to_element_frame,
    to_lab_frame,
)
from diffaccel.dynamics.elements.drift import drift_matrix
from diffaccel.dynamics.elements.element import Coords, Element, bcast
from diffaccel.dynamics.species import ELECTRON, Species

__all__ = ["TransverseDeflectingCavity"]


class TransverseDeflectingCavity(Element):
    """Transverse deflecting cavity: drift(L/2), thin RF kick, drift(L/2).

    In the cavity frame the kick is vertical:
    ``py += a sin(phase - k0 z)`` and, by Panofsky-Wenzel,
    ``pz -= a k0 y cos(phase - k0 z)`` with ``a = |q| voltage / p0c`` and
    ``k0 = 2 pi frequency / (beta0 c)``. Using the reference velocity ``beta0`` in
    ``k0`` makes the kick exactly symplectic (the per-particle velocity spread is
    neglected in the RF phase). ``phase = 0`` is the zero crossing (pure streak,
    no centroid kick); particles at the head (z > 0) are kicked to -y.

    Args:
        name: Element name.
        length: Length [m], >= 0.
        voltage: Peak deflecting voltage [V].
        frequency: RF frequency [Hz], >= 0.
        phase: RF phase [rad].
        tilt: Roll [rad]; ``0`` streaks in y (couples z to y-py), ``pi / 2``
            streaks in x (couples z to x-px).

    Shapes:
        ``track``: ``(*K, N, 6) -> (*K, N, 6)``; ``transfer_map``: ``(*K, 6, 6)``.
        The linear map omits the constant kick ``a sin(phase)``.

    Example:
        >>> tdc = TransverseDeflectingCavity("T1", 0.5, 1e6, 2.856e9)
        >>> tdc.transfer_map(1e9)[3, 4].item() < 0
        True
    """

    param_names = ("length", "voltage", "frequency", "phase", "tilt")
    optional_params = ("tilt",)

    def __init__(
        self,
        name: str,
        length: Tensor | float = 0.0,
        voltage: Tensor | float = 0.0,
        frequency: Tensor | float = 0.0,
        phase: Tensor | float = 0.0,
        tilt: Tensor | float = 0.0,
    ) -> None:
        super().__init__(name)
        for key, value in (
            ("length", length),
            ("voltage", voltage),
            ("frequency", frequency),
            ("phase", phase),
            ("tilt", tilt),
        ):
            self._set_param(key, value)
        owner = f"TransverseDeflectingCavity {name!r}"
        check_nonnegative("length [m]", self.length, owner)
        check_nonnegative("frequency [Hz]", self.frequency, owner)

    def _strength(self, p0c: Tensor, species: Species) -> tuple[Tensor, Tensor]:
        """``a = |q| V / p0c`` and ``k0 = 2 pi f / (beta0 c)`` [1/m]."""
        mu2 = (species.mass_ev / p0c).square()
        beta0 = 1.0 / (1.0 + mu2).sqrt()
        a = abs(species.charge) * self.voltage.to(p0c) / p0c
        k0 = 2 * math.pi * self.frequency.to(p0c) / (beta0 * SPEED_OF_LIGHT)
        return a, k0

    def track(
        self, particles: Tensor, p0c: Tensor | float, species: Species = ELECTRON
    ) -> Tensor:
        """Track particles ``(*K, N, 6)`` through the cavity (see class docstring)."""
        return self._track_via_columns(particles, p0c, species)

    def track_columns(self, coords: Coords, p0c: Tensor, species: Species) -> Coords:
        """Unchecked column tracking (see :meth:`Element.track_columns`)."""
        x, px, y, py, z, pz = coords
        a, k0 = self._strength(p0c, species)
        a, k0 = a.unsqueeze(-1), k0.unsqueeze(-1)
        half = bcast(self.length, x) / 2
        phase = bcast(self.phase, x)
        mu2 = (species.mass_ev / p0c).square().unsqueeze(-1)
        rolled = not is_zero(self.tilt)
        if rolled:
            zero = x.new_zeros(())
            frame = (zero, zero, bcast(self.tilt, x))
            x, px, y, py = to_element_frame(x, px, y, py, *frame)
        x, y, z = exact_drift(x, px, y, py, z, pz, half, mu2)
        rf = phase - k0 * z
        py = py + a * rf.sin()
        pz = pz - a * k0 * y * rf.cos()
        x, y, z = exact_drift(x, px, y, py, z, pz, half, mu2)
        if rolled:
            x, px, y, py = to_lab_frame(x, px, y, py, *frame)
        return x, px, y, py, z, pz

    def transfer_map(self, p0c: Tensor | float, species: Species = ELECTRON) -> Tensor:
        """Linear map about the reference orbit, shape ``(*K, 6, 6)``."""
        p0c = as_p0c(p0c, self.length)
        a, k0 = self._strength(p0c, species)
        length, phase, tilt, a, k0, p0c = torch.broadcast_tensors(
            self.length, self.phase.to(a), self.tilt.to(a), a, k0, p0c
        )
        d = drift_matrix(length / 2, p0c, species)
        kick = torch.eye(6, dtype=d.dtype, device=d.device).expand_as(d).clone()
        kick[..., 3, 4] = -a * k0 * phase.cos()
        kick[..., 5, 2] = -a * k0 * phase.cos()
        rot = roll_matrix(tilt)
        return rot.transpose(-1, -2) @ d @ kick @ d @ rot
