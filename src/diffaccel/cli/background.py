"""Figure work in a forked child: :mod:`diffaccel.reconstruction.background`."""

from diffaccel.reconstruction.background import can_fork, in_child

__all__ = ["can_fork", "in_child"]
