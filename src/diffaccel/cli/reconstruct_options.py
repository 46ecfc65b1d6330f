"""The options of ``diffaccel reconstruct`` and what they set in the config."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import click
from click.core import ParameterSource

from diffaccel.cli.options import seed_option
from diffaccel.reconstruction import ReconstructionConfig
from diffaccel.reconstruction.probe import PROBE_STEP

__all__ = ["PARAMETER_FLAGS", "config_options", "given_flags", "reconstruct_options"]

F = TypeVar("F", bound=Callable)

_DEFAULTS = {d: ReconstructionConfig(dims=d) for d in (4, 6)}


#: Parameters of ``reconstruct`` that set the config, by their flags.
PARAMETER_FLAGS = {
    "dims": "--dims",
    "particles": "--particles",
    "steps": "--steps",
    "snapshots": "--snapshots",
    "seed": "--seed",
    "image_loss": "--image-loss",
    "blur": "--blur",
    "loss_smoothing": "--loss-smoothing",
    "uncoupled": "--uncoupled",
    "probe": "--probe",
}


def _loss_smoothing(value: str | None) -> float | str | None:
    """``--loss-smoothing`` as the config takes it (one-line error otherwise)."""
    if value is None or value == "auto":
        return value
    try:
        return float(value)
    except ValueError:
        raise click.BadParameter(
            f"expected a number of pixels or 'auto'; got {value!r}.",
            param_hint="--loss-smoothing",
        ) from None


def given_flags(ctx: click.Context) -> set[str]:
    """The flags of :data:`PARAMETER_FLAGS` given on the command line."""
    return {
        flag
        for name, flag in PARAMETER_FLAGS.items()
        if ctx.get_parameter_source(name) in (ParameterSource.COMMANDLINE,)
    }


def config_options(
    *,
    dims: str,
    particles: int | None,
    steps: int | None,
    snapshots: int | None,
    seed: int,
    image_loss: str,
    blur: float | None,
    loss_smoothing: str | None,
    uncoupled: bool,
    probe: bool | None,
) -> dict[str, Any]:
    """The options as :class:`ReconstructionConfig` keywords (None: the default)."""
    return {
        "dims": int(dims),
        "n_particles": particles,
        "steps": steps,
        "snapshots": snapshots,
        "seed": seed,
        "image_loss": image_loss,
        "blur_pixels": blur,
        "loss_smoothing": _loss_smoothing(loss_smoothing),
        "place_coupling": uncoupled,
        "probe_unseen": None if probe is None else PROBE_STEP if probe else 0.0,
    }


#: The argument and options of ``reconstruct``, in the order of its ``--help``.
_OPTIONS = [
    click.argument(
        "dataset", type=click.Path(exists=True, dir_okay=False, path_type=Path)
    ),
    click.option(
        "--out",
        type=click.Path(file_okay=False, path_type=Path),
        required=True,
        help="Output directory (ensemble, summary.json, figures).",
    ),
    click.option(
        "--particles",
        type=click.IntRange(min=16),
        default=None,
        help="Fresh particles per training step [default: "
        f"{_DEFAULTS[4].n_particles} for --dims 4, {_DEFAULTS[6].n_particles} for "
        "--dims 6].",
    ),
    click.option(
        "--steps",
        "--epochs",
        "steps",
        type=click.IntRange(min=1),
        default=None,
        help="Optimisation steps (multiple of --snapshots); --epochs is an alias "
        f"[default: {_DEFAULTS[4].steps} for --dims 4, {_DEFAULTS[6].steps} for "
        "--dims 6].",
    ),
    click.option(
        "--snapshots",
        type=click.IntRange(min=1),
        default=None,
        help="Cosine learning-rate cycles; the ensemble keeps the last snapshots - "
        f"burn-in (burn-in {_DEFAULTS[4].burn_in} for --dims 4, "
        f"{_DEFAULTS[6].burn_in} for --dims 6) [default: {_DEFAULTS[4].snapshots} for "
        f"--dims 4, {_DEFAULTS[6].snapshots} for --dims 6].",
    ),
    seed_option,
    click.option(
        "--device", default="cpu", show_default=True, help="cpu, cuda, cuda:1..."
    ),
    click.option(
        "--train-indices",
        default="all",
        show_default=True,
        help="Settings to train on, per scan: all, even, odd or a list like 0,2,4 "
        "(the same rule in every scan), or SCAN:RULE;SCAN:RULE (e.g. "
        "'dipole_off:0,1,4,5;dipole_on:all'; scans not named are held out). The "
        "others are held out and scored.",
    ),
    click.option(
        "--dims",
        type=click.Choice(["4", "6"]),
        default="4",
        show_default=True,
        help="4: transverse phase space only; 6: also z, pz (seen with a deflecting "
        "cavity and/or dispersion; otherwise weakly constrained).",
    ),
    click.option(
        "--image-loss",
        type=click.Choice(["kl", "l1", "l2"]),
        default=_DEFAULTS[4].image_loss,
        show_default=True,
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
    click.option(
        "--uncoupled",
        is_flag=True,
        help="--dims 6: put the x-y coupling that the screens barely see (x-py, "
        "px-y against px-py) at the largest entropy instead of where training "
        "settled: the 4D and 6D emittances then do not depend on training there. "
        "Right for beams not turned in x-y; wrong for beams turned in x-y (e.g. "
        "by a solenoid).",
    ),
    click.option(
        "--probe/--no-probe",
        default=None,
        help="--dims 6: let the training images move the beam off the stated prior "
        "point along the px-pz direction the screens cannot see (zero px-pz partial "
        "correlation) where members refitted there fit clearly better: a "
        "likelihood-ratio probe on the side away from where training left the "
        "members, one or more extra refits per member (about 20 s on two CPU cores) "
        "[default: on for --dims 6].",
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
        show_default=True,
        help="Calibrated moment std (moment-space posterior, see "
        "docs/methods/uncertainty.md) and the per-pixel spread in the image figures; "
        "--no-uncertainty reports the ensemble scatter only (faster, under-covers).",
    ),
    click.option(
        "--force",
        is_flag=True,
        help="Replace an earlier reconstruction in --out (at the end); discard an "
        "interrupted run's checkpoint in .OUT.partial.",
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
        show_default=True,
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
