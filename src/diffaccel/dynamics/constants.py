"""Physical constants used by the tracking code (CODATA 2018, SI units plus eV)."""

from __future__ import annotations

__all__ = ["ELECTRON_MASS_EV", "PROTON_MASS_EV", "SPEED_OF_LIGHT"]

#: Speed of light in vacuum [m/s].
SPEED_OF_LIGHT: float = 299_792_458.0
#: Electron rest energy m c^2 [eV].
ELECTRON_MASS_EV: float = 510_998.950_00
#: Proton rest energy m c^2 [eV].
PROTON_MASS_EV: float = 938_272_088.16
