"""diffaccel.plotting."""
