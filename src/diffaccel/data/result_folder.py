"""All-or-nothing result folders: a run's outputs appear together or not at all.

A command that writes a folder of results (``reconstruct``, ``demo``,
``hysteresis fit``, ``hysteresis gp-fit``) writes into a staging folder beside
the destination, ``.<name>.partial``, and swaps it in when everything is
written. A failure at any point leaves an earlier result in the destination
untouched. A lock file beside the destination, ``.<name>.lock``, refuses a
second run into the same folder while one is running; a lock left by a process
that no longer exists (on this host) is taken over.

The staging folder of a failed run is removed, unless the command asks to
keep it (``keep_partial=True``) and it holds something: a reconstruction keeps
its checkpoint there, so ``--resume`` continues the interrupted run. The swap
is two renames within the parent folder (old result aside, staging in) and then
the removal of the old result; were the process killed between the renames,
the old result is still there as ``.<name>.old``.

A destination is only replaced with ``force`` (or ``resume``), and only if it
is empty or holds an earlier result of the same command and nothing else: the
marker file that every result folder gets (``.diffaccel-result``) names the
command and the files it wrote. A folder written before markers listed files
counts as a result if it holds nothing but names the command declares as its
own, as does one written before markers existed. A result of another command, a
folder with anything else in it (a user's notes beside a result), or one
holding an input of the run, is refused: nothing a user gave is deleted.

A staging folder kept by an interrupted run (``keep_partial``) is continued
with ``resume`` and discarded only with ``force``; a run with neither is
refused. A staging folder left by a killed command that keeps nothing for a
resume is half a result and removed.
"""

from __future__ import annotations

import fnmatch
import json
import os
import shutil
import socket
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = [
    "MARKER",
    "ResultFolder",
    "ResultFolderError",
    "partial_folder",
    "result_folder",
]

#: Marker file written into every result folder (JSON: command, time, pid and
#: ``files``, the sorted names the result wrote; markers of versions before
#: 2026-12 have no ``files``).
MARKER = ".diffaccel-result"


class ResultFolderError(OSError):
    """A result folder cannot be written: busy, not ours, not writable."""


class ResultFolder:
    """A result folder being written: files go to :attr:`path` (the staging folder).

    Attributes:
        out: The destination folder.
        path: The staging folder to write into; swapped in as ``out`` on success.
        previous: ``out`` as it was at the start if it held a result (where a
            resume may find earlier files), else None.
    """

    def __init__(self, out: Path, path: Path, previous: Path | None) -> None:
        self.out = out
        self.path = path
        self.previous = previous

    def __truediv__(self, name: str) -> Path:
        return self.path / name


def _sibling(out: Path, tag: str) -> Path:
    return out.parent / f".{out.name}.{tag}"


def partial_folder(out: str | os.PathLike) -> Path:
    """The staging folder of a run into ``out`` (kept after a failed run if asked)."""
    return _sibling(Path(out), "partial")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    except OSError:
        return False
    return True


def _take_lock(lock: Path, out: Path) -> None:
    me = {"pid": os.getpid(), "host": socket.gethostname(), "time": time.time()}
    for _ in range(2):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            try:
                holder = json.loads(lock.read_text(encoding="utf-8"))
                pid, host = int(holder["pid"]), str(holder["host"])
            except (OSError, ValueError, KeyError, TypeError):
                pid, host = -1, ""  # unreadable or half-written lock
                if time.time() - _mtime(lock) < 5.0:
                    pid, host = 0, "?"  # being written right now: treat as busy
            stale = host == socket.gethostname() and pid > 0 and not _pid_alive(pid)
            if pid == -1 or stale:
                lock.unlink(missing_ok=True)
                continue
            raise ResultFolderError(
                f"{out} is being written by another run (pid {pid} on {host}, lock "
                f"{lock}); wait for it to finish, or delete the lock file if no such "
                "run exists."
            ) from None
        except OSError as err:
            raise ResultFolderError(
                f"cannot write next to {out}: {err.strerror or err} ({lock})"
            ) from err
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(me, f)
        return
    raise ResultFolderError(f"cannot take the lock {lock} for {out}; try again.")


def _mtime(path: Path) -> float:
    try:
        return path.stat().st_mtime
    except OSError:
        return 0.0


def _marker(out: Path) -> dict:
    """The marker of the result in ``out`` ({} if unreadable)."""
    try:
        marker = json.loads((out / MARKER).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return marker if isinstance(marker, dict) else {}


def _foreign(out: Path, marker: dict, owned: Iterable[str]) -> list[str]:
    """Entries of ``out`` that are not (or may not be) results of the command.

    The marker's ``files`` are the result's; without them (a marker of an
    earlier version, or no marker) the names matching ``owned`` are.
    """
    entries = sorted(p.name for p in out.iterdir() if p.name != MARKER)
    files = marker.get("files")
    if isinstance(files, list):
        written = {str(f) for f in files}
        return [n for n in entries if n not in written]
    pats = list(owned)
    return [n for n in entries if not any(fnmatch.fnmatch(n, p) for p in pats)]


def _names(names: list[str]) -> str:
    return f"{', '.join(names[:5])}{', ...' if len(names) > 5 else ''}"


def _inside(path: Path, folder: Path) -> bool:
    try:
        path.resolve().relative_to(folder.resolve())
    except ValueError:
        return False
    return True


@contextmanager
def result_folder(
    out: str | os.PathLike,
    *,
    command: str,
    force: bool = False,
    resume: bool = False,
    keep_partial: bool = False,
    owned: Iterable[str] = (),
    inputs: Iterable[str | os.PathLike] = (),
) -> Iterator[ResultFolder]:
    """Write a result folder all-or-nothing (see the module docstring).

    Args:
        out: Destination folder.
        command: Name of the command, recorded in the marker file.
        force: Replace an existing result of ``command`` in ``out``, and
            discard a staging folder kept by an interrupted run.
        resume: Continue a kept staging folder (implies ``force`` for ``out``);
            without a staging folder, start one from ``out``'s files.
        keep_partial: Keep the staging folder when the body raises (a later
            ``resume`` continues from it); otherwise it is removed, as is
            one a ``resume`` started from ``out``'s files.
        owned: Glob patterns of the files the command writes; a folder whose
            marker lists no files (or without a marker) holding only such
            names counts as an earlier result.
        inputs: Files the run reads; refused if one lies inside ``out``.

    Yields:
        The :class:`ResultFolder`; write into ``folder.path``.

    Raises:
        ResultFolderError: ``out`` is a file, holds a result and neither
            ``force`` nor ``resume`` is given, holds a result of another
            command or files that the result did not write, holds an input, is
            being written by another run, has a kept staging folder and neither
            ``force`` nor ``resume`` is given, or cannot be written (checked
            before the body runs).

    Example:
        >>> import tempfile
        >>> out = Path(tempfile.mkdtemp()) / "run"
        >>> with result_folder(out, command="doc") as folder:
        ...     _ = (folder.path / "a.txt").write_text("1")
        >>> sorted(p.name for p in out.iterdir())
        ['.diffaccel-result', 'a.txt']
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ResultFolderError(f"--out {out} exists and is not a folder.")
    parent = out.parent if str(out.parent) else Path(".")
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ResultFolderError(
            f"cannot create the folder {parent}: {err.strerror or err}"
        ) from err
    for src in inputs:
        if out.exists() and _inside(Path(src), out):
            raise ResultFolderError(
                f"input {src} lies inside --out {out}, which this run replaces; "
                "move it or choose another --out."
            )
    lock = _sibling(out, "lock")
    _take_lock(lock, out)
    staging = partial_folder(out)
    try:
        has_result = out.exists() and any(out.iterdir())
        if has_result:
            marked = (out / MARKER).exists()
            marker = _marker(out) if marked else {}
            # a marker naming no command (unreadable) leaves the names to judge
            if marker.get("command", command) != command:
                raise ResultFolderError(
                    f"--out {out} holds a result of {marker['command']!r}, not of "
                    f"{command!r}; choose another (new or empty) folder."
                )
            foreign = _foreign(out, marker, owned)
            if foreign and marked:
                raise ResultFolderError(
                    f"--out {out} holds files its result did not write "
                    f"({_names(foreign)}); move them out of it or choose another "
                    "folder."
                )
            if foreign:
                raise ResultFolderError(
                    f"--out {out} holds files that are not a diffaccel result "
                    f"({_names(foreign)}); choose another (new or empty) folder."
                )
            if not (force or resume):
                # only commands that keep a failed run's files can resume it
                hint = ""
                if keep_partial:
                    hint = " or --resume to continue an interrupted run"
                raise ResultFolderError(
                    f"--out {out} is not empty; pass --force to replace it{hint}."
                )
            if not os.access(out, os.W_OK | os.X_OK):
                raise ResultFolderError(f"--out {out} is not writable.")
        if staging.exists() and not resume:
            kept = sorted(p.name for p in staging.iterdir())
            if kept and keep_partial and not force:
                raise ResultFolderError(
                    f"{staging} holds an interrupted run's files ({_names(kept)}); "
                    "pass --resume to continue it or --force to discard it."
                )
            shutil.rmtree(staging)
        copied = False  # the staging folder starts as a copy of out's result
        if not staging.exists():
            staging.mkdir()
            if resume and has_result:  # continue from the completed folder's files
                copied = True
                for p in out.iterdir():
                    if p.is_file():
                        shutil.copy2(p, staging / p.name)
        probe = staging / ".write-test"
        probe.write_bytes(b"")
        probe.unlink()
    except ResultFolderError:
        lock.unlink(missing_ok=True)
        raise
    except OSError as err:
        lock.unlink(missing_ok=True)
        raise ResultFolderError(
            f"cannot write results next to {out}: {err.strerror or err} "
            f"({getattr(err, 'filename', None) or staging})"
        ) from err
    folder = ResultFolder(out, staging, out if has_result else None)
    try:
        try:
            yield folder
        except BaseException:
            # an empty staging folder has nothing to resume from, nor has a
            # copy of out's result (a resume continues from out itself)
            if not keep_partial or copied or not any(staging.iterdir()):
                shutil.rmtree(staging, ignore_errors=True)
            raise
        files = sorted(p.name for p in staging.iterdir() if p.name != MARKER)
        marker = {
            "command": command,
            "written": time.time(),
            "pid": os.getpid(),
            "files": files,
        }
        (staging / MARKER).write_text(json.dumps(marker) + "\n", encoding="utf-8")
        old = _sibling(out, "old")
        if old.exists():
            shutil.rmtree(old)
        if out.exists():
            os.replace(out, old)
        os.replace(staging, out)
        shutil.rmtree(old, ignore_errors=True)
    finally:
        lock.unlink(missing_ok=True)
