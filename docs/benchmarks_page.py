"""Write the docs' benchmarks page from the stored benchmark results.

Every script in ``benchmarks/`` (not the helpers ``benchmarks/_*.py``) gets a
section: what it measures (its docstring's first line), how to run it, and the
headline figures of its current stored result ``benchmarks/results/NAME.json``
with the command, machine, date and commit of that run (its ``provenance``).
A benchmark without a stored result is listed as such. The page is written to
``docs/generated/benchmarks.md`` (not tracked by git); ``make docs`` runs this
script before ``mkdocs build``.

A stored result is ``{"name", "headline": {figure: value}, "provenance":
{"command", "machine", "date", "git_commit"}, "note"?, "result"?}``: one current
number per figure; this script reads ``headline``, ``provenance`` and ``note``
and ignores other keys. The benchmarks write their stored results themselves:
``python benchmarks/NAME.py --store`` prints its full JSON as without the flag
and also writes ``benchmarks/results/NAME.json`` atomically, the figures from
the script's ``headline(result)``, the provenance of that run (command, machine
on one line, UTC date, commit) and the full printed result under ``result``
(``benchmarks/_meta.py``: ``emit``, ``store``). ``make bench STORE=--store``
runs every CPU benchmark that way; ``python benchmarks/gpu_checks.py --store``
runs the GPU checks and stores their summary the same way.
"""

from __future__ import annotations

import ast
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"
RESULTS = BENCH / "results"
OUT = ROOT / "docs" / "generated" / "benchmarks.md"

#: Page order: the reconstruction benchmarks, then hysteresis, then the GPU run.
GROUPS = (
    (
        "Beam dynamics and reconstruction",
        (
            "tracking",
            "reconstruction",
            "reconstruction_process",
            "reconstruction_step",
            "reconstruction_distributed",
            "cli_help",
            "reconstruction_6d",
            "reconstruction_6d_beams",
            "calibration",
            "background_bias",
            "daq_6d",
            "resolution",
            "camera_4d",
            "camera_6d",
            "validate_defaults",
            "alarms",
            "design",
            "design_6d",
            "design_check_6d",
        ),
    ),
    (
        "Hysteresis and Bayesian optimisation",
        (
            "preisach",
            "preisach_slac",
            "preisach_acceptance",
            "preisach_stream",
            "preisach_bh_loops",
            "hysteresis_alarms",
            "hgp_vs_gp",
            "bo_hysteresis",
            "xopt_hysteresis",
        ),
    ),
    ("GPU", ("gpu_checks",)),
)


INTRO = """\
Each benchmark in `benchmarks/` prints one JSON object (last line of stdout) with
its figures and a `provenance` entry: the command, the machine, the date and the
commit. `make bench` installs the anchors (`gpsr`, `cheetah-accelerator`) and runs
every CPU benchmark. The tables show the current stored result of each
(`benchmarks/results/NAME.json`), one number per figure; a benchmark run with
`--store` writes it from its own JSON (figures, command, machine, date, commit and
the full result; `make bench STORE=--store` for all); earlier runs are in the git
history. Timings on a shared 2-core machine vary by tens of percent with its
load; the ratios against an anchor are taken within one run."""


def _summary(path: Path) -> str:
    """First line of a script's docstring (Python) or leading comment (shell)."""
    text = path.read_text(encoding="utf-8")
    if path.suffix == ".py":
        doc = ast.get_docstring(ast.parse(text)) or ""
        return doc.strip().splitlines()[0] if doc.strip() else ""
    for line in text.splitlines()[1:]:
        if line.startswith("#"):
            return line.lstrip("# ").strip()
    return ""


def _scripts() -> dict[str, Path]:
    found = {p.stem: p for p in sorted(BENCH.glob("[!_]*.py"))}
    found.update({p.stem: p for p in sorted(BENCH.glob("[!_]*.sh"))})
    return found


def _cell(value: object) -> str:
    return str(value).replace("|", "\\|")


def _section(name: str, script: Path) -> list[str]:
    run = (
        f"bash benchmarks/{script.name}"
        if script.suffix == ".sh"
        else (f"python benchmarks/{script.name}")
    )
    lines = [f"### `{script.name}`", "", _summary(script), "", f"Run: `{run}`", ""]
    stored = RESULTS / f"{name}.json"
    if not stored.exists():
        return [*lines, "No stored result yet.", ""]
    result = json.loads(stored.read_text(encoding="utf-8"))
    lines += ["| figure | current value |", "|---|---|"]
    for figure, value in result.get("headline", {}).items():
        lines.append(f"| {_cell(figure)} | {_cell(value)} |")
    prov = result.get("provenance", {})
    machine = prov.get("machine", "not recorded")
    if isinstance(machine, dict):
        machine = ", ".join(f"{k} {v}" for k, v in machine.items())
    lines += [
        "",
        f"Command: `{prov.get('command', 'not recorded')}`; machine: {machine}; "
        f"date: {prov.get('date') or 'not recorded'}; commit: "
        f"{prov.get('git_commit') or 'not recorded'}.",
    ]
    if result.get("note"):
        lines += ["", f"Note: {result['note']}."]
    return [*lines, ""]


def main() -> None:
    scripts = _scripts()
    listed = {n for _, names in GROUPS for n in names}
    missing = sorted(set(scripts) - listed)
    if missing:
        raise SystemExit(f"benchmarks not on the page (add them to GROUPS): {missing}")
    lines = ["# Benchmarks", "", INTRO, ""]
    for title, names in GROUPS:
        lines += [f"## {title}", ""]
        for name in names:
            if name not in scripts:
                raise SystemExit(f"GROUPS names {name!r}, which is not in benchmarks/")
            lines += _section(name, scripts[name])
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text("\n".join(lines), encoding="utf-8")
    print(f"wrote {OUT.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
