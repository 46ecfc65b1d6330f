"""Screen images of a reconstruction for new settings, with their warnings.

:func:`predict_scans` images every scan and setting of a dataset (its
beamlines and screens); :func:`predict_settings` images settings of the
result's own (first) training beamline. Both return a :class:`Prediction`:
the ensemble-mean images (each summing to 1), optionally their per-pixel
spread, the fraction of the beam on the screen at each setting, and the
warnings (settings where less than half of the beam lands on the screen, a
4D result imaged through z or pz readers).
"""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

from diffaccel.data.scans import MultiScanDataset
from diffaccel.reconstruction.alarms import prediction_alarms
from diffaccel.reconstruction.ensemble import Reconstruction
from diffaccel.reconstruction.evaluation import (
    check_on_screen,
    off_screen_warnings,
    predict_dataset,
)

__all__ = ["Prediction", "predict_scans", "predict_settings"]

#: Posterior beams per ensemble member for the per-pixel spread.
N_DRAWS = 4


@dataclass(frozen=True)
class Prediction:
    """Predicted screen images per scan.

    Attributes:
        images: ``{scan: (K, H, W)}`` float32 images, each summing to 1.
        spread: ``{scan: (K, H, W)}`` per-pixel spread (1 sigma, on the scale
            of the unit-sum images); None where it was not asked for.
        on_screen: ``{scan: (K,)}`` fraction of the beam on the screen.
        warnings: One line each (no ``warning:`` prefix).
    """

    images: dict[str, Tensor]
    spread: dict[str, Tensor] | None
    on_screen: dict[str, Tensor]
    warnings: list[str]


def predict_scans(
    result: Reconstruction,
    dataset: MultiScanDataset,
    *,
    n_particles: int = 50_000,
    seed: int = 0,
    return_std: bool = False,
) -> Prediction:
    """Images of every scan and setting of ``dataset``, on its screen grids.

    See :func:`~diffaccel.reconstruction.predict_dataset` (``n_particles``
    per ensemble member, sampling ``seed``, ``return_std``: also the spread).

    Raises:
        ValueError: a dataset the result cannot image (e.g. other scanned
            names).
    """
    out = predict_dataset(
        result,
        dataset,
        n_particles=n_particles,
        seed=seed,
        return_std=return_std,
        return_on_screen=True,
    )
    if return_std:
        images, spread, on_screen = out
    else:
        (images, on_screen), spread = out, None
    warnings = [
        w
        for name, scan in dataset
        for w in off_screen_warnings(
            on_screen[name], scan.settings, scan.setting_names, scan=name
        )
    ]
    warnings += [a.text() for a in prediction_alarms(result, dataset)]
    return Prediction(images, spread, on_screen, warnings)


def predict_settings(
    result: Reconstruction,
    settings: Tensor,
    *,
    n_particles: int = 50_000,
    seed: int = 0,
    return_std: bool = False,
) -> Prediction:
    """Images at ``settings`` of the result's own (first) training beamline.

    Args:
        result: The reconstruction.
        settings: ``(K, P)`` values of its scanned parameters.
        n_particles: Particles per ensemble member.
        seed: Sampling seed.
        return_std: Also the per-pixel spread.

    Returns:
        A :class:`Prediction` of one scan, the result's first.

    Raises:
        ValueError: settings where the beam misses the screen entirely
            (:func:`~diffaccel.reconstruction.check_on_screen`), or of the
            wrong shape.
    """
    fwd = result.forward
    name = result.scan_names[0]
    out = result.predict_images(
        settings,
        forward=fwd,
        n_particles=n_particles,
        seed=seed,
        return_std=return_std,
        n_draws=N_DRAWS,
        return_on_screen=True,
    )
    if return_std:
        images, std, fraction = out
        spread = {name: std}
    else:
        (images, fraction), spread = out, None
    check_on_screen(images, settings)
    warnings = off_screen_warnings(fraction, settings, fwd.names, scan=name)
    warnings += [a.text() for a in prediction_alarms(result, None, settings)]
    return Prediction({name: images}, spread, {name: fraction}, warnings)
