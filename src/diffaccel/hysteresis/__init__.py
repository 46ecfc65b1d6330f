"""diffaccel.hysteresis: differentiable Preisach hysteresis of magnets.

Names load on first use (PEP 562): the streaming of fitted models
(:class:`StreamSpec`, :class:`StreamPredictor`, :func:`load_stream_fit`) and
setting a magnet from it (:func:`plan_setpoint`) need numpy only, so that
``diffaccel hysteresis predict`` and ``set`` do not import torch (~2 s); the
torch parts load together on first use of one of their names; the GP parts
(:class:`HysteresisGP`, :class:`HGPFitResult`, :func:`fit_hysteresis_gp`,
:class:`HysteresisBO`) import GPyTorch and BoTorch (~1 s and ~100 MB) and load
apart, so that fitting Preisach models does not pay
for them. ``from diffaccel.hysteresis import HysteresisGP`` works as usual.
"""

from __future__ import annotations

from typing import Any

from diffaccel.hysteresis.fit_folder import (
    CONFIG_FILE,
    MODEL_FILE,
    STREAM_FILE,
    load_stream_fit,
)
from diffaccel.hysteresis.setpoint import (
    SetPoint,
    UnreachableTargetError,
    field_for_k1,
    plan_setpoint,
)
from diffaccel.hysteresis.stream import (
    InputRangeWarning,
    StreamPredictor,
    StreamSpec,
    outside_input_range,
    predict_chunks,
)

# name -> submodule, loaded on first access (see the module docstring)
_LAZY = {
    "BandFallbackWarning": "band",
    "LaplaceBand": "band",
    "laplace_band": "band",
    "FitResult": "fit",
    "fit_preisach": "fit",
    "InverseResult": "inverse",
    "invert_preisach": "inverse",
    "next_step_output": "inverse",
    "HystereticMagnet": "magnet",
    "hysteretic_settings": "magnet",
    "magnetic_rigidity": "magnet",
    "PreisachMesh": "mesh",
    "MagnetFit": "predictive",
    "adaptive_warp": "predictive",
    "changes_sign": "predictive",
    "default_input_range": "predictive",
    "fit_magnet": "predictive",
    "predict_stream": "predictive",
    "symmetric_default": "predictive",
    "INITIAL_STATES": "preisach",
    "PreisachModel": "preisach",
    "load_fit": "saved",
    "save_fit": "saved",
    "synthetic_magnet": "synthetic",
    "synthetic_measurement": "synthetic",
    "synthetic_protocol": "synthetic",
    "HGPFitResult": "hgp",
    "HysteresisGP": "hgp",
    "fit_hysteresis_gp": "hgp",
    "HysteresisBO": "bo",
}


def __getattr__(name: str) -> Any:
    """Load the torch names on first access, the GP ones apart (PEP 562)."""
    where = _LAZY.get(name)
    if where is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    if where == "hgp":
        from diffaccel.hysteresis import hgp as module
    elif where == "bo":
        from diffaccel.hysteresis import bo as module
    else:
        from diffaccel.hysteresis import (
            band,
            fit,
            inverse,
            magnet,
            mesh,
            predictive,
            preisach,
            saved,
            synthetic,
        )

        module = {
            "band": band,
            "fit": fit,
            "inverse": inverse,
            "magnet": magnet,
            "mesh": mesh,
            "predictive": predictive,
            "preisach": preisach,
            "saved": saved,
            "synthetic": synthetic,
        }[where]
    value = getattr(module, name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


__all__ = [
    "CONFIG_FILE",
    "INITIAL_STATES",
    "MODEL_FILE",
    "STREAM_FILE",
    "BandFallbackWarning",
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
    "SetPoint",
    "StreamPredictor",
    "StreamSpec",
    "UnreachableTargetError",
    "adaptive_warp",
    "changes_sign",
    "default_input_range",
    "field_for_k1",
    "fit_hysteresis_gp",
    "fit_magnet",
    "fit_preisach",
    "hysteretic_settings",
    "invert_preisach",
    "laplace_band",
    "load_fit",
    "load_stream_fit",
    "magnetic_rigidity",
    "next_step_output",
    "outside_input_range",
    "plan_setpoint",
    "predict_chunks",
    "predict_stream",
    "save_fit",
    "symmetric_default",
    "synthetic_magnet",
    "synthetic_measurement",
    "synthetic_protocol",
]
