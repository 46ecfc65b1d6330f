"""diffaccel.plotting: figures from results (functions take objects, return Figures)."""

from diffaccel.plotting.reconstruction import (
    plot_corner,
    plot_image_comparison,
    plot_rms_evolution,
    plot_training_curves,
)

__all__ = [
    "plot_corner",
    "plot_image_comparison",
    "plot_rms_evolution",
    "plot_training_curves",
]
