"""Provenance shared by the benchmark scripts (run as ``python benchmarks/X.py``)."""

from __future__ import annotations

import subprocess
from pathlib import Path


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
