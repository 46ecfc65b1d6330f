"""diffaccel.dynamics: differentiable particle tracking, screen images and statistics.

Coordinates are Bmad's ``(x, px, y, py, z, pz)`` about a reference momentum
``p0c`` [eV], as tensors shaped ``(*K, N, 6)`` (see ``docs/coordinates.md``).
"""

from __future__ import annotations

from diffaccel.dynamics import elements
from diffaccel.dynamics._validate import (
    as_p0c,
    as_real_tensor,
    check_particles,
    finite_checks,
    is_integer,
    is_real,
)
from diffaccel.dynamics.beamline import ELEMENT_TYPES, Beamline
from diffaccel.dynamics.constants import (
    ELECTRON_MASS_EV,
    PROTON_MASS_EV,
    SPEED_OF_LIGHT,
)
from diffaccel.dynamics.coordinates import (
    ELEMENTARY_CHARGE,
    bmad_to_cheetah,
    bmad_to_openpmd,
    cheetah_to_bmad,
    energy_to_p0c,
    openpmd_to_bmad,
    p0c_to_energy,
)
from diffaccel.dynamics.elements import *  # noqa: F403 (its __all__, below)
from diffaccel.dynamics.images import cic_image, gaussian_blur, kde_image, pixel_centers
from diffaccel.dynamics.species import ELECTRON, POSITRON, PROTON, Species
from diffaccel.dynamics.statistics import (
    Twiss,
    centroid,
    covariance,
    emittance,
    emittance_4d,
    emittance_6d,
    normalized_emittance,
    rms_sizes,
    twiss,
)

__all__ = [
    "ELECTRON",
    "ELECTRON_MASS_EV",
    "ELEMENTARY_CHARGE",
    "ELEMENT_TYPES",
    "POSITRON",
    "PROTON",
    "PROTON_MASS_EV",
    "SPEED_OF_LIGHT",
    "Beamline",
    "Species",
    "Twiss",
    "as_p0c",
    "as_real_tensor",
    "bmad_to_cheetah",
    "bmad_to_openpmd",
    "centroid",
    "check_particles",
    "cheetah_to_bmad",
    "cic_image",
    "covariance",
    "emittance",
    "emittance_4d",
    "emittance_6d",
    "energy_to_p0c",
    "finite_checks",
    "gaussian_blur",
    "is_integer",
    "is_real",
    "kde_image",
    "normalized_emittance",
    "openpmd_to_bmad",
    "p0c_to_energy",
    "pixel_centers",
    "rms_sizes",
    "twiss",
    *elements.__all__,
]
