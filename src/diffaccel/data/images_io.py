"""Camera frames from files: PNG, TIFF, ``.npy``, ``.npz`` and HDF5 datasets.

PNG and TIFF are decoded by imageio (TIFF through tifffile), the optional
``[images]`` extra; ``.npy`` and ``.npz`` by numpy (``allow_pickle=False``);
HDF5 by h5py. A frame is a 2-D array of pixel values as the camera stored them
(row 0 first, as the file lists the rows); orientation is applied by the caller.

References name a file and, where the file holds several arrays, which one:

* ``frame.png``, ``frame.tif`` / ``.tiff``, ``frame.npy``: the file's image;
* ``frames.npz`` (one array) or ``frames.npz:name``: an array of the archive;
* ``run.h5:/camera/frames`` or ``run.h5:/camera/frames[3]``: an HDF5 dataset,
  or frame 3 (first axis) of a 3-D one.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from diffaccel.data.errors import FormatError

__all__ = ["IMAGE_SUFFIXES", "Frame", "read_frame"]

#: File name endings read as images (case-insensitive).
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".npy", ".npz", ".h5", ".hdf5")
_H5_REF = re.compile(
    r"^(?P<path>.+?\.(?:h5|hdf5)):(?P<dset>/?[^\[\]]+)(?:\[(?P<i>\d+)\])?$"
)
_NPZ_REF = re.compile(r"^(?P<path>.+?\.npz)(?::(?P<key>[^:]+))?$", re.IGNORECASE)


@dataclass(frozen=True)
class Frame:
    """One camera frame.

    Args:
        pixels: ``(H, W)`` float64 pixel values [camera units].
        dtype: The stored dtype (``"uint16"``, ``"float32"``, ...).
        max_value: Largest value the stored integer type holds (the camera's
            saturation when it fills the type), or ``None`` for float data.
    """

    pixels: np.ndarray
    dtype: str
    max_value: float | None


def _imageio_read(path: Path) -> np.ndarray:
    try:
        import imageio.v3 as iio
    except ImportError as err:
        raise ImportError(
            f"{path.name}: reading PNG/TIFF images needs imageio (and tifffile): "
            "pip install diffaccel[images]"
        ) from err
    try:
        return np.asarray(iio.imread(path))
    except Exception as err:  # the decoders raise many types
        raise FormatError(f"{path}: not a readable image ({err})") from err


def _h5_read(path: Path, dset: str, index: int | None, ref: str) -> np.ndarray:
    try:
        h5 = h5py.File(path, "r")
    except OSError as err:
        raise FormatError(f"{path}: not a readable HDF5 file ({err})") from err
    with h5:
        if dset not in h5 or not isinstance(h5[dset], h5py.Dataset):
            raise FormatError(f"{ref}: no dataset {dset!r} in {path.name}")
        d = h5[dset]
        if index is None:
            return np.asarray(d[()])
        if d.ndim != 3 or not 0 <= index < d.shape[0]:
            raise FormatError(
                f"{ref}: frame [{index}] needs a 3-D dataset with more than {index} "
                f"frames; {dset} has shape {d.shape}"
            )
        return np.asarray(d[index])


def read_frame(ref: str, base: Path) -> Frame:
    """Read one camera frame.

    Args:
        ref: File reference (see the module docstring), relative to ``base``
            unless absolute.
        base: Folder that relative references start from.

    Returns:
        The frame, 2-D.

    Raises:
        FileNotFoundError: naming the file when it does not exist.
        FormatError: for an unknown file type, an unreadable file, a missing
            array or dataset, an array that is not 2-D real numbers.
        ImportError: for PNG/TIFF without the ``[images]`` extra.
    """
    text = str(ref).strip()
    h5m = _H5_REF.match(text)
    npz = _NPZ_REF.match(text)
    if h5m:
        path = base / h5m["path"]
    elif npz:
        path = base / npz["path"]
    else:
        path = base / text
    suffix = path.suffix.lower()
    if suffix not in IMAGE_SUFFIXES:
        raise FormatError(
            f"{text}: unknown image type {suffix or '(none)'!r}; expected one of "
            f"{', '.join(IMAGE_SUFFIXES)}"
        )
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    if suffix in (".png", ".tif", ".tiff"):
        arr = _imageio_read(path)
    elif suffix == ".npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except ValueError as err:
            raise FormatError(f"{path}: not a numeric .npy array ({err})") from err
    elif suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as archive:
                keys = list(archive.keys())
                key = npz["key"] if npz and npz["key"] else None
                if key is None:
                    if len(keys) != 1:
                        raise FormatError(
                            f"{text}: {path.name} holds {len(keys)} arrays "
                            f"({', '.join(keys)}); name one as {path.name}:NAME"
                        )
                    key = keys[0]
                if key not in keys:
                    raise FormatError(f"{text}: no array {key!r} in {path.name}")
                arr = archive[key]
        except (ValueError, OSError) as err:
            raise FormatError(f"{path}: not a readable .npz archive ({err})") from err
    else:
        if not h5m:
            raise FormatError(
                f"{text}: name the dataset of the HDF5 file, e.g. "
                f"{path.name}:/camera/frames or {path.name}:/camera/frames[0]"
            )
        index = int(h5m["i"]) if h5m["i"] is not None else None
        arr = _h5_read(path, h5m["dset"], index, text)
    arr = np.asarray(arr)
    if arr.dtype.kind not in "uif":
        raise FormatError(
            f"{text}: expected real pixel values; found dtype {arr.dtype}"
        )
    if arr.ndim == 3 and arr.shape[-1] in (3, 4):
        raise FormatError(
            f"{text}: a colour image ({arr.shape[-1]} channels); expected one "
            "grey-level channel as cameras for beam profiles record"
        )
    if arr.ndim != 2:
        raise FormatError(f"{text}: expected a 2-D image; found shape {arr.shape}")
    max_value = float(np.iinfo(arr.dtype).max) if arr.dtype.kind in "ui" else None
    return Frame(arr.astype(np.float64), str(arr.dtype), max_value)
