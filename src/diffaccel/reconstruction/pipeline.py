"""End-to-end reconstruction of a quad-scan dataset."""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import torch

from diffaccel.data.quad_scan import QuadScanDataset
from diffaccel.reconstruction.ensemble import Reconstruction
from diffaccel.reconstruction.forward import ScreenForwardModel
from diffaccel.reconstruction.initial import fit_gaussian
from diffaccel.reconstruction.training import (
    ReconstructionConfig,
    StepInfo,
    checkpoint_config,
    train_generator,
)


def _check_images(images: torch.Tensor) -> None:
    if not torch.isfinite(images).all():
        raise ValueError("measured images contain NaN or infinite values.")
    sums = images.sum((-2, -1))
    if (sums <= 0).any():
        bad = torch.nonzero(sums <= 0).flatten().tolist()
        raise ValueError(f"measured images {bad} are all zero (or negative).")


def reconstruct(
    dataset: QuadScanDataset,
    config: ReconstructionConfig | None = None,
    *,
    train_indices: Sequence[int] | None = None,
    checkpoint: str | os.PathLike | None = None,
    resume: bool = False,
    callback: Callable[[StepInfo], None] | None = None,
    device: str | torch.device = "cpu",
) -> Reconstruction:
    """Reconstruct the initial phase space of a beam from a quad-scan dataset.

    Builds the forward model of the dataset (beamline, screen, scanned names),
    fits a Gaussian to the image moments as a starting point, and trains a
    snapshot ensemble of beam generators on the shot-averaged, sum-normalised
    images of ``train_indices``.

    Args:
        dataset: The scan (images ``(K, S, H, W)``, settings ``(K, P)``).
        config: Training settings; defaults to :class:`ReconstructionConfig`.
        train_indices: Settings used for training (default all).
        checkpoint: Checkpoint file (written atomically during training).
        resume: Continue from ``checkpoint`` if it exists (the stored config
            must equal ``config``).
        callback: Progress callback, see
            :func:`~diffaccel.reconstruction.training.train_generator`.
        device: ``"cpu"``, ``"cuda"``...

    Returns:
        The :class:`Reconstruction`; ``info`` holds ``train_indices``,
        ``train_settings`` and timings [s].

    Raises:
        ValueError: for NaN or all-zero images, bad indices, or a checkpoint
            written with a different config.
    """
    config = config or ReconstructionConfig()
    k = dataset.n_settings
    idx = list(range(k)) if train_indices is None else [int(i) for i in train_indices]
    if not idx or any(i < 0 or i >= k for i in idx) or len(set(idx)) != len(idx):
        raise ValueError(
            f"train_indices must be distinct integers in [0, {k}); got {idx}."
        )
    images = dataset.mean_images()
    _check_images(images)
    if resume and checkpoint is not None and Path(checkpoint).exists():
        stored = checkpoint_config(checkpoint)
        if stored != config:
            raise ValueError(
                f"checkpoint {checkpoint} was written with a different config "
                f"({stored}); resume with the same options."
            )
    t0 = time.perf_counter()
    forward = ScreenForwardModel.from_dataset(dataset, blur_pixels=config.blur_pixels)
    measured = images[idx]
    settings = dataset.settings[idx]
    guess = fit_gaussian(forward, measured, settings)
    t1 = time.perf_counter()
    state = train_generator(
        forward,
        measured.to(device),
        settings,
        guess,
        config,
        checkpoint=checkpoint,
        resume=resume,
        callback=callback,
        device=device,
    )
    forward.to("cpu")
    info = {
        "train_indices": idx,
        "train_settings": settings.tolist(),
        "setting_names": list(dataset.setting_names),
        "initial_guess_mean": guess.mean.tolist(),
        "initial_guess_cov": guess.cov.tolist(),
        "timings_s": {"initial_fit": t1 - t0, "training": state.elapsed_s},
        "device": str(device),
    }
    return Reconstruction(config, state.snapshots, forward, state.history, info)
