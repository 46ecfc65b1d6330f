"""User-given text in figures is shown as written, never interpreted as TeX.

Element, scan and column names come from users' files and may hold ``$``,
``_``, ``^``, ``%`` or ``\\``. Matplotlib would parse the span between two
``$`` as mathtext (and with ``text.usetex`` every special character as TeX),
so a name such as ``Q$1`` or ``$\\frac{a$`` crashed the drawing at ``savefig``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import ParamSpec, TypeVar

import matplotlib as mpl

__all__ = ["literal", "no_usetex"]

_P = ParamSpec("_P")
_R = TypeVar("_R")


def literal(text: str) -> str:
    """``text`` with ``$`` escaped, so that matplotlib draws it literally.

    Example:
        >>> literal("Q$1.k1")
        'Q\\\\$1.k1'
    """
    return str(text).replace("$", r"\$")


def no_usetex(func: Callable[_P, _R]) -> Callable[_P, _R]:
    """Build the figure with ``text.usetex`` off (a user's matplotlibrc may set it)."""

    @functools.wraps(func)
    def wrapper(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        with mpl.rc_context({"text.usetex": False}):
            return func(*args, **kwargs)

    return wrapper
