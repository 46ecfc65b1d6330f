"""Griffe extension: docstrings written for Sphinx-like readers, read as Markdown.

- The docstrings name their doctest section ``Example:``; griffe's Google parser
  knows only ``Examples:`` as a section of code examples and would render the
  singular as an admonition of plain Markdown (``>>>`` lines as block quotes).
- Cross-reference roles (``:func:`name```, ``:class:`~pkg.Name```) become code
  spans of the name.

Used by ``mkdocs.yml`` (mkdocstrings' Python handler, ``extensions``).
"""

from __future__ import annotations

import re
from typing import Any

import griffe

_EXAMPLE = re.compile(r"^(\s*)Example:\s*$", re.MULTILINE)
_ROLE = re.compile(r":(?:func|class|meth|mod|data|attr|exc|obj):`~?([^`]+)`")


class ExampleSections(griffe.Extension):
    """Rename ``Example:`` sections, turn roles into code spans, before parsing."""

    def on_instance(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            value = _EXAMPLE.sub(r"\1Examples:", obj.docstring.value)
            obj.docstring.value = _ROLE.sub(r"`\1`", value)
