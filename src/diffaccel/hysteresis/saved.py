"""Fitted Preisach models on disk: ``model.json`` (settings), ``model.pt`` (tensors)
and ``stream.npz`` (numbers for streaming, see :mod:`~diffaccel.hysteresis.fit_folder`).

``model.pt`` holds the model's ``state_dict`` and, under keys ``band.*``, its
predictive band; it is read with ``torch.load(weights_only=True)``. Every
mismatch between the files is a one-line ``ValueError`` naming the file.
"""

from __future__ import annotations

from pathlib import Path

import torch

from diffaccel.data import atomic_write, atomic_write_json
from diffaccel.hysteresis.band import LaplaceBand
from diffaccel.hysteresis.fit_folder import (
    CONFIG_FILE,
    MODEL_FILE,
    check_model_file,
    read_config,
    write_stream_file,
)
from diffaccel.hysteresis.preisach import PreisachModel

__all__ = ["load_fit", "save_fit"]

_BAND = "band."


def save_fit(
    fit_dir: str | Path,
    model: PreisachModel,
    band: LaplaceBand | None = None,
    extra: dict | None = None,
    *,
    overwrite: bool = False,
) -> None:
    """Write ``model.pt``, ``model.json`` and ``stream.npz`` into ``fit_dir``.

    Each file is written atomically: ``model.pt``, then ``stream.npz`` (the
    model's numbers for ``diffaccel hysteresis predict``, which runs without
    torch, with the SHA-256 of ``model.pt``), then ``model.json``, so that a
    folder whose writing was interrupted has no ``model.json`` and is refused
    by :func:`load_fit` and ``predict``. Overwriting removes the old
    ``model.json`` first for the same reason; other files in the folder are
    left alone.

    Args:
        fit_dir: Folder (created if missing).
        model: The fitted model.
        band: Its predictive band, if any.
        extra: JSON-serialisable entries added to ``model.json`` (e.g. column
            names); they must not shadow the model's own settings.
        overwrite: Write into a folder that is not empty (replacing an earlier
            fit there). The CLI writes results all-or-nothing instead (see
            :func:`diffaccel.data.result_folder`).

    Raises:
        FileExistsError: if ``fit_dir`` exists, is not empty and ``overwrite``
            is False.
    """
    fit_dir = Path(fit_dir)
    if fit_dir.is_dir() and any(fit_dir.iterdir()) and not overwrite:
        raise FileExistsError(
            f"{fit_dir} is not empty; pass overwrite=True to replace a fit there "
            "(or choose a new or empty folder)."
        )
    fit_dir.mkdir(parents=True, exist_ok=True)
    tensors = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
    if band is not None:
        for k, v in band.state_dict().items():
            tensors[_BAND + k] = v.detach().cpu().clone()
    config = {**(extra or {}), **model.config(), "band": band is not None}
    spec = band.stream_spec(model) if band is not None else model.stream_spec()
    (fit_dir / CONFIG_FILE).unlink(missing_ok=True)  # written last: the fit is whole
    atomic_write(fit_dir / MODEL_FILE, lambda p: torch.save(tensors, p))
    write_stream_file(fit_dir, spec)
    atomic_write_json(fit_dir / CONFIG_FILE, config)


def load_fit(fit_dir: str | Path) -> tuple[PreisachModel, LaplaceBand | None, dict]:
    """Read a fit written by :func:`save_fit` (safe loading, checked).

    Returns:
        ``(model, band or None, config)``.

    Raises:
        ValueError: for a missing, unreadable or inconsistent file (e.g. a
            ``model.pt`` whose hysteron count differs from ``model.json``, or
            that is not the one ``stream.npz`` records).
    """
    fit_dir = Path(fit_dir)
    cfg_path, pt_path = fit_dir / CONFIG_FILE, fit_dir / MODEL_FILE
    config = read_config(fit_dir)
    if not pt_path.is_file():
        raise ValueError(f"{pt_path}: missing; is {fit_dir} a hysteresis fit folder?")
    try:
        tensors = torch.load(pt_path, weights_only=True, map_location="cpu")
    except Exception as err:  # torch raises several types for corrupt files
        msg = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise ValueError(f"{pt_path}: cannot read tensors ({msg}).") from None
    if not isinstance(tensors, dict) or not all(
        isinstance(v, torch.Tensor) for v in tensors.values()
    ):
        raise ValueError(f"{pt_path}: expected a dict of tensors.")
    n_cfg = config.get("n_hysterons")
    raw = tensors.get("raw_density")
    if raw is None or raw.ndim != 1:
        raise ValueError(f"{pt_path}: no raw_density vector.")
    if n_cfg is not None and int(n_cfg) != raw.numel():
        raise ValueError(
            f"{pt_path} holds {raw.numel()} hysterons but {cfg_path} says "
            f"{n_cfg}; the two files come from different fits."
        )
    band_t = {k[len(_BAND) :]: v for k, v in tensors.items() if k.startswith(_BAND)}
    model_t = {k: v for k, v in tensors.items() if not k.startswith(_BAND)}
    try:
        model = PreisachModel.from_config(config, model_t)
    except (KeyError, TypeError, ValueError, RuntimeError, AttributeError) as err:
        msg = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise ValueError(f"{fit_dir}: inconsistent model files ({msg}).") from None
    band = None
    if band_t:
        try:
            band = LaplaceBand(
                band_t["directions"], band_t["noise_std"], float(band_t["calibration"])
            )
        except (KeyError, ValueError) as err:
            raise ValueError(
                f"{pt_path}: malformed band ({str(err).rstrip('.')})."
            ) from None
        if band.n_hysterons != raw.numel():
            raise ValueError(
                f"{pt_path}: band has {band.n_hysterons} hysterons, the model "
                f"{raw.numel()}."
            )
    # last, so that a damaged model.pt is named for what is wrong with it
    check_model_file(fit_dir)
    return model, band, config
