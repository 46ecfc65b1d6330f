"""Provenance and stored results shared by the benchmark scripts.

The scripts run as ``python benchmarks/X.py``. Every benchmark prints its
result with :func:`emit`: one JSON object on the last line of stdout, with a
``provenance`` entry (:func:`provenance`: the command, the machine, the date and
the commit). Each script has a ``headline(result) -> {figure: value}`` function
that turns its result into the figures of the docs' benchmarks page (formatted
strings with units) and a ``--store`` flag (:func:`add_store_flag`): with it,
:func:`emit` also writes the stored result ``benchmarks/results/NAME.json``
(:func:`store`), which ``docs/benchmarks_page.py`` turns into the page::

    {"name": NAME, "headline": {figure: value}, "note"?: text,
     "provenance": {"command", "machine" (one line), "date", "git_commit"},
     "result": the full printed result}

Without ``--store`` nothing under ``benchmarks/results/`` is touched.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shlex
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

from diffaccel.data import atomic_write_json, atomic_write_text

#: where the stored results live (one ``NAME.json`` per benchmark)
RESULTS = Path(__file__).resolve().parent / "results"

Headline = Callable[[dict], dict[str, str]]


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


def reconstruct_cli(
    data: Path, out: Path, threads: int, *options: str
) -> tuple[dict, float]:
    """Run ``diffaccel reconstruct DATA --out OUT OPTIONS`` as a user would, on
    ``threads`` threads; return its ``summary.json`` and the command's wall time
    [s] (Python's start-up included)."""
    command = [sys.executable, "-m", "diffaccel", "reconstruct", str(data)]
    command += ["--out", str(out), *options]
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    t0 = time.perf_counter()
    subprocess.run(command, check=True, env=env, stdout=subprocess.DEVNULL)
    seconds = time.perf_counter() - t0
    return json.loads((out / "summary.json").read_text()), seconds


def against_truth(mean: float, std: float, rel_err: float) -> tuple[float, bool]:
    """A reported ``mean +- std`` whose relative error against the truth is
    ``rel_err``: its std relative to the truth, and whether the truth lies within
    2 reported std."""
    true = mean / (1 + rel_err)
    return std / abs(true), abs(mean - true) <= 2 * std


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


def machine_line(info: dict | str) -> str:
    """One line for the page from :func:`machine`'s dict (a string is kept)."""
    if isinstance(info, str):
        return info
    parts = [str(info.get("cpu", "unknown CPU"))]
    if info.get("cores"):
        parts.append(f"{info['cores']} cores")
    if "load_avg_1min" in info:
        parts.append(f"load {float(info['load_avg_1min']):.1f}")
    if info.get("gpu"):
        parts.append(str(info["gpu"]))
    if info.get("torch"):
        parts.append(f"torch {info['torch']}")
    parts.append(f"Python {info.get('python', platform.python_version())}")
    return ", ".join(parts)


def span(values: list[float], fmt: str = ".2g") -> str:
    """``"lo-hi"`` of ``values`` formatted with ``fmt`` (one value if they agree)."""
    lo, hi = format(min(values), fmt), format(max(values), fmt)
    return lo if lo == hi else f"{lo}-{hi}"


def add_store_flag(parser: argparse.ArgumentParser) -> None:
    """Add the common ``--store`` flag (see :func:`emit`) to ``parser``."""
    parser.add_argument(
        "--store",
        action="store_true",
        help="also write the stored result benchmarks/results/NAME.json "
        "(headline figures, provenance, full result) for the docs' benchmarks page",
    )


def stored_result(
    result: dict,
    headline: Headline | dict[str, str],
    note: str | Callable[[dict], str | None] | None = None,
    name: str | None = None,
) -> dict:
    """The stored form of ``result`` (see the module docstring).

    Args:
        result: a benchmark's result (with ``provenance``; one is made if
            missing).
        headline: the benchmark's ``headline`` function, or its figures.
        note: optional text shown under the figures, or a function of
            ``result`` that returns it.
        name: the stored result's name (the script's, ``NAME.json``); default
            ``result["name"]``.

    Raises:
        ValueError: no name, or the headline is empty or not
            ``{str: str | number}``.
    """
    name = name or result.get("name")
    if not name:
        raise ValueError("benchmark result has no 'name'")
    figures = headline(result) if callable(headline) else headline
    if not figures or not all(
        isinstance(k, str) and isinstance(v, str | int | float)
        for k, v in figures.items()
    ):
        raise ValueError(f"{name}: headline must be a non-empty {{figure: value}}")
    if callable(note):
        note = note(result)
    prov = result.get("provenance") or provenance()
    stored: dict = {"name": name, "headline": dict(figures)}
    if note:
        stored["note"] = note
    stored["provenance"] = {
        "command": prov.get("command") or "not recorded",
        "machine": machine_line(prov.get("machine") or machine()),
        "date": prov.get("date") or "not recorded",
        "git_commit": prov.get("git_commit") or "unknown",
    }
    stored["result"] = {**result, "provenance": prov}
    return stored


def store(
    result: dict,
    headline: Headline | dict[str, str],
    note: str | Callable[[dict], str | None] | None = None,
    name: str | None = None,
    results: Path = RESULTS,
) -> Path:
    """Write ``results/NAME.json`` atomically (:func:`stored_result`); its path.

    Standard JSON: NaN and infinite floats are written as ``null``.
    """
    stored = stored_result(result, headline, note, name)
    path = Path(results) / f"{stored['name']}.json"
    return atomic_write_json(path, stored)


def emit(
    result: dict,
    path: Path | None = None,
    *,
    headline: Headline | None = None,
    store_result: bool = False,
    note: str | Callable[[dict], str | None] | None = None,
    name: str | None = None,
    results: Path = RESULTS,
) -> None:
    """Print ``result`` as one JSON line; also write it atomically to ``path``.

    A ``provenance`` entry (:func:`provenance`) is added unless ``result``
    has one. With ``store_result`` (the ``--store`` flag) the stored result
    ``results/NAME.json`` is also written from ``headline(result)`` and
    ``note`` (:func:`store`; ``name`` defaults to ``result["name"]``); a
    skipped run (``result["skipped"]``) is not stored and says so on stderr.
    """
    result = {**result, "provenance": result.get("provenance") or provenance()}
    text = json.dumps(result)
    if path is not None:
        atomic_write_text(path, text + "\n")
    print(text, flush=True)
    if store_result:
        if headline is None:
            raise ValueError("store_result needs the benchmark's headline function")
        if result.get("skipped"):
            print(f"not stored: {result['skipped']}", file=sys.stderr)
        else:
            written = store(result, headline, note, name, results)
            print(f"stored {written}", file=sys.stderr)
