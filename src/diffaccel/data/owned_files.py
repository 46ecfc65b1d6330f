"""Output files record that diffaccel wrote them: ``--force`` replaces only those.

A command's ``--force`` replaces an existing output file only if diffaccel
wrote it; a file of the same name that it did not write (a measurement, a
user's array) is refused. The record lives in the file itself:

- HDF5 (``.h5``, ``.hdf5``): the root attribute :data:`H5_ATTRIBUTE`
  (``"diffaccel <version>"``), written by every quad-scan writer;
- ``.npy``: a comment after the header's dictionary
  (``{'descr': ..., } # written by diffaccel``), which numpy's reader skips;
- ``.npz``: the zip archive's comment (:data:`MARK`), ignored by ``np.load``;
- CSV: the header line, whose last columns are those the command appends
  (``hysteresis predict``: ``prediction, prediction_std, outside_input_range``).

A file that cannot be read is never replaced blind: a damaged one counts as
not written by diffaccel, a locked one (or one without permission) raises.
"""

from __future__ import annotations

import csv
import os
import struct
import zipfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import BinaryIO

import numpy as np

from diffaccel import __version__
from diffaccel.data.atomic import atomic_write, os_condition, os_error_text
from diffaccel.data.result_folder import MARKER

__all__ = [
    "H5_ATTRIBUTE",
    "MARK",
    "OutputFileError",
    "check_out_file",
    "h5_mark",
    "mark_npz",
    "save_arrays",
    "save_npy",
    "written_by_diffaccel",
]

#: Root attribute of the HDF5 files diffaccel writes; value ``"diffaccel <version>"``.
H5_ATTRIBUTE = "written_by"
#: The record in ``.npy`` headers and ``.npz`` archive comments.
MARK = "written by diffaccel"
_NPY_MAGIC = b"\x93NUMPY"


def h5_mark() -> str:
    """The value of :data:`H5_ATTRIBUTE`: ``"diffaccel <version>"``."""
    return f"diffaccel {__version__}"


def save_npy(f: BinaryIO, array: np.ndarray) -> None:
    """Write ``array`` to the binary file ``f`` as ``.npy`` (version 1.0) with the mark.

    The header's dictionary is followed by ``# written by diffaccel`` (a
    Python comment, which ``np.load`` skips); otherwise the file is what
    ``np.save`` writes (C order, no pickles).

    Example:
        >>> import io
        >>> buf = io.BytesIO()
        >>> save_npy(buf, np.arange(3, dtype=np.float32))
        >>> _ = buf.seek(0)
        >>> np.load(buf)
        array([0., 1., 2.], dtype=float32)
    """
    array = np.ascontiguousarray(array)
    if array.dtype.hasobject:
        raise ValueError("save_npy writes numeric arrays only (no pickled objects).")
    descr = np.lib.format.dtype_to_descr(array.dtype)
    header = (
        f"{{'descr': {descr!r}, 'fortran_order': False, 'shape': {array.shape!r}, }}"
        f" # {MARK}"
    )
    # magic (6) + version (2) + length (2) + header + newline: a multiple of 64
    header += " " * ((-(10 + len(header) + 1)) % 64) + "\n"
    f.write(_NPY_MAGIC + b"\x01\x00" + struct.pack("<H", len(header)))
    f.write(header.encode("latin1"))
    f.write(array.tobytes(order="C"))


def mark_npz(path: str | os.PathLike) -> None:
    """Set the zip comment of the ``.npz`` archive ``path`` to :data:`MARK`."""
    with zipfile.ZipFile(path, "a") as z:
        z.comment = MARK.encode()


def save_arrays(path: str | os.PathLike, arrays: Mapping[str, np.ndarray]) -> Path:
    """Write arrays as one marked ``.npy`` (one array) or ``.npz`` file, atomically.

    A ``.npy`` name (any case) writes the single array of ``arrays``
    (:func:`save_npy`); any other name writes an ``.npz`` archive with one
    entry per key (:func:`mark_npz`). A missing parent folder is created.

    Args:
        path: The file to write (an existing one is replaced).
        arrays: ``{name: array}``; exactly one for a ``.npy`` file.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        ValueError: several arrays for a ``.npy`` file.
        OSError: the file or its folder cannot be written.
    """
    path = Path(path)
    npy = path.suffix.lower() == ".npy"
    if npy and len(arrays) != 1:
        raise ValueError(f"{path}: {len(arrays)} arrays; write them to an .npz file")

    def save(p: Path) -> None:
        with p.open("wb") as f:
            if npy:
                save_npy(f, next(iter(arrays.values())))
            else:
                np.savez(f, **arrays)
        if not npy:
            mark_npz(p)

    path.parent.mkdir(parents=True, exist_ok=True)
    return atomic_write(path, save)


def _npy_marked(path: Path) -> bool:
    with path.open("rb") as f:
        head = f.read(10)
        if len(head) < 10 or not head.startswith(_NPY_MAGIC):
            return False
        major = head[6]
        if major == 1:
            (n,) = struct.unpack("<H", head[8:10])
            text = f.read(n)
        else:
            rest = f.read(2)
            (n,) = struct.unpack("<I", head[8:10] + rest)
            text = f.read(n)
    return f"# {MARK}".encode() in text


def _h5_marked(path: Path) -> bool:
    import h5py  # here: hysteresis predict checks CSV outputs without h5py

    with h5py.File(path, "r") as h5:
        value = h5.attrs.get(H5_ATTRIBUTE, "")
    if isinstance(value, bytes):
        value = value.decode("utf-8", "replace")
    return str(value).startswith("diffaccel")


def _csv_marked(path: Path, columns: Sequence[str]) -> bool:
    if not columns:
        return False
    with path.open(newline="", encoding="utf-8", errors="replace") as f:
        header = next(csv.reader(f), [])
    return [c.strip() for c in header[-len(columns) :]] == list(columns)


def written_by_diffaccel(
    path: str | os.PathLike, *, csv_columns: Sequence[str] = ()
) -> bool:
    """True if the file ``path`` carries diffaccel's record (see the module doc).

    Args:
        path: An existing file.
        csv_columns: For a ``.csv`` file, the last header columns that the
            writing command appends.

    Returns:
        False for a file without the record, of another type, or damaged.

    Raises:
        OSError: the file cannot be read for a condition of the machine
            (locked by another program, no permission; see
            :func:`~diffaccel.data.atomic.os_condition`).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    try:
        if suffix in (".h5", ".hdf5"):
            return _h5_marked(path)
        if suffix == ".npy":
            return _npy_marked(path)
        if suffix == ".npz":
            with zipfile.ZipFile(path) as z:
                return z.comment == MARK.encode()
        if suffix == ".csv":
            return _csv_marked(path, csv_columns)
    except OSError as err:
        if os_condition(err) is not None:  # locked, no permission: say so
            raise
        return False
    except (ValueError, zipfile.BadZipFile, struct.error):
        return False
    return False


class OutputFileError(ValueError):
    """An output file that must not be written (the message names it, one line)."""


def check_out_file(
    out: Path,
    force: bool,
    inputs: Mapping[str, Path | None],
    option: str = "--out",
    csv_columns: Sequence[str] = (),
) -> None:
    """Refuse an output file that would replace something the user gave.

    ``out`` may replace an existing file only with ``force`` and only if
    diffaccel wrote it (:func:`written_by_diffaccel`; ``csv_columns``: the
    columns a CSV output ends with), never one of the ``inputs``
    (``{"--dataset": path}``; None entries are skipped), and is never written
    into a diffaccel result folder (a fit, a reconstruction), ``force`` or
    not: the command could destroy the result it reads, and a foreign file
    there makes the folder refuse a later ``--force``. ``option`` names ``out``
    in the messages.

    Raises:
        OutputFileError: naming the option and the file.
    """
    for name, path in inputs.items():
        if path is not None and out.resolve() == path.resolve():
            raise OutputFileError(
                f"{option} {out} is the {name} file; write the output elsewhere."
            )
    if (out.resolve().parent / MARKER).exists():
        # a result folder holds what its command wrote, nothing else: a new
        # file there would make a later --force refuse the folder as foreign
        raise OutputFileError(
            f"{option} {out} is inside the result folder {out.parent}; write the "
            "output elsewhere."
        )
    if out.exists() and not force:
        raise OutputFileError(f"{out} exists; pass --force to overwrite it")
    try:
        ours = not out.exists() or written_by_diffaccel(out, csv_columns=csv_columns)
    except OSError as err:  # locked, no permission
        raise OutputFileError(os_error_text(err, out, doing="read")) from err
    if not ours:
        raise OutputFileError(
            f"{out} exists and was not written by diffaccel; --force "
            "replaces only diffaccel's own output files: move it or choose "
            "another name."
        )
