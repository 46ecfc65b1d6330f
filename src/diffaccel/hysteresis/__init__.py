"""diffaccel.hysteresis: differentiable Preisach hysteresis of magnets.

The GP parts (:class:`HysteresisGP`, :class:`HGPFitResult`,
:func:`fit_hysteresis_gp`, :class:`HysteresisBO`) import GPyTorch and BoTorch
(~1 s and ~100 MB); they load on first use of their names, so that fitting and
predicting Preisach models (e.g. ``diffaccel hysteresis predict``) do not pay
for them. ``from diffaccel.hysteresis import HysteresisGP`` works as usual.
"""

from __future__ import annotations

from typing import Any

from diffaccel.hysteresis.band import LaplaceBand, laplace_band
from diffaccel.hysteresis.fit import FitResult, fit_preisach
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

# name -> submodule, loaded on first access (see the module docstring)
_LAZY = {
    "HGPFitResult": "hgp",
    "HysteresisGP": "hgp",
    "fit_hysteresis_gp": "hgp",
    "HysteresisBO": "bo",
}


def __getattr__(name: str) -> Any:
    """Load the GP names on first access (PEP 562)."""
    if _LAZY.get(name) == "hgp":
        from diffaccel.hysteresis import hgp

        return getattr(hgp, name)
    if _LAZY.get(name) == "bo":
        from diffaccel.hysteresis import bo

        return getattr(bo, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


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
