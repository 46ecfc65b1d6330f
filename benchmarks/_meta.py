"""Provenance shared by the benchmark scripts (run as ``python benchmarks/X.py``).

Every benchmark prints its result with :func:`emit`: one JSON object on the last
line of stdout, with a ``provenance`` entry (:func:`provenance`: the command,
the machine, the date and the commit). ``docs/benchmarks_page.py`` turns such
results, stored under ``benchmarks/results/``, into the docs' benchmarks page.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import shlex
import subprocess
import sys
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


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine() -> dict:
    """The machine a benchmark runs on: CPU model, cores, load, OS, versions."""
    info = {
        "cpu": _cpu_model(),
        "cores": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
    }
    try:
        info["load_avg_1min"] = os.getloadavg()[0]
    except OSError:
        pass
    torch = sys.modules.get("torch")
    if torch is not None:
        info["torch"] = torch.__version__
        if torch.cuda.is_available():
            info["gpu"] = torch.cuda.get_device_name(0)
    return info


def provenance() -> dict:
    """Command, machine, UTC date and commit of the running benchmark."""
    script = Path(sys.argv[0])
    try:
        script = script.resolve().relative_to(Path(__file__).resolve().parents[1])
    except ValueError:
        pass
    return {
        "command": shlex.join(["python", str(script), *sys.argv[1:]]),
        "machine": machine(),
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "git_commit": git_commit(),
    }


def emit(result: dict, path: Path | None = None) -> None:
    """Print ``result`` as one JSON line; also write it atomically to ``path``.

    A ``provenance`` entry (:func:`provenance`) is added unless ``result``
    has one.
    """
    result = {**result, "provenance": result.get("provenance") or provenance()}
    text = json.dumps(result)
    if path is not None:
        atomic_write_text(path, text + "\n")
    print(text)
