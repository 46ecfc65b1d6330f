"""Errors raised by the ``diffaccel.data`` readers, writers and containers."""

from __future__ import annotations

__all__ = ["FormatError"]


class FormatError(ValueError):
    """A file or container that does not follow its documented format.

    The message names the field (HDF5 attribute, dataset or dataclass field), what
    was expected and what was found, e.g. ``"images: expected 4 dimensions
    (K, S, H, W); found shape (20, 100, 100)"``.
    """
