"""Beamline elements, one per module."""

from __future__ import annotations

from diffaccel.dynamics.elements.dipole import Dipole
from diffaccel.dynamics.elements.drift import Drift
from diffaccel.dynamics.elements.element import Element
from diffaccel.dynamics.elements.linear_map import LinearMap
from diffaccel.dynamics.elements.quadrupole import Quadrupole
from diffaccel.dynamics.elements.rf_cavity import RFCavity
from diffaccel.dynamics.elements.screen import Screen
from diffaccel.dynamics.elements.sextupole import Sextupole
from diffaccel.dynamics.elements.solenoid import Solenoid
from diffaccel.dynamics.elements.transverse_deflecting_cavity import (
    TransverseDeflectingCavity,
)

__all__ = [
    "Dipole",
    "Drift",
    "Element",
    "LinearMap",
    "Quadrupole",
    "RFCavity",
    "Screen",
    "Sextupole",
    "Solenoid",
    "TransverseDeflectingCavity",
]
