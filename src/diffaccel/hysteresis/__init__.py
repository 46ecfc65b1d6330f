"""diffaccel.hysteresis."""
