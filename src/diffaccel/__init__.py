"""diffaccel: differentiable modeling of particle accelerators."""

__version__ = "0.1.0"
