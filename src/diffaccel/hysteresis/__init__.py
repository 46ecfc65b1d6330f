"""diffaccel.hysteresis: differentiable Preisach hysteresis of magnets."""

from __future__ import annotations

from diffaccel.hysteresis.band import LaplaceBand, laplace_band
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
from diffaccel.hysteresis.predictive import (
    MagnetFit,
    default_input_range,
    fit_magnet,
    predict_stream,
    symmetric_default,
)
from diffaccel.hysteresis.preisach import (
    INITIAL_STATES,
    InputRangeWarning,
    PreisachModel,
)
from diffaccel.hysteresis.saved import CONFIG_FILE, MODEL_FILE, load_fit, save_fit
from diffaccel.hysteresis.synthetic import (
    synthetic_magnet,
    synthetic_measurement,
    synthetic_protocol,
)

__all__ = [
    "CONFIG_FILE",
    "INITIAL_STATES",
    "MODEL_FILE",
    "FitResult",
    "HGPFitResult",
    "HysteresisBO",
    "HysteresisGP",
    "HystereticMagnet",
    "InputRangeWarning",
    "InverseResult",
    "LaplaceBand",
    "MagnetFit",
    "PreisachMesh",
    "PreisachModel",
    "default_input_range",
    "fit_hysteresis_gp",
    "fit_magnet",
    "fit_preisach",
    "hysteretic_settings",
    "invert_preisach",
    "laplace_band",
    "load_fit",
    "magnetic_rigidity",
    "next_step_output",
    "predict_stream",
    "save_fit",
    "symmetric_default",
    "synthetic_magnet",
    "synthetic_measurement",
    "synthetic_protocol",
]
