"""diffaccel.hysteresis: differentiable Preisach hysteresis of magnets."""

from __future__ import annotations

from diffaccel.hysteresis.bo import HysteresisBO
from diffaccel.hysteresis.fit import FitResult, fit_preisach
from diffaccel.hysteresis.hgp import HGPFitResult, HysteresisGP, fit_hysteresis_gp
from diffaccel.hysteresis.inverse import (
    InverseResult,
    invert_preisach,
    next_step_output,
)
from diffaccel.hysteresis.magnet import (
    HystereticMagnet,
    hysteretic_settings,
    magnetic_rigidity,
)
from diffaccel.hysteresis.mesh import PreisachMesh
from diffaccel.hysteresis.preisach import (
    INITIAL_STATES,
    InputRangeWarning,
    PreisachModel,
)
from diffaccel.hysteresis.synthetic import (
    synthetic_magnet,
    synthetic_measurement,
    synthetic_protocol,
)

__all__ = [
    "INITIAL_STATES",
    "FitResult",
    "HGPFitResult",
    "HysteresisBO",
    "HysteresisGP",
    "HystereticMagnet",
    "InputRangeWarning",
    "InverseResult",
    "PreisachMesh",
    "PreisachModel",
    "fit_hysteresis_gp",
    "fit_preisach",
    "hysteretic_settings",
    "invert_preisach",
    "magnetic_rigidity",
    "next_step_output",
    "synthetic_magnet",
    "synthetic_measurement",
    "synthetic_protocol",
]
