"""Provenance shared by the benchmark scripts (run as ``python benchmarks/X.py``)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

from diffaccel.data import atomic_write_text


def git_commit() -> str:
    """Full hash of the checked-out commit, or ``"unknown"`` outside git."""
    try:
        return subprocess.run(
            ["git", "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
            cwd=Path(__file__).resolve().parent,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def emit(result: dict, path: Path | None = None) -> None:
    """Print ``result`` as one JSON line; also write it atomically to ``path``."""
    text = json.dumps(result)
    if path is not None:
        atomic_write_text(path, text + "\n")
    print(text)
