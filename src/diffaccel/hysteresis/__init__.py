"""diffaccel.hysteresis: differentiable Preisach hysteresis of magnets."""

from __future__ import annotations

from diffaccel.hysteresis.fit import FitResult, fit_preisach
from diffaccel.hysteresis.mesh import PreisachMesh
from diffaccel.hysteresis.preisach import INITIAL_STATES, PreisachModel

__all__ = [
    "INITIAL_STATES",
    "FitResult",
    "PreisachMesh",
    "PreisachModel",
    "fit_preisach",
]
