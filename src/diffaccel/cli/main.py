"""The ``diffaccel`` command-line tool: one click group, commands in sibling modules.

Each command's module (and with it torch, h5py, matplotlib, gpytorch, botorch...)
is imported only when that command runs: ``diffaccel --help`` lists the commands
from the table below without importing any of them, so it costs the start-up of
Python and click alone. ``tests/cli/test_main.py`` checks that the table's help
lines equal the commands' own docstrings and that ``--help`` stays light.
"""

from __future__ import annotations

import gc
import importlib
import logging
import os
import sys
import threading
from typing import Any

import click

from diffaccel import __version__

#: command name -> (module, attribute, one-line help shown by ``diffaccel --help``)
COMMANDS: dict[str, tuple[str, str, str]] = {
    "data": (
        "diffaccel.cli.data_cmd",
        "data",
        "Quad-scan files from DAQ output: camera frames, knob tables, backgrounds.",
    ),
    "demo": (
        "diffaccel.cli.demo",
        "demo",
        "Simulate a 6D quad scan and reconstruct it end to end (a few minutes on CPU).",
    ),
    "design": (
        "diffaccel.cli.design",
        "design_command",
        "What the scans in DATA determine and which settings to add.",
    ),
    "hysteresis": (
        "diffaccel.cli.hysteresis",
        "hysteresis",
        "Preisach hysteresis models of magnets: fit and predict.",
    ),
    "lattice": (
        "diffaccel.cli.lattice",
        "lattice",
        "List a lattice FILE (Bmad, elegant, LatticeJSON) read through cheetah.",
    ),
    "predict": (
        "diffaccel.cli.predict",
        "predict",
        "Ensemble-mean screen images of a reconstruction (RESULT_DIR) for new "
        "settings.",
    ),
    "reconstruct": (
        "diffaccel.cli.reconstruct",
        "reconstruct_command",
        "Reconstruct a beam's phase space from the quad-scan file DATASET.",
    ),
    "synthetic": (
        "diffaccel.cli.synthetic",
        "synthetic",
        "Simulate a quadrupole scan of a known beam and write it to OUT (HDF5).",
    ),
}
#: group name -> its subcommands, each (module, attribute, one-line help); a
#: subcommand's module is imported only when it runs (``hysteresis predict``
#: must not pay for the plotting of ``fit`` or the GP libraries of ``gp-fit``)
SUBCOMMANDS: dict[str, dict[str, tuple[str, str, str]]] = {
    "data": {
        "import": (
            "diffaccel.cli.data_import",
            "import_command",
            "Build a quad-scan file (format 2) from the DAQ files EXPERIMENT.yaml "
            "names.",
        ),
    },
    "hysteresis": {
        "fit": (
            "diffaccel.cli.hysteresis_fit",
            "fit_command",
            "Fit a Preisach model to the first N rows of DATA (CSV) and test on "
            "the rest.",
        ),
        "gp-fit": (
            "diffaccel.cli.hysteresis_gp",
            "gp_fit",
            "Fit a joint hysteresis GP (Preisach state -> response) to DATA.csv.",
        ),
        "predict": (
            "diffaccel.cli.hysteresis_predict",
            "predict_command",
            "Predict every row of a CSV (streamed), from the fit's initial state.",
        ),
        "set": (
            "diffaccel.cli.hysteresis_set",
            "set_command",
            "The input that brings a fitted magnet to TARGET after its history.",
        ),
    },
}


def _import(module: str, attr: str) -> click.Command:
    """``module.attr``, imported with the cyclic garbage collector paused.

    A command's module brings torch (and numpy, h5py, matplotlib...): some
    300 000 objects that live as long as the process. Collected as they come,
    they cost repeated full collections during the import and every later one
    traverses them again (~1 s of CPU in a default ``reconstruct``).
    Imports create little garbage, so the collector is paused while they run
    and what is alive afterwards goes to the permanent generation
    (``gc.freeze``), which collections skip.
    """
    enabled = gc.isenabled()
    gc.disable()
    try:
        cmd = getattr(importlib.import_module(module), attr)
    finally:
        if enabled:
            gc.enable()
    gc.freeze()
    return cmd


def load_command(name: str) -> click.Command:
    """Import the module of command ``name`` and return the command.

    A group in ``SUBCOMMANDS`` is a :class:`LazyGroup` over its table there:
    its subcommands are listed from the table and imported when they run.
    Only ``cli`` modules are loaded this way (the leaf room: nothing imports
    it, so deferring these imports cannot hide an import cycle).
    """
    return _import(*COMMANDS[name][:2])


def _short_help(text: str, limit: int) -> str:
    """``text`` shortened as click shortens a command's help in a listing."""
    return click.Command("_", help=text).get_short_help_str(limit)


class LazyGroup(click.Group):
    """A click group whose commands are imported when they are invoked.

    ``table`` maps command names to ``(module, attribute, help)``; the top
    level uses ``COMMANDS``, a group of subcommands its table in
    ``SUBCOMMANDS``.
    """

    def __init__(
        self, *args: Any, table: dict[str, tuple[str, str, str]] | None = None, **kw
    ) -> None:
        super().__init__(*args, **kw)
        self.table = COMMANDS if table is None else table

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(self.table)

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        if cmd_name not in self.table:
            return None
        if cmd_name not in self.commands:
            self.commands[cmd_name] = _import(*self.table[cmd_name][:2])
        return self.commands[cmd_name]

    def invoke(self, ctx: click.Context) -> object:
        """Run the command; an unforeseen exception becomes one line (``-vv``: raise).

        Commands report the errors they expect themselves, naming the file, field
        and problem; this is the net below them, so that a user never sees a
        traceback unless asking for one.
        """
        try:
            return super().invoke(ctx)
        except (click.ClickException, click.exceptions.Exit, click.Abort):
            raise
        except Exception as err:
            # -v is an option of the top-level group: a nested group (hysteresis)
            # reads it from the root context
            if ctx.find_root().params.get("verbose", 0) >= 2:
                raise
            first = str(err).strip().splitlines()[0] if str(err).strip() else ""
            raise click.ClickException(
                f"unexpected {type(err).__name__}: {first} (this is a bug in "
                "diffaccel; please report it with the command line; -vv shows the "
                "traceback)"
            ) from err

    def format_commands(
        self, ctx: click.Context, formatter: click.HelpFormatter
    ) -> None:
        # the table's help lines, so that listing imports no command module
        # (same truncation as click.Group.format_commands)
        names = self.list_commands(ctx)
        limit = formatter.width - 6 - max(len(n) for n in names)
        rows = [(n, _short_help(self.table[n][2], limit)) for n in names]
        with formatter.section("Commands"):
            formatter.write_dl(rows)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="diffaccel")
@click.option(
    "-v", "--verbose", count=True, help="More log output (-v info, -vv debug)."
)
def main(verbose: int) -> None:
    """Differentiable modeling of particle accelerators."""
    level = logging.WARNING - 10 * min(verbose, 2)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")


def run() -> None:
    """``diffaccel`` as a program: run the command, then end the process at once.

    Once a command has returned (its files written and closed), the
    interpreter's teardown would still free the objects of torch, numpy,
    matplotlib... one by one and collect the garbage of the figures: ~0.5 s
    of a default ``reconstruct`` for nothing the command needs.
    ``run`` flushes logging and the standard streams and ends the process
    with ``os._exit`` and the command's exit status. Where that could lose
    work (a non-daemon thread still running, a stream that cannot be flushed)
    the normal exit runs instead. ``python -m diffaccel`` and the
    ``diffaccel`` script call this; tests call :func:`main`.
    """
    try:
        main()
    except SystemExit as exc:
        code = exc.code
    else:  # click's standalone mode always raises SystemExit
        code = 0
    if code is None:
        code = 0
    elif not isinstance(code, int):  # sys.exit("message"): print it, status 1
        print(code, file=sys.stderr)
        code = 1
    others = [
        t
        for t in threading.enumerate()
        if t is not threading.main_thread() and not t.daemon and t.is_alive()
    ]
    if others:
        sys.exit(code)
    try:
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
    except (OSError, ValueError):  # e.g. a closed pipe: let Python report it
        sys.exit(code)
    os._exit(code)
