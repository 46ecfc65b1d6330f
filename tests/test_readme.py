"""README.md is a product page: short, readable, and its set-up commands come first."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"


def _prose_lines(text: str) -> list[tuple[int, str]]:
    """Lines outside fenced code blocks and tables."""
    out, code = [], False
    for n, line in enumerate(text.splitlines(), 1):
        if line.startswith("```"):
            code = not code
            continue
        if not code and not line.lstrip().startswith("|"):
            out.append((n, line))
    return out


def test_readme_is_at_most_about_10_kb() -> None:
    assert README.stat().st_size <= 10 * 1024


def test_readme_prose_lines_are_at_most_200_characters() -> None:
    long = [
        (n, len(line))
        for n, line in _prose_lines(README.read_text())
        if len(line) > 200
    ]
    assert not long, f"README lines longer than 200 characters: {long}"


def test_readme_starts_with_the_two_make_commands() -> None:
    text = README.read_text()
    first = re.search(r"```bash\n(.*?)```", text, re.DOTALL)
    assert first is not None
    commands = [line.split("#")[0].strip() for line in first.group(1).splitlines()]
    assert commands == ["make demo", "make test"]
    makefile = (ROOT / "Makefile").read_text()
    assert re.search(r"^demo:", makefile, re.MULTILINE)
    assert re.search(r"^test:", makefile, re.MULTILINE)


def test_readme_links_point_to_files_that_exist() -> None:
    text = README.read_text()
    for target in re.findall(r"\]\(([^)#]+)\)", text):
        if "://" not in target:
            assert (ROOT / target).exists(), target
