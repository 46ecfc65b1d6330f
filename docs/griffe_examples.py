"""Griffe extension: read a Google-style ``Example:`` section as ``Examples:``.

The docstrings name their doctest section ``Example:``; griffe's Google parser
knows only ``Examples:`` as a section of code examples and would render the
singular as an admonition of plain Markdown (``>>>`` lines as block quotes).
Used by ``mkdocs.yml`` (mkdocstrings' Python handler, ``extensions``).
"""

from __future__ import annotations

import re
from typing import Any

import griffe

_EXAMPLE = re.compile(r"^(\s*)Example:\s*$", re.MULTILINE)


class ExampleSections(griffe.Extension):
    """Rename ``Example:`` section titles to ``Examples:`` before parsing."""

    def on_instance(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = _EXAMPLE.sub(r"\1Examples:", obj.docstring.value)
