"""diffaccel.dynamics."""
