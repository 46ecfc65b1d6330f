"""The docs site's sources are complete: every page in the navigation, every
benchmark on the benchmarks page with a stored result, every tutorial run.

``make docs`` checks the same and more (``mkdocs build --strict``); these
checks need no MkDocs and run with the test suite.
"""

from __future__ import annotations

import importlib.util
import json
import re
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


def _module(path: Path) -> ModuleType:
    spec = importlib.util.spec_from_file_location(path.stem, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _nav_pages() -> set[str]:
    text = (ROOT / "mkdocs.yml").read_text()
    nav = text[text.index("\nnav:") :]
    return set(re.findall(r"^\s+-\s+(?:[^:\n]+:\s+)?(\S+\.md)\s*$", nav, re.MULTILINE))


def test_every_docs_page_is_in_the_navigation() -> None:
    pages = {
        str(p.relative_to(DOCS))
        for p in DOCS.rglob("*.md")
        if "generated" not in p.relative_to(DOCS).parts
    }
    assert pages <= _nav_pages(), sorted(pages - _nav_pages())
    assert "index.md" in _nav_pages()


def test_every_tutorial_is_run_and_in_the_navigation() -> None:
    run = _module(DOCS / "tutorials" / "run.py")
    scripts = {p.stem for p in (DOCS / "tutorials").glob("*.py")} - {"run"}
    assert set(run.TUTORIALS) == scripts
    nav = _nav_pages()
    for name in run.TUTORIALS:
        assert f"generated/tutorials/{name}.md" in nav, name


def test_every_benchmark_is_on_the_page_with_a_stored_result() -> None:
    page = _module(DOCS / "benchmarks_page.py")
    listed = [n for _, names in page.GROUPS for n in names]
    assert sorted(listed) == sorted(page._scripts())
    for name in listed:
        stored = ROOT / "benchmarks" / "results" / f"{name}.json"
        result = json.loads(stored.read_text())
        assert result["headline"], name
        prov = result["provenance"]
        assert prov["command"] and prov["machine"] and prov["date"], name


def test_the_build_fails_on_broken_links_and_anchors() -> None:
    # `mkdocs build --strict` turns these warnings into errors: a link to a page
    # that does not exist, to an anchor a page lacks, a page outside the nav
    text = (ROOT / "mkdocs.yml").read_text()
    assert re.search(r"^strict: true$", text, re.MULTILINE)
    block = text[text.index("\nvalidation:") :].split("\nnav:")[0]
    keys = ("omitted_files", "not_found", "absolute_links", "unrecognized_links")
    for key in (*keys, "anchors"):
        assert re.search(rf"^\s+{key}: warn$", block, re.MULTILINE), key
    ci = (ROOT / ".ci" / "docs").read_text()
    assert "set -euo pipefail" in ci and "make docs" in ci
    assert "--strict" in (ROOT / "Makefile").read_text()
