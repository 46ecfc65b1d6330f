"""``diffaccel reconstruct``: phase-space reconstruction into a result folder.

The command parses its options, checks the run with
:func:`diffaccel.reconstruction.results.plan_run`, trains with
:func:`diffaccel.reconstruction.reconstruct` and writes the folder with
:func:`diffaccel.reconstruction.results.run_in_folder` (figures drawn by
:mod:`diffaccel.plotting.reconstruction`); the resume policy is that of
:mod:`diffaccel.reconstruction.results`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from contextlib import nullcontext
from pathlib import Path
from types import SimpleNamespace
from typing import Any, TypeVar

import click
import torch
import torch.distributed as tdist
from click.core import ParameterSource
from tqdm import tqdm

from diffaccel.cli.output import (
    IN_FILE,
    OUT_DIR,
    SHOW_DEFAULTS,
    click_errors,
    echo_lines,
    echo_warnings,
    force_option,
    out_option,
    output_folder,
    seed_option,
)
from diffaccel.data import MultiScanDataset, partial_folder
from diffaccel.plotting.reconstruction import (
    plot_corner,
    plot_image_comparison,
    write_image_figures,
    write_result_figures,
)
from diffaccel.reconstruction import ReconstructionConfig, StepInfo, reconstruct
from diffaccel.reconstruction.results import (
    OWNED,
    REPORT,
    ResultFigures,
    RunError,
    config_options,
    finding_lines,
    plan_run,
    run_in_folder,
    score_lines,
    stopped_note,
)
from diffaccel.reconstruction.runtime import (
    init_distributed,
    memory_shortfall,
    resolve_device,
    shared_refusal,
)
from diffaccel.reconstruction.training import CHECKPOINT_EVERY

__all__ = ["check_device", "reconstruct_command", "run_reconstruction"]

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
        "--image-loss",
        type=click.Choice(["kl", "l1", "l2"]),
        default=_DEFAULTS[4].image_loss,
        help="Distance of simulated from measured images: kl (the images' Poisson "
        "log-likelihood), l1 or l2.",
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


def check_device(device: str) -> torch.device:
    """``--device`` as a torch device that exists here (one-line error otherwise)."""
    try:
        return resolve_device(device)
    except ValueError as err:
        raise click.BadParameter(str(err), param_hint="--device") from err


def _init_distributed(device: str) -> str:
    """Join the process group that torchrun describes; this process's device."""
    try:
        return init_distributed(device)
    except ValueError as err:
        raise click.ClickException(str(err)) from err


def _shared_refusal(target: Any, distributed: bool) -> Any:
    """Enter ``target`` (process 0's result folder); every process learns a refusal.

    See :func:`~diffaccel.reconstruction.runtime.shared_refusal`; the others
    raise ``process 0 stopped: <its one-line error>``.
    """
    return shared_refusal(
        target,
        distributed,
        refusal=click.ClickException,
        text=lambda err: err.format_message(),
        stopped=lambda text: click.ClickException(f"process 0 stopped: {text}"),
    )


#: The figures of a result folder, drawn with :mod:`diffaccel.plotting`.
FIGURES = ResultFigures(
    # the drawing functions are looked up here at each call: tests replace them
    summary=lambda *a: write_result_figures(*a, corner=plot_corner),
    images=lambda *a: write_image_figures(*a, plot=plot_image_comparison),
)


def run_reconstruction(
    ds: MultiScanDataset,
    folder: Path,
    config: ReconstructionConfig,
    selection: dict[str, list[int]],
    figures: bool = True,
    distributed: bool = False,
    **run: Any,
) -> dict[str, Any]:
    """Reconstruct with a progress bar, then write the result into ``folder``.

    ``folder`` is the staging folder of an :func:`~diffaccel.cli.output.output_folder`
    (the checkpoint and the training selection go there too); the files are those of
    :func:`~diffaccel.reconstruction.results.write_result`, the figures
    :data:`FIGURES` unless not ``figures``. With ``distributed`` (an
    initialised ``torch.distributed`` group) every process trains its share
    and only process 0 writes; the others return an empty dict. ``run``: the
    other keywords of :func:`~diffaccel.reconstruction.results.run_in_folder`
    (``dataset_path``, ``device``, ``resume``, ``split``, ``uncertainty``,
    ``charge_C``).
    """
    writer = not distributed or tdist.get_rank() == 0
    bar = tqdm(
        total=None,  # set by the first report (the run's training steps)
        desc="reconstruct",
        unit="step",
        leave=False,
        disable=not writer,
    )

    def callback(info: StepInfo) -> None:
        bar.total = info.total
        bar.n = info.step
        bar.set_postfix(
            image=f"{info.image_loss:.4f}", lr=f"{info.lr:.1e}", refresh=False
        )
        bar.refresh()

    # bad data, options, checkpoint, calibration: one line
    with bar, click_errors(RunError):
        return run_in_folder(
            ds,
            folder,
            config,
            selection,
            figures=FIGURES if figures else None,
            distributed=distributed,
            callback=callback,
            train=reconstruct,  # looked up here: tests wrap it
            **run,
        )


@click.command("reconstruct", context_settings=SHOW_DEFAULTS)
@reconstruct_options
def reconstruct_command(
    dataset: Path,
    out: Path,
    device: str,
    train_indices: str,
    no_figures: bool,
    uncertainty: bool,
    force: bool,
    resume: bool,
    distributed: bool,
    split: str,
    charge_pc: float | None,
    **config_values: Any,
) -> None:
    """Reconstruct a beam's phase space from the quad-scan file DATASET.

    The results appear in OUT all together at the end (written into a
    staging folder ``.OUT.partial`` beside it first); an interrupted run keeps
    its checkpoint there and ``--resume`` continues it (``--force`` discards it).
    """
    ctx = click.get_current_context()
    if split != "particles" and not distributed:
        raise click.BadParameter(
            "--split members needs --distributed (processes started by torchrun).",
            param_hint="--split",
        )
    # _init_distributed: a module name, looked up here (tests replace it)
    dev = _init_distributed(device) if distributed else check_device(device)
    writer = not distributed or tdist.get_rank() == 0
    with click_errors():  # --dims, --particles, --steps, ...: the config's
        options = config_options(**config_values)
    charge_C = None if charge_pc is None else charge_pc * 1e-12
    source = ctx.get_parameter_source("train_indices")
    with click_errors(RunError):
        plan = plan_run(
            dataset,
            out,
            options,
            given=given_flags(ctx, config_values),
            train_indices=train_indices,
            indices_given=source == ParameterSource.COMMANDLINE,
            resume=resume,
            charge_C=charge_C,
        )
    config, selection = plan.config, plan.selection
    if plan.finished:  # a finished result: nothing to continue
        if distributed:
            tdist.destroy_process_group()
        click.echo(
            f"nothing to resume: {out} holds the finished run of {plan.checkpoint}; "
            "it is unchanged (use --force without --resume to run it again)."
        )
        return
    if plan.checkpoint is not None:
        click.echo(f"resuming from {plan.checkpoint} ({config})", err=True)
    if torch.device(dev).type == "cpu":
        problem = memory_shortfall(config, sum(len(v) for v in selection.values()))
        if problem is not None:
            raise click.BadParameter(problem, param_hint="--particles")
    started = False
    try:
        if writer:
            target = output_folder(
                out,
                "reconstruct",
                force=force,
                resume=resume,
                keep_partial=True,
                owned=OWNED,
                inputs=[dataset],
            )
        else:  # process 0 owns the folder; the others read its checkpoint
            target = nullcontext(SimpleNamespace(path=partial_folder(out)))
        with _shared_refusal(target, distributed) as folder:
            started = True  # the folder is this run's (not refused, not locked)
            summary = run_reconstruction(
                plan.dataset,
                folder.path,
                config,
                selection,
                dataset_path=dataset,
                device=dev,
                resume=resume,
                figures=not no_figures,
                distributed=distributed,
                split=split,
                uncertainty=uncertainty,
                charge_C=charge_C,
            )
    except (KeyboardInterrupt, click.ClickException) as err:
        # a refused run (another run's lock) must not point at that run's files
        note = started and stopped_note(
            out, isinstance(err, KeyboardInterrupt), CHECKPOINT_EVERY
        )
        if note:
            click.echo(note, err=True)
        raise
    if distributed:
        tdist.destroy_process_group()
    if not summary:  # a process other than 0 of a distributed run
        return
    click.echo(f"wrote {out / 'summary.json'}")
    echo_lines(score_lines(summary))
    echo_warnings(summary.get("warnings", []))
    echo_lines(finding_lines(summary))
    click.echo(f"report: {out / REPORT}")
