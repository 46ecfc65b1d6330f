"""diffaccel.data."""
