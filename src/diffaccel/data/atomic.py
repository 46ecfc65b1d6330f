"""Atomic file writes: readers never see a half-written file.

Every file diffaccel writes goes through :func:`atomic_write`: the content is
written to a temporary file in the destination's directory, which then replaces
the destination with ``os.replace`` (atomic on POSIX and Windows). On any error
the temporary file is removed and the destination is left as it was.
"""

from __future__ import annotations

import errno
import json
import math
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = [
    "OutputWriteError",
    "atomic_write",
    "atomic_write_bytes",
    "atomic_write_json",
    "atomic_write_text",
    "clean_json",
    "os_condition",
    "os_error_text",
]


def _default_mode() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def atomic_write(
    path: str | os.PathLike, write: Callable[[Path], object], *, overwrite: bool = True
) -> Path:
    """Write ``path`` atomically through ``write(tmp_path)``.

    Args:
        path: Destination file.
        write: Called once with the temporary file's path; writes the content
            there (e.g. ``lambda p: torch.save(obj, p)``). The temporary name
            ends in ``.tmp``, so pass an explicit format where a writer guesses
            it from the suffix (``fig.savefig(p, format="png")``).
        overwrite: If False and ``path`` exists, raise ``FileExistsError``.

    Returns:
        The destination path.

    Raises:
        FileExistsError: if ``path`` exists and ``overwrite`` is False.

    Example:
        >>> import tempfile
        >>> d = Path(tempfile.mkdtemp())
        >>> atomic_write(d / "a.txt", lambda p: p.write_text("hi")).read_text()
        'hi'
    """
    dest = Path(path)
    if not overwrite and dest.exists():
        raise FileExistsError(f"{dest} exists; pass overwrite=True (CLI: --force).")
    fd, tmp = tempfile.mkstemp(dir=dest.parent, prefix=f".{dest.name}.", suffix=".tmp")
    os.close(fd)
    try:
        write(Path(tmp))
        os.chmod(tmp, _default_mode())  # mkstemp creates 0600 files
        os.replace(tmp, dest)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return dest


def atomic_write_bytes(
    path: str | os.PathLike, data: bytes, *, overwrite: bool = True
) -> Path:
    """Write ``data`` to ``path`` atomically (see :func:`atomic_write`)."""
    return atomic_write(path, lambda p: p.write_bytes(data), overwrite=overwrite)


def atomic_write_text(
    path: str | os.PathLike, text: str, *, overwrite: bool = True
) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically (see :func:`atomic_write`)."""
    return atomic_write(
        path, lambda p: p.write_text(text, encoding="utf-8"), overwrite=overwrite
    )


def clean_json(obj: Any) -> Any:
    """``obj`` with NaN/inf floats replaced by None (standard JSON)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: clean_json(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [clean_json(v) for v in obj]
    return obj


def atomic_write_json(
    path: str | os.PathLike, obj: Any, *, overwrite: bool = True
) -> Path:
    """Write ``obj`` as indented standard JSON, atomically; returns ``path``.

    NaN and infinite floats are written as ``null`` (:func:`clean_json`); the
    project's one JSON writer (summaries, model settings).
    """
    text = json.dumps(clean_json(obj), indent=2, allow_nan=False) + "\n"
    return atomic_write_text(path, text, overwrite=overwrite)


#: errno values of conditions of the machine, not of diffaccel or its input
_CONDITIONS = {
    errno.EACCES: "permission denied",
    errno.EPERM: "permission denied",
    errno.EROFS: "read-only file system",
    errno.ENOSPC: "no space left on the device (disk full)",
    errno.EDQUOT: "disk quota exceeded",
    errno.EAGAIN: "locked by another program",
    errno.EBUSY: "busy (in use by another program)",
}


def os_condition(err: BaseException) -> str | None:
    """The machine's condition behind ``err`` in words, or None if it names none.

    Permission denied, read-only file system, disk full or quota exceeded, and
    a file locked by another program (HDF5 reports a lock as an ``OSError``
    whose message names it; an open file's lock is ``EAGAIN``/``EWOULDBLOCK``).
    """
    seen = err
    for _ in range(4):  # the error and its causes (h5py wraps the OS's)
        if isinstance(seen, OSError):
            code = seen.errno
            if code in _CONDITIONS:
                return _CONDITIONS[code]
            text = str(seen).lower()
            if "unable to lock file" in text or "file locking" in text:
                return "locked by another program (an open HDF5 viewer or writer?)"
            if "no space left" in text:
                return _CONDITIONS[errno.ENOSPC]
            if "read-only file system" in text:
                return _CONDITIONS[errno.EROFS]
            if "permission denied" in text:
                return _CONDITIONS[errno.EACCES]
        if seen.__cause__ is None:
            break
        seen = seen.__cause__
    return None


class OutputWriteError(OSError):
    """An output that could not be written; the message names the file and why."""


def os_error_text(err: BaseException, path: Path, doing: str = "write") -> str:
    """A one-line message for an OS condition while reading or writing ``path``.

    Names the condition (:func:`os_condition`) and what became of ``path``,
    e.g. ``cannot write out.h5: read-only file system (out lies on a read-only
    file system); nothing was replaced.``; other errors keep their own text.

    Example:
        >>> os_error_text(OSError(errno.EACCES, "x"), Path("b.h5"), doing="read")
        'cannot read b.h5: permission denied.'
    """
    condition = os_condition(err)
    if condition is None:
        return f"cannot {doing} {path}: {err}"
    if doing != "write":
        return f"cannot {doing} {path}: {condition}."
    hint = {
        "permission denied": f"the folder {path.parent} is not writable by you",
        "read-only file system": f"{path.parent} lies on a read-only file system",
    }.get(condition, "")
    where = f" ({hint})" if hint else ""
    return f"cannot write {path}: {condition}{where}; nothing was replaced."
