"""``diffaccel reconstruct``: phase-space reconstruction into a result folder.

The command parses its options (:mod:`diffaccel.cli.reconstruct_options`),
trains with :func:`diffaccel.reconstruction.reconstruct` and writes the folder
with :func:`diffaccel.reconstruction.results.run_in_folder` (figures drawn by
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

from diffaccel.cli.options import (
    check_device,
    check_memory,
    echo_lines,
    echo_warnings,
    read_dataset,
    shared_refusal,
)
from diffaccel.cli.options import join_distributed as _init_distributed
from diffaccel.cli.output import output_folder
from diffaccel.cli.reconstruct_options import (
    config_options,
    given_flags,
    reconstruct_options,
)
from diffaccel.data import MultiScanDataset, partial_folder
from diffaccel.plotting.reconstruction import (
    plot_corner,
    plot_image_comparison,
    write_image_figures,
    write_result_figures,
)
from diffaccel.reconstruction import (
    ReconstructionConfig,
    StepInfo,
    reconstruct,
    training_selection,
)
from diffaccel.reconstruction.results import (
    CHECKPOINT,
    OWNED,
    REPORT,
    SELECTION,
    ResultFigures,
    ResultWriteError,
    ResumeError,
    RunError,
    bunch_charge,
    finding_lines,
    resume_plan,
    resume_start,
    run_in_folder,
    score_lines,
    stopped_note,
)

__all__ = [
    "CHECKPOINT",
    "OWNED",
    "SELECTION",
    "echo_warnings",
    "reconstruct_command",
    "run_reconstruction",
]

#: The figures of a result folder, drawn with :mod:`diffaccel.plotting`.
FIGURES = ResultFigures(
    # the drawing functions are looked up here at each call: tests replace them
    summary=lambda *a: write_result_figures(*a, corner=plot_corner),
    images=lambda *a: write_image_figures(*a, plot=plot_image_comparison),
)


def run_reconstruction(
    ds: MultiScanDataset,
    dataset_path: Path,
    folder: Path,
    config: ReconstructionConfig,
    selection: dict[str, list[int]],
    device: torch.device | str,
    resume: bool,
    figures: bool = True,
    distributed: bool = False,
    split: str = "particles",
    uncertainty: bool = True,
    charge_C: float | None = None,
) -> dict[str, Any]:
    """Reconstruct with a progress bar, then write the result into ``folder``.

    ``folder`` is the staging folder of an :func:`~diffaccel.cli.output.output_folder`
    (the checkpoint and :data:`SELECTION` go there too); the files are those of
    :func:`~diffaccel.reconstruction.results.write_result`. With ``distributed``
    (an initialised ``torch.distributed`` group) every process trains its share
    (``split``) and only process 0 writes; the others return an empty dict.
    ``uncertainty``: attach the moment-space posterior (calibrated ``std``);
    without it ``std`` is the ensemble scatter only. ``charge_C``: bunch charge
    of ``particles.h5`` [C] (default: the dataset's, else 1 pC).
    """
    writer = not distributed or tdist.get_rank() == 0
    bar = tqdm(
        # set by the first report: training, plus the refit of placed members
        # where the scans leave directions unseen (not known before the fit)
        total=None,
        desc="reconstruct",
        unit="step",
        leave=False,
        disable=not writer,
    )

    def callback(info: StepInfo) -> None:
        bar.total = info.total  # the refit's steps only where it runs
        bar.n = info.step
        bar.set_postfix(
            image=f"{info.image_loss:.4f}", lr=f"{info.lr:.1e}", refresh=False
        )
        bar.refresh()

    try:
        with bar:
            return run_in_folder(
                ds,
                folder,
                config,
                selection,
                dataset_path=dataset_path,
                device=device,
                resume=resume,
                figures=FIGURES if figures else None,
                distributed=distributed,
                split=split,
                uncertainty=uncertainty,
                charge_C=charge_C,
                callback=callback,
                train=reconstruct,  # looked up here: tests wrap it
            )
    except RunError as err:  # bad data, options, checkpoint, calibration
        raise click.ClickException(str(err)) from err


@click.command("reconstruct")
@reconstruct_options
def reconstruct_command(
    dataset: Path,
    out: Path,
    particles: int | None,
    steps: int | None,
    snapshots: int | None,
    seed: int,
    device: str,
    train_indices: str,
    dims: str,
    image_loss: str,
    blur: float | None,
    loss_smoothing: str | None,
    uncoupled: bool,
    probe: bool | None,
    no_figures: bool,
    uncertainty: bool,
    force: bool,
    resume: bool,
    distributed: bool,
    split: str,
    charge_pc: float | None,
) -> None:
    """Reconstruct a beam's phase space from the quad-scan file DATASET.

    The results appear in OUT all together at the end (written into a
    staging folder ``.OUT.partial`` beside it first); an interrupted run keeps
    its checkpoint there and ``--resume`` continues it (``--force`` discards it).
    """
    ctx = click.get_current_context()
    given = given_flags(ctx)
    if split != "particles" and not distributed:
        raise click.BadParameter(
            "--split members needs --distributed (processes started by torchrun).",
            param_hint="--split",
        )
    # _init_distributed: a module name, looked up here (tests replace it)
    dev = _init_distributed(device) if distributed else check_device(device)
    writer = not distributed or tdist.get_rank() == 0
    options = config_options(
        dims=dims, particles=particles, steps=steps, snapshots=snapshots,
        seed=seed, image_loss=image_loss, blur=blur, loss_smoothing=loss_smoothing,
        uncoupled=uncoupled, probe=probe,
    )  # fmt: skip
    checkpoint = stored = None
    if resume:  # options not given are the checkpoint's
        try:
            checkpoint, stored, options = resume_start(out, options, given)
        except ResumeError as err:
            raise click.ClickException(str(err)) from err
    try:
        config = ReconstructionConfig(**options)
    except ValueError as err:
        raise click.ClickException(str(err)) from err
    ds = read_dataset(dataset)
    charge_C = None if charge_pc is None else charge_pc * 1e-12
    try:
        bunch_charge(ds, charge_C)  # a bad recorded charge refused before training
    except ResultWriteError as err:
        raise click.ClickException(f"{dataset}: {err}") from err
    indices_given = (
        ctx.get_parameter_source("train_indices") == ParameterSource.COMMANDLINE
    )
    try:
        selection = training_selection(ds, train_indices)
    except ValueError as err:
        if not indices_given:  # the file's own settings: no option to blame
            text = str(err).replace("train_indices select", "its settings hold", 1)
            raise click.ClickException(f"{dataset}: {text}") from err
        raise click.BadParameter(str(err), param_hint="--train-indices") from err
    if checkpoint is not None and stored is not None:
        try:
            config, selection, finished = resume_plan(
                checkpoint,
                stored,
                config,
                ds,
                selection,
                given=given,
                indices_given=indices_given,
                out=out,
            )
        except ResumeError as err:
            raise click.ClickException(str(err)) from err
        if finished:  # a finished result: nothing to continue
            if distributed:
                tdist.destroy_process_group()
            click.echo(
                f"nothing to resume: {out} holds the finished run of {checkpoint}; "
                "it is unchanged (use --force without --resume to run it again)."
            )
            return
        click.echo(f"resuming from {checkpoint} ({config})", err=True)
    if torch.device(dev).type == "cpu":
        check_memory(config, sum(len(v) for v in selection.values()))
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
        with shared_refusal(target, distributed) as folder:
            started = True  # the folder is this run's (not refused, not locked)
            summary = run_reconstruction(
                ds,
                dataset,
                folder.path,
                config,
                selection,
                dev,
                resume,
                figures=not no_figures,
                distributed=distributed,
                split=split,
                uncertainty=uncertainty,
                charge_C=charge_C,
            )
    except (KeyboardInterrupt, click.ClickException) as err:
        # a refused run (another run's lock) must not point at that run's files
        note = started and stopped_note(
            out, isinstance(err, KeyboardInterrupt), config.checkpoint_every
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
