"""Fit folders, the part that needs no torch: file names, settings, the stream file.

A fit folder (:func:`~diffaccel.hysteresis.save_fit`) holds ``model.json``
(settings), ``model.pt`` (the model's tensors, read by
:func:`~diffaccel.hysteresis.load_fit` with torch) and ``stream.npz``: the
model's numbers for streaming long histories
(:class:`~diffaccel.hysteresis.stream.StreamSpec`, plain float64 arrays read
with ``numpy.load(allow_pickle=False)``) and the SHA-256 of the ``model.pt`` it
was made from, so that ``diffaccel hysteresis predict`` runs without torch and
still refuses a folder whose files do not belong together. Every problem is a
one-line ``ValueError`` naming the file.
"""

from __future__ import annotations

import hashlib
import json
import zipfile
from pathlib import Path

import numpy as np

from diffaccel.data.atomic import atomic_write
from diffaccel.hysteresis.stream import StreamSpec

__all__ = [
    "CONFIG_FILE",
    "FLOAT_DTYPES",
    "MODEL_FILE",
    "STREAM_FILE",
    "check_model_file",
    "load_stream_fit",
    "read_config",
    "write_stream_file",
]

MODEL_FILE = "model.pt"
CONFIG_FILE = "model.json"
STREAM_FILE = "stream.npz"
#: dtype names a saved model may have (``model.json`` ``dtype``)
FLOAT_DTYPES = ("float16", "bfloat16", "float32", "float64")
_HASH = "model_sha256"


def _sha256(path: Path) -> np.ndarray:
    return np.frombuffer(hashlib.sha256(path.read_bytes()).digest(), dtype=np.uint8)


def _check_digest(digest: np.ndarray | None, pt_path: Path, path: Path) -> None:
    """Refuse ``pt_path`` unless its SHA-256 is ``digest`` (read from ``path``)."""
    if digest is None or not np.array_equal(digest, _sha256(pt_path)):
        raise ValueError(
            f"{pt_path} is not the file {path} was made from; the files come "
            "from different fits (save the fit again)."
        )


def _read_arrays(path: Path) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as npz:
            return {k: npz[k] for k in npz.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
        msg = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise ValueError(f"{path}: cannot read arrays ({msg}).") from None


def check_model_file(fit_dir: str | Path) -> None:
    """Refuse a ``model.pt`` other than the one the folder's ``stream.npz`` records.

    ``stream.npz`` records the SHA-256 of ``model.pt``; a folder without
    ``stream.npz`` (saved before it existed) is not checked.

    Raises:
        ValueError: naming both files if ``model.pt`` differs from the recorded
            one, or if ``stream.npz`` cannot be read.
    """
    fit_dir = Path(fit_dir)
    path, pt_path = fit_dir / STREAM_FILE, fit_dir / MODEL_FILE
    if path.is_file():
        _check_digest(_read_arrays(path).get(_HASH), pt_path, path)


def read_config(fit_dir: str | Path) -> dict:
    """``model.json`` of a fit folder, checked to be a JSON object.

    Raises:
        ValueError: for a missing file or one that is not a JSON object.
    """
    fit_dir = Path(fit_dir)
    path = fit_dir / CONFIG_FILE
    if not path.is_file():
        raise ValueError(f"{path}: missing; is {fit_dir} a hysteresis fit folder?")
    try:
        config = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: not valid JSON ({err}).") from None
    if not isinstance(config, dict):
        raise ValueError(f"{path}: expected a JSON object.")
    return config


def write_stream_file(fit_dir: str | Path, spec: StreamSpec) -> Path:
    """Write ``stream.npz`` for ``spec`` next to the folder's ``model.pt`` (atomically).

    Call after ``model.pt`` is written: its SHA-256 is recorded.
    """
    fit_dir = Path(fit_dir)
    arrays = {**spec.to_arrays(), _HASH: _sha256(fit_dir / MODEL_FILE)}

    def write(p: Path) -> None:
        with open(p, "wb") as f:
            np.savez(f, **arrays)

    return atomic_write(fit_dir / STREAM_FILE, write)


def load_stream_fit(fit_dir: str | Path) -> tuple[StreamSpec, dict]:
    """The stream spec and settings of a fit folder, without torch (checked).

    Returns:
        ``(spec, config)``; ``spec`` starts from the model's own initial state.

    Raises:
        FileNotFoundError: if the folder has no ``stream.npz`` (fits saved
            before it existed: use :func:`~diffaccel.hysteresis.load_fit`).
        ValueError: for a damaged file or files from different fits.
    """
    fit_dir = Path(fit_dir)
    config = read_config(fit_dir)
    cfg_path, pt_path = fit_dir / CONFIG_FILE, fit_dir / MODEL_FILE
    path = fit_dir / STREAM_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing.")
    if not pt_path.is_file():
        raise ValueError(f"{pt_path}: missing; is {fit_dir} a hysteresis fit folder?")
    arrays = _read_arrays(path)
    _check_digest(arrays.pop(_HASH, None), pt_path, path)
    try:
        spec = StreamSpec.from_arrays(arrays)
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from None
    problems = []
    if config.get("type") != "PreisachModel":
        problems.append(f"type {config.get('type')!r} is not 'PreisachModel'")
    if str(config.get("dtype", "float64")) not in FLOAT_DTYPES:
        problems.append(f"dtype {config.get('dtype')!r} is not one of {FLOAT_DTYPES}")
    try:
        lo, hi = (float(v) for v in config["input_range"])
    except (KeyError, TypeError, ValueError):
        problems.append("no input_range [lo, hi]")
    else:
        if (lo, hi) != spec.input_range:
            problems.append(f"input_range {[lo, hi]} differs from {path.name}'s")
    n = config.get("n_hysterons", spec.alpha.size)
    if n != spec.alpha.size:
        problems.append(f"{n!r} hysterons, {path.name} {spec.alpha.size}")
    if bool(config.get("band", spec.has_band)) != spec.has_band:
        problems.append(f"band {config['band']}, {path.name} the opposite")
    if problems:
        raise ValueError(f"{cfg_path}: {'; '.join(problems)}.")
    return spec, config
