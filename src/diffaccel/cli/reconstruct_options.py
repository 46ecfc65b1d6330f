"""The argument and options of ``diffaccel reconstruct`` (its ``--help``)."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import TypeVar

import click
from click.core import ParameterSource

from diffaccel.cli.output import (
    IN_FILE,
    OUT_DIR,
    force_option,
    out_option,
    seed_option,
)
from diffaccel.reconstruction import ReconstructionConfig

__all__ = ["given_flags", "reconstruct_options"]

F = TypeVar("F", bound=Callable)

_DEFAULTS = {d: ReconstructionConfig(dims=d) for d in (4, 6)}


def _by_dims(field: str) -> str:
    """The config's default ``field`` for both ``--dims``, as the help states it."""
    four, six = (getattr(_DEFAULTS[d], field) for d in (4, 6))
    return f"{four} for --dims 4, {six} for --dims 6"


def given_flags(ctx: click.Context, names: Iterable[str]) -> set[str]:
    """The first flags of the parameters ``names`` given on the command line."""
    return {
        param.opts[0]
        for param in ctx.command.params
        if param.name in names
        and ctx.get_parameter_source(param.name) is ParameterSource.COMMANDLINE
    }


#: The argument and options of ``reconstruct``, in the order of its ``--help``.
_OPTIONS = [
    click.argument("dataset", type=IN_FILE),
    out_option(OUT_DIR, "Output directory (ensemble, summary.json, figures)."),
    click.option(
        "--particles",
        type=click.IntRange(min=16),
        default=None,
        help=f"Fresh particles per training step [default: {_by_dims('n_particles')}].",
    ),
    click.option(
        "--steps",
        "--epochs",
        "steps",
        type=click.IntRange(min=1),
        default=None,
        help="Optimisation steps (multiple of --snapshots); --epochs is an alias "
        f"[default: {_by_dims('steps')}].",
    ),
    click.option(
        "--snapshots",
        type=click.IntRange(min=1),
        default=None,
        help="Cosine learning-rate cycles; the ensemble keeps the last snapshots - "
        f"burn-in (burn-in {_by_dims('burn_in')}) [default: {_by_dims('snapshots')}].",
    ),
    seed_option,
    click.option("--device", default="cpu", help="cpu, cuda, cuda:1..."),
    click.option(
        "--train-indices",
        default="all",
        help="Settings to train on, per scan: all, even, odd or a list like 0,2,4 "
        "(the same rule in every scan), or SCAN:RULE;SCAN:RULE (e.g. "
        "'dipole_off:0,1,4,5;dipole_on:all'; scans not named are held out). The "
        "others are held out and scored.",
    ),
    click.option(
        "--dims",
        type=click.Choice(["4", "6"]),
        default="4",
        help="4: transverse phase space only; 6: also z, pz (seen with a deflecting "
        "cavity and/or dispersion; otherwise weakly constrained).",
    ),
    click.option(
        "--blur",
        type=click.FloatRange(min=0),
        default=None,
        help="Point-spread rms of simulated images [pixels] [default: the file's "
        "screen resolution_pixels where recorded, else 1.0 for --dims 4, sqrt(1/12) "
        "for --dims 6].",
    ),
    click.option(
        "--loss-smoothing",
        default=None,
        metavar="PIXELS|auto",
        help="Rms of the Gaussian applied to measured and simulated images before "
        "they are compared [camera pixels], or 'auto': sized per scan by the data "
        "(the widest image's rms times N^(-1/6) for N particles per step, at most "
        "the beam's smallest spot), so that the fit does not depend on the "
        "camera's pixel size; 0 compares pixel by pixel [default: auto for --dims "
        "4, 1 for --dims 6].",
    ),
    click.option("--no-figures", is_flag=True, help="Skip the PNG figures."),
    click.option(
        "--charge",
        "charge_pc",
        type=click.FloatRange(min=0, min_open=True),
        default=None,
        help="Bunch charge [pC] of the particles in particles.h5 [default: the "
        "dataset's metadata charge_C where recorded, else 1 pC].",
    ),
    click.option(
        "--uncertainty/--no-uncertainty",
        default=True,
        help="Calibrated moment std (moment-space posterior, see "
        "docs/methods/uncertainty.md) and the per-pixel spread in the image figures; "
        "--no-uncertainty reports the ensemble scatter only (faster, under-covers).",
    ),
    force_option(
        "Replace an earlier reconstruction in --out (at the end); discard an "
        "interrupted run's checkpoint in .OUT.partial."
    ),
    click.option(
        "--resume",
        is_flag=True,
        help="Continue the interrupted run into --out from its checkpoint (same data; "
        "options not given are the checkpoint's).",
    ),
    click.option(
        "--distributed",
        is_flag=True,
        help="Run on the processes started by torchrun (gloo on CPUs, NCCL with "
        "--device cuda: one GPU per process), sharing the work as --split says; "
        "process 0 writes --out. See docs/distributed.md.",
    ),
    click.option(
        "--split",
        type=click.Choice(["particles", "members"]),
        default="particles",
        help="With --distributed: 'particles' splits every step's particles across "
        "the processes (one ensemble, same answer as one process); 'members' trains "
        "one independent ensemble per process (process r: seed + 7919 r) and joins "
        "all members into one ensemble (P processes: P times the members).",
    ),
]


def reconstruct_options(command: F) -> F:
    """Apply the argument and options of ``reconstruct`` to ``command``."""
    for option in reversed(_OPTIONS):
        command = option(command)
    return command
