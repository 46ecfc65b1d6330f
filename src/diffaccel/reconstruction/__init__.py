"""diffaccel.reconstruction."""
