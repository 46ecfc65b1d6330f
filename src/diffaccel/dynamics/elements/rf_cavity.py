"""Accelerating RF cavity (Bmad rfcavity convention: fixed reference momentum)."""

from __future__ import annotations

import math
from typing import Any

from torch import Tensor

from diffaccel.dynamics.constants import SPEED_OF_LIGHT
from diffaccel.dynamics.elements._kernels import exact_drift, is_zero
from diffaccel.dynamics.elements._tracked_map import tracked_affine_map
from diffaccel.dynamics.elements.element import Coords, Element, bcast
from diffaccel.dynamics.species import ELECTRON, Species

__all__ = ["RFCavity"]


class RFCavity(Element):
    """Accelerating (TM010-like) cavity as Bmad's ``rfcavity`` tracks it.

    **Reference momentum:** unchanged through the element (Bmad's ``rfcavity``,
    not ``lcavity``): every particle's energy gain, the reference particle's
    included, shows up in its ``pz`` relative to the same ``p0c``. Downstream
    magnets therefore keep their strengths at ``p0c`` while the RF phase is
    scanned, as fixed magnet currents do.

    **Energy kick:** a particle at RF phase ``phi = phase + k z / beta``
    (``k = 2 pi frequency / c``, ``beta`` its velocity, ``z = -beta c t``: the
    head, ``z > 0``, arrives early) gains ``dE = |q| voltage sin(phi)``;
    ``phase = pi / 2`` is on crest and ``phase = 0`` the zero crossing, where
    the head gains energy (Bmad's ``phi0 = phase / (2 pi)``). Positive
    ``voltage`` accelerates the tracked species on crest.

    **Body:** ``num_steps`` drifts of ``length / num_steps`` with energy kicks
    ``dE / num_steps`` between them and ``dE / (2 num_steps)`` at both ends
    (Bmad's bmad_standard slicing; its default is one step). An energy kick
    sets the new ``pz`` and rescales ``z`` by ``beta_new / beta_old`` (the
    arrival time is kept). No transverse fields: neither RF focusing nor the
    entrance/exit fringe kicks, nor coupler kicks.

    Args:
        name: Element name.
        length: Length [m], >= 0.
        voltage: Peak voltage [V].
        frequency: RF frequency [Hz], >= 0.
        phase: RF phase of the reference particle [rad].
        num_steps: Number of slices (an integer >= 1; not a tensor).

    Shapes:
        ``track``: ``(*K, N, 6) -> (*K, N, 6)``; ``transfer_map``: ``(*K, 7, 7)``.
        The map's offset column holds the reference particle's energy gain.

    Example:
        >>> cav = RFCavity("C1", length=1.0, voltage=1e6, frequency=2.856e9)
        >>> cav.transfer_map(1e8)[5, 4].item() > 0  # zero crossing: the head gains
        True
    """

    param_names = ("length", "voltage", "frequency", "phase")
    nonnegative_params = (("length", "m"), ("frequency", "Hz"))
    config_names = ("num_steps",)

    def __init__(
        self,
        name: str,
        length: Tensor | float = 0.0,
        voltage: Tensor | float = 0.0,
        frequency: Tensor | float = 0.0,
        phase: Tensor | float = 0.0,
        num_steps: int = 1,
    ) -> None:
        super().__init__(
            name, length=length, voltage=voltage, frequency=frequency, phase=phase
        )
        if isinstance(num_steps, bool) or not isinstance(num_steps, int):
            raise ValueError(
                f"{self.owner}: num_steps must be an integer >= 1; got {num_steps!r}."
            )
        if num_steps < 1:
            raise ValueError(f"{self.owner}: num_steps must be >= 1; got {num_steps}.")
        self.num_steps = num_steps

    def _config(self) -> dict[str, Any]:
        return {"num_steps": self.num_steps}

    def to_spec(self) -> dict[str, Any]:
        """As :meth:`Element.to_spec`, with ``num_steps``."""
        return {**super().to_spec(), "num_steps": self.num_steps}

    def track_columns(self, coords: Coords, p0c: Tensor, species: Species) -> Coords:
        """Unchecked column tracking (see :meth:`Element.track_columns`)."""
        like = coords[0]
        n = self.num_steps
        a = abs(species.charge) * bcast(self.voltage, like) / p0c.unsqueeze(-1)
        k = 2 * math.pi * bcast(self.frequency, like) / SPEED_OF_LIGHT
        phase = bcast(self.phase, like)
        step = bcast(self.length, like) / n
        mu2 = (species.mass_ev / p0c).square().unsqueeze(-1)
        x, px, y, py, z, pz = coords
        for i in range(n + 1):
            share = a / (2 * n) if i in (0, n) else a / n
            z, pz = _energy_kick(z, pz, share, k, phase, mu2)
            if i < n:
                x, y, z = exact_drift(x, px, y, py, z, pz, step, mu2)
        return x, px, y, py, z, pz

    def transfer_map(self, p0c: Tensor | float, species: Species = ELECTRON) -> Tensor:
        """Affine map about the reference orbit, shape ``(*K, 7, 7)``.

        The Jacobian of :meth:`track` at ``u = 0`` (by differentiation); the
        offset column is the reference particle's ``pz`` gain (and its ``z``).
        """
        return tracked_affine_map(self, p0c, species)

    def linear_map_is_exact(self, monochromatic: bool) -> bool:
        """Only when switched off (then as a drift)."""
        return is_zero(self.voltage) and (monochromatic or is_zero(self.length))


def _energy_kick(
    z: Tensor, pz: Tensor, a: Tensor, k: Tensor, phase: Tensor, mu2: Tensor
) -> tuple[Tensor, Tensor]:
    """Energy gain ``a sin(phase + k z / beta)`` [p0c]; new ``(z, pz)``."""
    p = 1.0 + pz
    energy = (p.square() + mu2).sqrt()  # E / p0c
    beta = p / energy
    d_energy = a * (phase + k * z / beta).sin()
    energy_new = energy + d_energy
    p_new = (energy_new.square() - mu2).sqrt()
    # p_new - p without cancellation: (E_new^2 - E^2) / (p_new + p)
    pz = pz + d_energy * (energy_new + energy) / (p_new + p)
    z = z * (p_new / energy_new) / beta
    return z, pz
