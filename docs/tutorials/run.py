"""Run the tutorial scripts and write their pages (called by ``make docs``).

Each tutorial is a plain Python script in this folder, listed in
:data:`TUTORIALS`. Its module docstring (Markdown) opens the page; the page
then shows the code, what the script printed and every figure (PNG) it saved
in its working directory. Pages and figures go to ``docs/generated/tutorials/``
(not tracked by git). A script that fails, or runs past ``--timeout`` seconds,
fails the docs build with its output.

To add a tutorial: write ``docs/tutorials/NAME.py``, add ``NAME`` to
:data:`TUTORIALS` and ``generated/tutorials/NAME.md`` to the ``nav`` of
``mkdocs.yml``.

Usage: ``python docs/tutorials/run.py [--only NAME ...] [--timeout S]``
"""

from __future__ import annotations

import argparse
import ast
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
OUT = ROOT / "docs" / "generated" / "tutorials"

#: Tutorial scripts in page order (file stems in this folder).
TUTORIALS = (
    "quad_scan_4d",
    "scan_6d",
    "bring_your_own",
    "magnet_fit",
    "hysteresis_bo",
)


def _split(source: str) -> tuple[str, str]:
    """The module docstring and the code after it."""
    tree = ast.parse(source)
    doc = ast.get_docstring(tree) or ""
    body = tree.body
    if doc and body:
        end = body[0].end_lineno or 0
        code = "\n".join(source.splitlines()[end:]).strip("\n")
    else:
        code = source.strip("\n")
    return doc, code


def run(name: str, timeout: float) -> float:
    """Run one tutorial, write its page; return the wall time [s]."""
    script = HERE / f"{name}.py"
    work = OUT / name
    work.mkdir(parents=True, exist_ok=True)
    for old in work.glob("*.png"):
        old.unlink()
    env = dict(os.environ, MPLBACKEND="Agg")
    env.setdefault("OMP_NUM_THREADS", "1")
    src = str(ROOT / "src")
    env["PYTHONPATH"] = os.pathsep.join([src, *filter(None, [env.get("PYTHONPATH")])])
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(
            [sys.executable, str(script)],
            cwd=work,
            env=env,
            capture_output=True,
            text=True,
            timeout=timeout,
        )
    except subprocess.TimeoutExpired as exc:
        raise SystemExit(f"tutorial {name}: ran past {timeout:.0f} s") from exc
    seconds = time.perf_counter() - t0
    if proc.returncode != 0:
        sys.stderr.write(proc.stdout + proc.stderr)
        raise SystemExit(f"tutorial {name}: exit status {proc.returncode}")
    doc, code = _split(script.read_text(encoding="utf-8"))
    title, _, intro = doc.partition("\n")
    lines = [
        f"# {title.strip().rstrip('.')}",
        "",
        intro.strip(),
        "",
        f"Source: `docs/tutorials/{name}.py` (run by `make docs`: {seconds:.0f} s "
        "on the machine that built this page).",
        "",
        "```python",
        code,
        "```",
        "",
        "## Output",
        "",
        "```text",
        proc.stdout.rstrip() or "(nothing printed)",
        "```",
        "",
    ]
    figures = sorted(work.glob("*.png"))
    if figures:
        lines += ["## Figures", ""]
        for fig in figures:
            lines += [f"![{fig.stem}]({name}/{fig.name})", ""]
    (OUT / f"{name}.md").write_text("\n".join(lines), encoding="utf-8")
    return seconds


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="*", choices=TUTORIALS, default=None)
    ap.add_argument("--timeout", type=float, default=600.0)
    args = ap.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    for name in args.only or TUTORIALS:
        seconds = run(name, args.timeout)
        print(f"tutorial {name}: {seconds:.1f} s")


if __name__ == "__main__":
    main()
