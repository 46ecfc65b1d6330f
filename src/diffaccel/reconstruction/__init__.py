"""Phase-space reconstruction from screen images (beam generators, losses, ensembles).

Example:
    >>> from diffaccel.reconstruction import ReconstructionConfig
    >>> ReconstructionConfig().dims
    4
"""

from diffaccel.reconstruction.config import ReconstructionConfig
from diffaccel.reconstruction.design import (
    observability,
    propose_quad_settings,
    recommend,
)
from diffaccel.reconstruction.ensemble import Reconstruction, load
from diffaccel.reconstruction.evaluation import (
    LOW_ON_SCREEN_FRACTION,
    POOR_FIT_RELATIVE_L1,
    check_on_screen,
    clean_json,
    evaluate,
    off_screen_warnings,
    predict_dataset,
    predicted_dataset,
)
from diffaccel.reconstruction.forward import ScreenForwardModel
from diffaccel.reconstruction.generator import BeamGenerator
from diffaccel.reconstruction.initial import GaussianGuess, fit_gaussian
from diffaccel.reconstruction.losses import (
    cyclic_cosine_lr,
    gaussian_entropy,
    gaussian_prior_term,
    image_distance,
    penalty_schedule,
    robust_covariance,
)
from diffaccel.reconstruction.metrics import (
    beam_moments,
    image_errors,
    moment_errors,
    sliced_wasserstein,
)
from diffaccel.reconstruction.particles import to_particle_group
from diffaccel.reconstruction.pipeline import (
    as_scans,
    reconstruct,
    training_selection,
)
from diffaccel.reconstruction.screen_moments import moment_design
from diffaccel.reconstruction.training import (
    StepInfo,
    TrainingState,
    load_checkpoint,
    save_checkpoint,
    train_generator,
)

__all__ = [
    "LOW_ON_SCREEN_FRACTION",
    "POOR_FIT_RELATIVE_L1",
    "BeamGenerator",
    "GaussianGuess",
    "Reconstruction",
    "ReconstructionConfig",
    "ScreenForwardModel",
    "StepInfo",
    "TrainingState",
    "as_scans",
    "beam_moments",
    "check_on_screen",
    "clean_json",
    "cyclic_cosine_lr",
    "evaluate",
    "fit_gaussian",
    "gaussian_entropy",
    "gaussian_prior_term",
    "image_distance",
    "image_errors",
    "load",
    "load_checkpoint",
    "moment_design",
    "moment_errors",
    "observability",
    "off_screen_warnings",
    "penalty_schedule",
    "predict_dataset",
    "predicted_dataset",
    "propose_quad_settings",
    "recommend",
    "reconstruct",
    "robust_covariance",
    "save_checkpoint",
    "sliced_wasserstein",
    "to_particle_group",
    "train_generator",
    "training_selection",
]
