"""``diffaccel reconstruct``: phase-space reconstruction into a result folder.

The command parses its options, checks the run with
:func:`diffaccel.reconstruction.results.plan_run`, trains with
:func:`diffaccel.reconstruction.reconstruct` and writes the folder with
:func:`diffaccel.reconstruction.results.run_in_folder` (figures drawn by
:mod:`diffaccel.plotting.reconstruction`); the resume policy is that of
:mod:`diffaccel.reconstruction.results`.
"""

from __future__ import annotations

from contextlib import nullcontext
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import click
import torch
import torch.distributed as tdist
from click.core import ParameterSource
from tqdm import tqdm

from diffaccel.cli.output import (
    SHOW_DEFAULTS,
    click_errors,
    echo_lines,
    echo_warnings,
    output_folder,
)
from diffaccel.cli.reconstruct_options import given_flags, reconstruct_options
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
