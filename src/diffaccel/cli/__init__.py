"""Command-line interface: argument parsing, progress bars, logging set-up."""

from diffaccel.cli.main import main

__all__ = ["main"]
