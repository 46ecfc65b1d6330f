"""``diffaccel data``: quad-scan files from what a DAQ leaves behind.

``data import EXPERIMENT.yaml --out DATA.h5`` reads the camera frames, knob
tables and background frames an experiment description names (schema in
``docs/file_formats.md``), preprocesses them and writes one quad-scan file
(format version 2). Nothing is written when an input is bad. The subcommand
lives in ``cli/data_import.py`` and is imported when it runs.
"""

from __future__ import annotations

import click

from diffaccel.cli.main import SUBCOMMANDS, LazyGroup

__all__ = ["data"]


@click.group("data", cls=LazyGroup, table=SUBCOMMANDS["data"])
def data() -> None:
    """Quad-scan files from DAQ output: camera frames, knob tables, backgrounds."""
