"""Particle species: rest energy and charge of the tracked particles."""

from __future__ import annotations

from dataclasses import dataclass

from diffaccel.dynamics.constants import ELECTRON_MASS_EV, PROTON_MASS_EV

__all__ = ["ELECTRON", "POSITRON", "PROTON", "Species"]


@dataclass(frozen=True)
class Species:
    """A particle species, described by its rest energy and charge.

    Args:
        name: Lower-case name, e.g. ``"electron"``; used in files and specs.
        mass_ev: Rest energy m c^2 [eV]; must be positive.
        charge: Charge in units of the elementary charge e (electron: -1).

    Example:
        >>> ELECTRON.mass_ev
        510998.95
        >>> Species.from_name("proton").charge
        1
    """

    name: str
    mass_ev: float
    charge: int

    def __post_init__(self) -> None:
        if not self.mass_ev > 0:
            raise ValueError(f"Species mass must be > 0 eV; got {self.mass_ev} eV.")
        if self.charge == 0:
            raise ValueError("Species charge must be non-zero (neutral particles).")

    @staticmethod
    def from_name(name: str) -> Species:
        """The built-in species called ``name`` (electron, positron or proton)."""
        key = name.strip().lower()
        if key not in _BY_NAME:
            raise ValueError(
                f"Unknown species {name!r}; known species are {sorted(_BY_NAME)}."
            )
        return _BY_NAME[key]


ELECTRON = Species("electron", ELECTRON_MASS_EV, -1)
POSITRON = Species("positron", ELECTRON_MASS_EV, 1)
PROTON = Species("proton", PROTON_MASS_EV, 1)

_BY_NAME = {s.name: s for s in (ELECTRON, POSITRON, PROTON)}
