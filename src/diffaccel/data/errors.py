"""Errors raised by the ``diffaccel.data`` readers, writers and containers, and
the refusal of one option's value that library functions behind the CLI raise."""

from __future__ import annotations

__all__ = ["FormatError", "OptionError"]


class FormatError(ValueError):
    """A file or container that does not follow its documented format.

    The message names the field (HDF5 attribute, dataset or dataclass field), what
    was expected and what was found, e.g. ``"images: expected 4 dimensions
    (K, S, H, W); found shape (20, 100, 100)"``.
    """


class OptionError(ValueError):
    """A value refused for one option of a command (``option``: its flag).

    Raised by the library functions that check a command's inputs, so that
    the command can name the option, e.g. ``OptionError("41 exceeds the 40
    rows of m.csv.", "--train-rows")``.
    """

    def __init__(self, message: str, option: str) -> None:
        super().__init__(message)
        self.option = option
