"""The product text describes what the code does, not how it came to be.

README, docs, docstrings, comments, CLI help and test names carry no
development history: no "stop N" or "issue N" labels, no "session" or
"audit" narratives, no commit hashes, no dates of changes and no names of
internal study beams. The history lives in git. This test scans the text of
``src/``, ``tests/``, ``docs/`` (sources, not generated pages) and README.md,
the help of every CLI command and option, and the test names.

``benchmarks/`` is not scanned: its data tables name the synthetic beams the
benchmarks draw, and its stored results (``benchmarks/results/*.json``) record
the commit and date of each measurement as provenance.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import click
import pytest

ROOT = Path(__file__).resolve().parents[1]

#: (name, regular expression) of the history patterns, matched per line
PATTERNS: tuple[tuple[str, re.Pattern[str]], ...] = tuple(
    (name, re.compile(rx, re.IGNORECASE))
    for name, rx in (
        ("stop label", r"\bstops? \d+"),
        ("issue label", r"\bissues? #?\d+"),
        ("session", r"\bsessions?\b"),
        ("audit narrative", r"\baudit(s|ed|'s)?\b"),
        # 7-40 hex digits with at least one letter and one digit, not part of a
        # number (1.602176634e-19), an identifier or a 0x literal
        (
            "commit hash",
            r"(?<![\w.])(?=[0-9a-f]*[a-f])(?=[0-9a-f]*\d)[0-9a-f]{7,40}(?![\w.])",
        ),
        # a date as the time of a change or a measurement ("until 2026-11-27");
        # dates as data (a file's description, a time stamp) are not history
        (
            "date",
            r"\b(since|until|as of|before|after|measured|on)\s+20\d\d-[01]\d-[0-3]\d\b",
        ),
        (
            "internal beam name",
            r"\btilted\d{4}_\d+|\bfamily_draw_[ab]\b|\bdraw\d{4}_\d+",
        ),
    )
)

#: text that is not history although a pattern matches it
ALLOWED = (
    re.compile(r"""scope=["']session["']"""),  # pytest fixture scope
)

#: files the scan skips: this test (it spells the patterns out)
SKIP = {Path(__file__).resolve()}


def history_hits(text: str) -> list[tuple[int, str, str]]:
    """``(line number, pattern name, line)`` of every history match in ``text``."""
    hits = []
    for number, line in enumerate(text.splitlines(), 1):
        clean = line
        for allowed in ALLOWED:
            clean = allowed.sub("", clean)
        for name, rx in PATTERNS:
            if rx.search(clean):
                hits.append((number, name, line.strip()))
    return hits


def _product_files() -> list[Path]:
    files = [ROOT / "README.md"]
    for folder, patterns in (
        ("src", ("*.py",)),
        ("tests", ("*.py",)),
        ("docs", ("*.md", "*.py")),
    ):
        for pattern in patterns:
            files += sorted((ROOT / folder).rglob(pattern))
    generated = ROOT / "docs" / "generated"
    return [
        f
        for f in files
        if f.is_file() and f.resolve() not in SKIP and generated not in f.parents
    ]


def _report(hits: list[tuple[str, int, str, str]]) -> str:
    return "development history in the product text:\n" + "\n".join(
        f"  {where}:{n}: [{name}] {line[:160]}" for where, n, name, line in hits
    )


def test_patterns_catch_history_lines() -> None:
    module = '"""A module."""\n\nx = 1  # fixed in stop 31\n'
    assert [h[1] for h in history_hits(module)] == ["stop label"]
    for line, name in (
        ("# the default since issue 9", "issue label"),
        ("# measured in session stop 17", "session"),
        ("# reverted in 4b4a566", "commit hash"),
        ("# 30 of 33 audit runs met", "audit narrative"),
        ("# the default until 2026-11-27", "date"),
        ("# tilted3100_2 emit_z -30 %", "internal beam name"),
        ("# family_draw_b is placed wrong", "internal beam name"),
    ):
        assert name in [h[1] for h in history_hits(line)], line


def test_patterns_leave_present_tense_text_alone() -> None:
    text = (
        "ELEMENTARY_CHARGE = 1.602176634e-19  # [C]\n"
        '@pytest.fixture(scope="session")\n'
        "# stops the training when the loss is not finite; 0xdeadbeef1\n"
        "# the 6D estimator keeps 3 of 6 cycles; seeds 0-2\n"
        "description: AWA 6D scan, 2026-05-12\n"
    )
    assert history_hits(text) == []


def test_product_text_has_no_history() -> None:
    hits = []
    for path in _product_files():
        rel = path.relative_to(ROOT)
        for n, name, line in history_hits(path.read_text(encoding="utf-8")):
            hits.append((str(rel), n, name, line))
    assert not hits, _report(hits)


def _test_names() -> list[tuple[str, int, str]]:
    names = []
    for path in sorted((ROOT / "tests").rglob("test_*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.FunctionDef | ast.ClassDef) and (
                node.name.lower().startswith("test")
            ):
                names.append((str(path.relative_to(ROOT)), node.lineno, node.name))
    return names


def test_test_names_have_no_history() -> None:
    hits = []
    for where, n, name in _test_names():
        spoken = name.replace("_", " ")
        for _, pattern, _line in history_hits(spoken):
            hits.append((where, n, pattern, name))
    assert not hits, _report(hits)


def _help_texts(command: click.Command, path: str) -> list[tuple[str, str]]:
    texts = [(path, command.help or ""), (path, command.short_help or "")]
    for param in command.params:
        texts.append((f"{path} {param.name}", getattr(param, "help", None) or ""))
    if isinstance(command, click.Group):
        ctx = click.Context(command)
        for name in command.list_commands(ctx):
            sub = command.get_command(ctx, name)
            if sub is not None:
                texts += _help_texts(sub, f"{path} {name}")
    return texts


def test_cli_help_has_no_history() -> None:
    main = pytest.importorskip("diffaccel.cli.main")
    hits = []
    for where, text in _help_texts(main.main, "diffaccel"):
        for n, name, line in history_hits(text):
            hits.append((where, n, name, line))
    assert not hits, _report(hits)
