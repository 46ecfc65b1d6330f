"""Atomic writes leave either the old file or the complete new one."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import pytest

from diffaccel.data.atomic import (
    atomic_write,
    atomic_write_bytes,
    atomic_write_text,
    os_error_text,
)


def test_failed_write_keeps_old_content_and_leaves_no_temp_file(tmp_path: Path) -> None:
    dest = atomic_write_text(tmp_path / "a.json", "old")

    def broken(p: Path) -> None:
        p.write_text("half")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        atomic_write(dest, broken)
    assert dest.read_text() == "old"
    assert sorted(x.name for x in tmp_path.iterdir()) == ["a.json"]


def test_refuses_to_overwrite_when_asked(tmp_path: Path) -> None:
    dest = atomic_write_bytes(tmp_path / "b.bin", b"1")
    with pytest.raises(FileExistsError, match=r"b\.bin exists"):
        atomic_write_bytes(dest, b"2", overwrite=False)
    assert dest.read_bytes() == b"1"


def test_file_mode_follows_umask_not_mkstemp(tmp_path: Path) -> None:
    old = os.umask(0o022)
    try:
        dest = atomic_write_text(tmp_path / "c.txt", "x")
    finally:
        os.umask(old)
    assert dest.stat().st_mode & 0o777 == 0o644


def test_atomic_write_json_is_standard_json(tmp_path) -> None:
    import json
    import math

    from diffaccel.data import atomic_write_json

    dest = atomic_write_json(tmp_path / "s.json", {"a": [1.0, math.nan], "b": math.inf})
    text = dest.read_text(encoding="utf-8")
    assert "NaN" not in text and "Infinity" not in text  # strict parsers accept it
    assert json.loads(text) == {"a": [1.0, None], "b": None}


def test_os_error_text_names_the_condition_and_the_folder() -> None:
    out = Path("results") / "out.h5"
    text = os_error_text(OSError(errno.EROFS, "Read-only file system"), out)
    assert text == (
        "cannot write results/out.h5: read-only file system (results lies on a "
        "read-only file system); nothing was replaced."
    )
    full = os_error_text(OSError(errno.ENOSPC, "No space"), out)
    assert full.endswith(
        "no space left on the device (disk full); nothing was replaced."
    )
    locked = os_error_text(OSError(errno.EAGAIN, "x"), out, doing="read")
    assert locked == "cannot read results/out.h5: locked by another program."
    assert os_error_text(OSError("odd"), out) == "cannot write results/out.h5: odd"
