"""``diffaccel reconstruct`` and ``diffaccel predict``: phase-space reconstruction."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import ExitStack, contextmanager, nullcontext
from functools import partial
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import click
import numpy as np
import torch
import torch.distributed as tdist
from click.core import ParameterSource
from tqdm import tqdm

from diffaccel.cli.background import can_fork, in_child
from diffaccel.cli.output import check_out_file, output_folder, save_png
from diffaccel.data import (
    FormatError,
    MultiScanDataset,
    atomic_write,
    atomic_write_json,
    partial_folder,
    read_scans,
    write_openpmd_particles,
    write_scans,
)
from diffaccel.plotting.reconstruction import (
    plot_corner,
    plot_image_comparison,
    plot_rms_evolution,
    plot_training_curves,
)
from diffaccel.reconstruction import (
    Reconstruction,
    ReconstructionConfig,
    ScreenForwardModel,
    StepInfo,
    as_scans,
    check_on_screen,
    evaluate,
    load,
    off_screen_warnings,
    predict_dataset,
    predicted_dataset,
    reconstruct,
    training_selection,
)
from diffaccel.reconstruction.alarms import prediction_alarms
from diffaccel.reconstruction.probe import PROBE_STEP
from diffaccel.reconstruction.training import CheckpointDataError, checkpoint_config

__all__ = ["predict", "reconstruct_command", "run_reconstruction"]

CHECKPOINT = "checkpoint.pt"
#: The training settings of a run, written beside its checkpoint so that
#: ``--resume`` needs no ``--train-indices``.
SELECTION = "selection.json"
_DEFAULTS = {d: ReconstructionConfig(dims=d) for d in (4, 6)}


def write_result_figures(
    result: Reconstruction, dataset: MultiScanDataset, out: Path
) -> list[str]:
    """Write ``phase_space.png``, ``training.png`` and ``rms_evolution.png``.

    The corner plot (truth overlaid when known), the training curves and the
    rms sizes during training; returns the file names.
    """
    figs = {
        "phase_space.png": plot_corner(result, dataset.ground_truth),
        "training.png": plot_training_curves(result),
        "rms_evolution.png": plot_rms_evolution(result, dataset.ground_truth),
    }
    return [save_png(fig, out / name, dpi=110).name for name, fig in figs.items()]


def write_image_figures(
    dataset: MultiScanDataset,
    train_indices: Mapping[str, Sequence[int]],
    out: Path,
    predicted: dict[str, torch.Tensor],
    predicted_std: dict[str, torch.Tensor] | None = None,
) -> list[str]:
    """Write one measured-vs-predicted image grid per scan; returns the file names.

    ``images.png`` for a single scan, ``images_<scan>.png`` otherwise
    (settings not in ``train_indices`` marked held out; with
    ``predicted_std`` a fourth row shows the per-pixel spread of the
    prediction).
    """
    names = []
    for name, scan in dataset:
        train = {int(i) for i in train_indices.get(name, [])}
        fwd = ScreenForwardModel.from_dataset(scan)
        fig_name = "images.png" if len(dataset) == 1 else f"images_{name}.png"
        fig = plot_image_comparison(
            scan.mean_images(),
            predicted[name],
            scan.settings,
            setting_name=", ".join(scan.setting_names),
            extent=fwd.extent_mm(),
            held_out=[i not in train for i in range(scan.n_settings)],
            title=f"scan {name!r}" if len(dataset) > 1 else "",
            predicted_std=None if predicted_std is None else predicted_std[name],
        )
        names.append(save_png(fig, out / fig_name, dpi=110).name)
    return names


#: Files a reconstruction writes (a folder of only these is an earlier result).
OWNED = (
    "ensemble.pt",
    "summary.json",
    "particles.h5",
    CHECKPOINT,
    SELECTION,
    "checkpoint.rank*.pt",  # the other processes' of --split members
    "*.png",
)
#: Parameters of ``reconstruct`` that set the config, by their flags.
PARAMETER_FLAGS = {
    "dims": "--dims",
    "particles": "--particles",
    "steps": "--steps",
    "snapshots": "--snapshots",
    "seed": "--seed",
    "image_loss": "--image-loss",
    "blur": "--blur",
    "uncoupled": "--uncoupled",
    "probe": "--probe",
}
#: Config fields set by ``reconstruct`` options, and those options.
CONFIG_OPTIONS = {
    "dims": "--dims",
    "n_particles": "--particles",
    "steps": "--steps",
    "snapshots": "--snapshots",
    "seed": "--seed",
    "image_loss": "--image-loss",
    "blur_pixels": "--blur",
    "place_coupling": "--uncoupled",
    "probe_unseen": "--probe",
}


def check_device(device: str) -> torch.device:
    """``--device`` as a torch device that exists here (one-line error otherwise)."""
    try:
        dev = torch.device(device)
    except (RuntimeError, ValueError) as err:
        raise click.BadParameter(
            f"{device!r} is not a device (cpu, cuda, cuda:1, mps...)",
            param_hint="--device",
        ) from err
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise click.BadParameter(
                f"{device}: CUDA is not available on this machine (torch "
                f"{torch.__version__}); use --device cpu",
                param_hint="--device",
            )
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise click.BadParameter(
                f"{device}: this machine has {torch.cuda.device_count()} CUDA "
                "device(s)",
                param_hint="--device",
            )
    elif dev.type == "mps" and not torch.backends.mps.is_available():
        raise click.BadParameter(
            f"{device}: MPS is not available on this machine", param_hint="--device"
        )
    elif dev.type in ("cpu", "mps") and dev.index not in (None, 0):
        # torch accepts "cpu:1" and ignores the index: refuse what does not exist
        raise click.BadParameter(
            f"{device}: there is one {dev.type} device; use --device {dev.type}",
            param_hint="--device",
        )
    elif dev.type not in ("cpu", "cuda", "mps"):
        raise click.BadParameter(
            f"{device}: unsupported device type {dev.type!r}", param_hint="--device"
        )
    return dev


def check_memory(config: ReconstructionConfig, n_images: int) -> None:
    """Refuse (one line, ``--particles``) a run that cannot fit in this machine's RAM.

    Compares :meth:`ReconstructionConfig.memory_bytes` with the physical memory
    (POSIX ``sysconf``); where that is unknown nothing is checked.
    """
    try:
        total = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return
    need = config.memory_bytes(n_images)
    if total > 0 and need > total:
        raise click.BadParameter(
            f"{config.n_particles} particles need about {need / 2**30:.3g} GiB "
            f"of memory to train on {n_images} image(s); this machine has "
            f"{total / 2**30:.3g} GiB: use fewer particles",
            param_hint="--particles",
        )


def read_dataset(path: Path) -> MultiScanDataset:
    """The scans of a quad-scan file, or a one-line click error naming the problem."""
    try:
        return as_scans(read_scans(path))
    except (FormatError, OSError) as err:
        text = str(err)  # reader errors already read "PATH: field: problem"
        if not text.startswith(str(path)):
            text = f"{path}: {text}"
        raise click.ClickException(f"cannot read {text}") from err


def resume_config(
    stored: ReconstructionConfig, config: ReconstructionConfig, given: set[str]
) -> ReconstructionConfig:
    """The config to resume with: the checkpoint's (``stored``), checked against
    the options given.

    Options the user gave that differ from the checkpoint's are refused (naming
    both values); options not given are taken from the checkpoint.
    """
    clash = [
        f"{flag} {getattr(config, key)} (checkpoint: {getattr(stored, key)})"
        for key, flag in CONFIG_OPTIONS.items()
        if flag in given and getattr(config, key) != getattr(stored, key)
    ]
    if clash:
        raise click.ClickException(
            "--resume continues the checkpoint's run, which used other options: "
            + "; ".join(clash)
            + ". Drop these options (or give the checkpoint's values) to resume, or "
            "use --force without --resume to start a new run."
        )
    return stored


def _stored_config(checkpoint: Path) -> ReconstructionConfig:
    try:
        return checkpoint_config(checkpoint)
    except ValueError as err:
        raise click.ClickException(f"cannot resume: {err}") from err


def _resume_checkpoint(out: Path) -> Path:
    """The checkpoint ``--resume`` continues: the staging folder's, else ``out``'s."""
    found = [
        d / CHECKPOINT for d in (partial_folder(out), out) if (d / CHECKPOINT).is_file()
    ]
    if not found:
        # a run killed before its first checkpoint leaves a staging folder
        # that a run without --resume refuses until --force discards it
        fresh = "run without --resume"
        if partial_folder(out).exists():
            fresh = "run with --force instead of --resume to discard it"
        raise click.ClickException(
            f"--resume: no {CHECKPOINT} in {out} or {partial_folder(out)} (an "
            f"interrupted run keeps it there); {fresh}."
        )
    return found[0]


def resume_selection(
    folder: Path,
    dataset: MultiScanDataset,
    selection: dict[str, list[int]],
    given: bool,
) -> dict[str, list[int]]:
    """The training settings to resume with: those the run stored in ``folder``.

    A run started by this version stores its selection (:data:`SELECTION`);
    without ``--train-indices`` (``given`` False) it is taken from there, a
    different one given is refused naming both. A run without the file (an
    older version) resumes with the selection given (default: all).
    """
    path = folder / SELECTION
    if not path.is_file():
        return selection
    try:
        stored = json.loads(path.read_text())["train_indices"]
        stored = training_selection(dataset, stored)
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise click.ClickException(
            f"cannot resume: {path} does not hold this dataset's training settings "
            f"({err}); was the run made with another file?"
        ) from err
    if given and dict(stored) != dict(selection):
        raise click.ClickException(
            "--resume continues the checkpoint's run, which trained on other "
            f"settings: --train-indices gives {dict(selection)}, the run used "
            f"{dict(stored)}. Drop --train-indices to resume, or use --force "
            "without --resume to start a new run."
        )
    return stored


def _init_distributed(device: str) -> str:
    """Join the process group that torchrun describes; this process's device."""
    needed = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")
    missing = [v for v in needed if v not in os.environ]
    if missing:
        raise click.ClickException(
            f"--distributed needs a launcher such as torchrun (missing {missing}); "
            "e.g. torchrun --standalone --nproc-per-node 2 -m diffaccel reconstruct "
            "... --distributed"
        )
    if device.startswith("cuda"):
        device = f"cuda:{int(os.environ['LOCAL_RANK'])}"
        torch.cuda.set_device(device)
        backend = "nccl"
    else:
        backend = "gloo"
    tdist.init_process_group(backend)
    return device


@contextmanager
def _shared_refusal(target: Any, distributed: bool) -> Iterator[Any]:
    """Enter ``target``; in a distributed run every process learns the outcome.

    Only process 0 opens the result folder. If it refuses (``--out`` exists
    without ``--force``, locked, read-only) the others must not wait for it in
    a collective forever: process 0 broadcasts its refusal (or ``None``) and
    every process raises the same one-line error. The broadcast also orders the
    staging folder's creation before the other processes read it.
    """
    refusal: click.ClickException | None = None
    with ExitStack() as stack:
        try:
            folder = stack.enter_context(target)
        except click.ClickException as err:
            refusal = err
        if distributed:
            message = [None if refusal is None else refusal.format_message()]
            tdist.broadcast_object_list(message, src=0)
            if message[0] is not None and refusal is None:
                tdist.destroy_process_group()
                raise click.ClickException(f"process 0 stopped: {message[0]}")
        if refusal is not None:
            if distributed:
                tdist.destroy_process_group()
            raise refusal
        yield folder


@contextmanager
def _torch_threads(n: int) -> Iterator[None]:
    """torch's intra-op threads at most ``n`` in the block."""
    before = torch.get_num_threads()
    torch.set_num_threads(min(n, before))
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _echo_warnings(warnings: Sequence[str]) -> None:
    """Each warning on stderr as ``warning: ...`` (``reconstruct`` and ``predict``)."""
    for warning in warnings:
        click.echo(f"warning: {warning}", err=True)


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
) -> dict[str, Any]:
    """Reconstruct, then write ensemble, summary.json, particles and figures.

    Everything is written into ``folder`` (the staging folder of an
    :func:`~diffaccel.cli.output.output_folder`), including the checkpoint.
    With ``distributed`` (an initialised ``torch.distributed`` group) every
    process trains its share of the particles (``split="particles"``) or its
    own ensemble members (``split="members"``) and only process 0 writes; the
    others return an empty dict. ``uncertainty``: attach the moment-space
    posterior (calibrated ``std`` in summary.json, per-pixel spread in the
    image figures); without it ``std`` is the ensemble scatter only.
    """
    writer = not distributed or tdist.get_rank() == 0
    t0 = time.perf_counter()
    ck = folder / CHECKPOINT
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

    stored = resume and (folder / SELECTION).is_file()
    if writer and not resume:  # a resumed run has its own (or, older, none)
        atomic_write_json(folder / SELECTION, {"train_indices": dict(selection)})
    done = False
    try:
        result = reconstruct(
            ds,
            config,
            train_indices=selection,
            checkpoint=ck,
            resume=resume,
            callback=callback,
            device=device,
            distributed=distributed,
            split=split,  # type: ignore[arg-type]
            uncertainty=uncertainty,
        )
        done = True
    except CheckpointDataError as err:
        # a run of a version before selection.json resumes with the
        # --train-indices given; with it, the settings were the run's own
        hint = (
            " Was the dataset file changed since?"
            if stored
            else " If the interrupted run had --train-indices, give the same "
            "again with --resume."
        )
        raise click.ClickException(f"{err}{hint}") from err
    except (ValueError, FloatingPointError) as err:
        raise click.ClickException(str(err)) from err
    finally:
        bar.close()
        if writer and not done and not ck.is_file():  # nothing to resume
            (folder / SELECTION).unlink(missing_ok=True)
    if not writer:
        return {}
    t_train = time.perf_counter() - t0
    result.info["dataset"] = str(dataset_path)
    result.save(folder, overwrite=True)
    # the corner plot, training curves and rms figures are drawn by a forked
    # child (cli.background) while this process predicts, evaluates and draws
    # the image grids, each on one core: torch runs on one thread meanwhile,
    # since an OpenMP team that shares its cores with the child waits for it
    # at every kernel (issue 12: ~0.5 s of a default reconstruct on 2 cores)
    with ExitStack() as stack:
        figures_done = None
        if figures:
            fork = not distributed and can_fork()
            figures_done = stack.enter_context(
                in_child(partial(write_result_figures, result, ds, folder), fork=fork)
            )
            if fork:
                stack.enter_context(_torch_threads(1))
        spread = None
        if figures and uncertainty:
            t_std = time.perf_counter()
            predicted, spread, on_screen = predict_dataset(
                result, ds, return_std=True, return_on_screen=True
            )
            result.info["timings_s"]["image_spread"] = time.perf_counter() - t_std
        else:
            predicted, on_screen = predict_dataset(result, ds, return_on_screen=True)
        # the particles file holds the sample that evaluate() compares with
        # the ground truth (n_sample, seed 0): drawn once
        particles = result.sample(100_000)
        summary = evaluate(
            result,
            ds,
            train_indices=selection,
            predicted=predicted,
            n_sample=100_000,
            sample=particles,
            on_screen=on_screen,
        )
        summary["dataset"] = str(dataset_path)
        try:
            parts = write_openpmd_particles(
                folder / "particles.h5",
                particles,
                ds.p0c,
                ds.species,
                overwrite=True,
            )
        except ValueError as err:  # e.g. no forward motion: a wrong calibration
            raise click.ClickException(str(err)) from err
        summary["particles_file"] = parts.name
        if figures_done is not None:
            images = write_image_figures(ds, selection, folder, predicted, spread)
            summary["figures"] = figures_done() + images
    summary["timings_s"]["total_wall"] = time.perf_counter() - t0
    summary["timings_s"]["reconstruct_wall"] = t_train
    atomic_write_json(folder / "summary.json", summary)
    return summary


@click.command("reconstruct")
@click.argument("dataset", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "--out",
    type=click.Path(file_okay=False, path_type=Path),
    required=True,
    help="Output directory (ensemble, summary.json, figures).",
)
@click.option(
    "--particles",
    type=click.IntRange(min=16),
    default=None,
    help="Fresh particles per training step [default: "
    f"{_DEFAULTS[4].n_particles} for --dims 4, {_DEFAULTS[6].n_particles} for "
    "--dims 6].",
)
@click.option(
    "--steps",
    "--epochs",
    "steps",
    type=click.IntRange(min=1),
    default=None,
    help="Optimisation steps (multiple of --snapshots); --epochs is an alias "
    f"[default: {_DEFAULTS[4].steps} for --dims 4, {_DEFAULTS[6].steps} for "
    "--dims 6].",
)
@click.option(
    "--snapshots",
    type=click.IntRange(min=1),
    default=None,
    help="Cosine learning-rate cycles; the ensemble keeps the last snapshots - "
    f"burn-in (burn-in {_DEFAULTS[4].burn_in} for --dims 4, "
    f"{_DEFAULTS[6].burn_in} for --dims 6) [default: {_DEFAULTS[4].snapshots} for "
    f"--dims 4, {_DEFAULTS[6].snapshots} for --dims 6].",
)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--device", default="cpu", show_default=True, help="cpu, cuda, cuda:1...")
@click.option(
    "--train-indices",
    default="all",
    show_default=True,
    help="Settings to train on, per scan: all, even, odd or a list like 0,2,4 "
    "(the same rule in every scan), or SCAN:RULE;SCAN:RULE (e.g. "
    "'dipole_off:0,1,4,5;dipole_on:all'; scans not named are held out). The "
    "others are held out and scored.",
)
@click.option(
    "--dims",
    type=click.Choice(["4", "6"]),
    default="4",
    show_default=True,
    help="4: transverse phase space only; 6: also z, pz (seen with a deflecting "
    "cavity and/or dispersion; otherwise weakly constrained).",
)
@click.option(
    "--image-loss",
    type=click.Choice(["kl", "l1", "l2"]),
    default=_DEFAULTS[4].image_loss,
    show_default=True,
)
@click.option(
    "--blur",
    type=click.FloatRange(min=0),
    default=None,
    help="Point-spread rms of simulated images [pixels] [default: the file's "
    "screen resolution_pixels where recorded, else 1.0 for --dims 4, sqrt(1/12) "
    "for --dims 6].",
)
@click.option(
    "--uncoupled",
    is_flag=True,
    help="--dims 6: put the x-y coupling that the screens barely see (x-py, "
    "px-y against px-py) at the largest entropy instead of where training "
    "settled: the 4D and 6D emittances then do not depend on training there. "
    "Right for beams not turned in x-y; wrong for beams turned in x-y (e.g. "
    "by a solenoid); see docs/generalisation_6d.md.",
)
@click.option(
    "--probe/--no-probe",
    default=None,
    help="--dims 6: let the training images move the beam off the stated prior "
    "point along the px-pz direction the screens cannot see (zero px-pz partial "
    "correlation) where members refitted there fit clearly better: a "
    "likelihood-ratio probe on the side away from where training left the "
    "members, one or more extra refits per member (about 20 s on two CPU cores) "
    "[default: on for --dims 6; see docs/generalisation_6d.md].",
)
@click.option("--no-figures", is_flag=True, help="Skip the PNG figures.")
@click.option(
    "--uncertainty/--no-uncertainty",
    default=True,
    show_default=True,
    help="Calibrated moment std (moment-space posterior, see docs/uncertainty.md) "
    "and the per-pixel spread in the image figures; --no-uncertainty reports "
    "the ensemble scatter only (faster, under-covers).",
)
@click.option(
    "--force",
    is_flag=True,
    help="Replace an earlier reconstruction in --out (at the end); discard an "
    "interrupted run's checkpoint in .OUT.partial.",
)
@click.option(
    "--resume",
    is_flag=True,
    help="Continue the interrupted run into --out from its checkpoint (same data; "
    "options not given are the checkpoint's).",
)
@click.option(
    "--distributed",
    is_flag=True,
    help="Run on the processes started by torchrun (gloo on CPUs, NCCL with "
    "--device cuda: one GPU per process), sharing the work as --split says; "
    "process 0 writes --out. See docs/distributed.md.",
)
@click.option(
    "--split",
    type=click.Choice(["particles", "members"]),
    default="particles",
    show_default=True,
    help="With --distributed: 'particles' splits every step's particles across "
    "the processes (one ensemble, same answer as one process); 'members' trains "
    "one independent ensemble per process (process r: seed + 7919 r) and joins "
    "all members into one ensemble (P processes: P times the members).",
)
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
    uncoupled: bool,
    probe: bool | None,
    no_figures: bool,
    uncertainty: bool,
    force: bool,
    resume: bool,
    distributed: bool,
    split: str,
) -> None:
    """Reconstruct a beam's phase space from the quad-scan file DATASET.

    The results appear in OUT all together at the end (written into a
    staging folder ``.OUT.partial`` beside it first); an interrupted run keeps
    its checkpoint there and ``--resume`` continues it (``--force`` discards it).
    """
    ctx = click.get_current_context()
    given = {
        flag
        for name, flag in PARAMETER_FLAGS.items()
        if ctx.get_parameter_source(name) in (ParameterSource.COMMANDLINE,)
    }
    if split != "particles" and not distributed:
        raise click.BadParameter(
            "--split members needs --distributed (processes started by torchrun).",
            param_hint="--split",
        )
    dev = _init_distributed(device) if distributed else check_device(device)
    writer = not distributed or tdist.get_rank() == 0
    options: dict[str, Any] = {
        "dims": int(dims),
        "n_particles": particles,
        "steps": steps,
        "snapshots": snapshots,
        "seed": seed,
        "image_loss": image_loss,
        "blur_pixels": blur,
        "place_coupling": uncoupled,
        "probe_unseen": None if probe is None else PROBE_STEP if probe else 0.0,
    }
    checkpoint = _resume_checkpoint(out) if resume else None
    stored = None if checkpoint is None else _stored_config(checkpoint)
    if stored is not None:
        # options not given are the checkpoint's: a given --steps is checked
        # against its --snapshots, not against the default's
        options.update(
            {k: getattr(stored, k) for k, f in CONFIG_OPTIONS.items() if f not in given}
        )
    try:
        config = ReconstructionConfig(**options)
    except ValueError as err:
        raise click.ClickException(str(err)) from err
    ds = read_dataset(dataset)
    try:
        selection = training_selection(ds, train_indices)
    except ValueError as err:
        raise click.BadParameter(str(err), param_hint="--train-indices") from err
    if checkpoint is not None and stored is not None:
        config = resume_config(stored, config, given)
        selection = resume_selection(
            checkpoint.parent,
            ds,
            selection,
            ctx.get_parameter_source("train_indices") == ParameterSource.COMMANDLINE,
        )
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
        with _shared_refusal(target, distributed) as folder:
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
            )
    except (KeyboardInterrupt, click.ClickException) as err:
        # a refused run (another run's lock) must not point at that run's files
        interrupted = started and isinstance(err, KeyboardInterrupt)
        if started and (partial_folder(out) / CHECKPOINT).is_file():
            click.echo(
                f"note: the run's checkpoint is kept in {partial_folder(out)}; "
                f"--resume continues it ({out} is unchanged)",
                err=True,
            )
        elif interrupted and checkpoint is not None and checkpoint.parent == out:
            # a resume of a finished result keeps no copy of it
            click.echo(f"note: {out} is unchanged", err=True)
        elif interrupted:
            click.echo(
                "note: interrupted before the first checkpoint (written every "
                f"{config.checkpoint_every} steps): nothing to resume, {out} is "
                "unchanged",
                err=True,
            )
        raise
    if distributed:
        tdist.destroy_process_group()
    if not summary:  # a process other than 0 of a distributed run
        return
    m = summary["metrics"]
    click.echo(f"wrote {out / 'summary.json'}")
    if "images_held_out" in m:
        click.echo(
            f"held-out image relative L1: {m['images_held_out']['relative_l1']:.4f}"
        )
    click.echo(f"train image relative L1: {m['images_train']['relative_l1']:.4f}")
    _echo_warnings(summary.get("warnings", []))
    if summary["unconstrained_coordinates"]:
        click.echo(
            "not constrained by the scan: "
            + ", ".join(summary["unconstrained_coordinates"])
        )
    for line in prior_dependence_lines(summary.get("prior_dependence", [])):
        click.echo(line)
    polish = summary.get("moment_polish", [])
    if polish:
        before = ", ".join(f"{100 * p['residual_before']:.2f}" for p in polish)
        after = ", ".join(f"{100 * p['residual_after']:.2f}" for p in polish)
        click.echo(
            "moment polish: training images' second moments off by "
            f"{before} % rms (per member) before, {after} % after"
        )


def _percent(change: dict | None, key: str) -> str:
    return "n/a" if change is None else f"{100 * change[key]:+.0f} %"


def prior_dependence_lines(entries: list[dict]) -> list[str]:
    """One line per unseen correlation of the summary's ``prior_dependence``:
    its value and how the moments would differ at the other listed values.

    Example:
        >>> entry = {"pair": "px-pz", "moves": "rms_pz", "partial_correlation": 0.0,
        ...          "if_partial_correlation": [
        ...              {"partial_correlation": -0.1, "relative_change": None},
        ...              {"partial_correlation": 0.1, "relative_change": {
        ...                  "rms_pz": 0.02, "emit_z": 0.15, "emit_6d": 0.14}}]}
        >>> print(prior_dependence_lines([entry])[0])  # doctest: +NORMALIZE_WHITESPACE
        set by the prior, not the images: px-pz partial correlation +0.00; with
        -0.10 / +0.10 instead the same images fit emit_z n/a / +15 %, rms_pz
        n/a / +2 %, emit_6d n/a / +14 %
    """
    lines = []
    for e in entries:
        at = e["if_partial_correlation"]
        where = " / ".join(f"{a['partial_correlation']:+.2f}" for a in at)
        fits = ", ".join(
            f"{key} " + " / ".join(_percent(a["relative_change"], key) for a in at)
            for key in ("emit_z", e["moves"], "emit_6d")
        )
        lines.append(
            f"set by the prior, not the images: {e['pair']} partial correlation "
            f"{e['partial_correlation']:+.2f}; with {where} instead the same "
            f"images fit {fits}"
        )
    return lines


def _write_spread(path: Path, spread: dict[str, torch.Tensor]) -> None:
    """Per-pixel spreads as .npy (one scan) or .npz (one array per scan), atomically."""
    arrays = {k: v.detach().cpu().numpy().astype(np.float32) for k, v in spread.items()}
    if path.suffix.lower() == ".npy" and len(arrays) != 1:
        raise click.ClickException(
            f"--std-out {path}: {len(arrays)} scans; write them to an .npz file"
        )
    path.parent.mkdir(parents=True, exist_ok=True)

    def _save(p: Path) -> None:
        with p.open("wb") as f:
            if path.suffix.lower() == ".npy":
                np.save(f, next(iter(arrays.values())))
            else:
                np.savez(f, **arrays)

    atomic_write(path, _save)
    click.echo(f"wrote {path}: per-pixel spread of {len(arrays)} scan(s)")


def parse_settings(text: str, names: list[str]) -> torch.Tensor:
    """``--settings`` text as a ``(K, P)`` float64 tensor for scanned ``names``.

    One parameter: ``"-3,0,2.5"`` (or one row per ``;``); several: rows
    separated by ``;``, the values of a row by ``:`` (``"1:2;3:4"``).

    Raises:
        ValueError: naming the value that is not a number, a row of the wrong
            length, an empty row or value (a stray ``;`` or ``,``), or an empty
            list.
    """
    if not text.replace(" ", "").strip(";,"):
        raise ValueError(f"--settings {text!r} holds no value; e.g. '-3,0,2.5'.")
    rows = text.replace(" ", "").split(";")
    if len(names) == 1 and len(rows) == 1:
        rows = rows[0].split(",")
        what, sep = "value", ","
    else:
        what, sep = "row", ";"
    for i, row in enumerate(rows):
        if not row:  # a stray separator would silently drop a setting
            raise ValueError(
                f"--settings {text!r}: {what} {i + 1} is empty (a stray {sep!r}?)."
            )
    out = []
    for i, row in enumerate(rows):
        cells = row.split(":")
        if len(cells) != len(names):
            raise ValueError(
                f"--settings row {i + 1} {row!r} has {len(cells)} value(s); "
                f"expected {len(names)} ({':'.join(names)}), rows separated by ';'."
            )
        try:
            out.append([float(c) for c in cells])
        except ValueError:
            raise ValueError(
                f"--settings row {i + 1} {row!r}: not a number; expected e.g. "
                f"'-3,0,2.5' or '1:2;3:4'."
            ) from None
    return torch.tensor(out, dtype=torch.float64)


@click.command("predict")
@click.argument(
    "result_dir", type=click.Path(exists=True, file_okay=False, path_type=Path)
)
@click.option(
    "--dataset",
    "dataset_path",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="Predict every scan and setting of this file (version 1 or 2), on its "
    "screen grids.",
)
@click.option(
    "--settings",
    "settings_text",
    default=None,
    help="Instead of --dataset: values of the scanned parameter(s) of the "
    "(first) training scan, e.g. '-3,0,2.5' (one parameter) or '1:2;3:4' (rows ';').",
)
@click.option(
    "--out",
    type=click.Path(dir_okay=False, path_type=Path),
    required=True,
    help="Output file: .h5 writes a quad-scan file of the same format version as "
    "--dataset with the predicted images (one shot, each summing to 1); .npy "
    "writes (K, H, W) float32 (one scan only). Settings where less than half of "
    "the beam lands on the screen are warned (and recorded in the .h5).",
)
@click.option(
    "--particles",
    type=click.IntRange(min=100),
    default=50_000,
    show_default=True,
    help="Particles per ensemble member.",
)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option(
    "--std-out",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Also write the per-pixel spread (1-sigma) of the predicted images, on "
    "their unit-sum scale: .npy (K, H, W) float32 for one scan, or .npz with one "
    "such array per scan name (ensemble scatter and the moment-space posterior; "
    "see docs/uncertainty.md).",
)
@click.option("--force", is_flag=True, help="Overwrite --out (and --std-out).")
def predict(
    result_dir: Path,
    dataset_path: Path | None,
    settings_text: str | None,
    out: Path,
    particles: int,
    seed: int,
    std_out: Path | None,
    force: bool,
) -> None:
    """Ensemble-mean screen images of a reconstruction (RESULT_DIR) for new settings."""
    check_out_file(out, force, {"--dataset": dataset_path})
    if std_out is not None:
        check_out_file(
            std_out, force, {"--dataset": dataset_path, "--out": out}, "--std-out"
        )
        if std_out.suffix.lower() not in (".npy", ".npz"):
            raise click.ClickException(
                f"--std-out {std_out}: expected a .npy (one scan) or .npz file name"
            )
    if (dataset_path is None) == (settings_text is None):
        raise click.ClickException("give exactly one of --dataset or --settings")
    suffix = out.suffix.lower()
    if suffix not in (".h5", ".hdf5", ".npy"):
        raise click.ClickException(
            f"--out {out}: expected a .h5 (quad-scan file) or .npy file name"
        )
    if suffix != ".npy" and dataset_path is None:
        raise click.ClickException(
            "--out .h5 needs --dataset (the file whose settings and screens to "
            "predict); with --settings write .npy"
        )
    want_std = std_out is not None
    try:
        result = load(result_dir)
        if dataset_path is not None:
            other = read_scans(dataset_path)
            predicted = predict_dataset(
                result,
                other,
                n_particles=particles,
                seed=seed,
                return_std=want_std,
                return_on_screen=True,
            )
            if want_std:
                predicted, spread, on_screen = predicted
            else:
                predicted, on_screen = predicted
            warnings = [
                w
                for name, scan in other
                for w in off_screen_warnings(
                    on_screen[name], scan.settings, scan.setting_names, scan=name
                )
            ]
            warnings += [a.text() for a in prediction_alarms(result, other)]
        else:
            fwd = result.forward
            settings = parse_settings(settings_text, fwd.names)
            images = result.predict_images(
                settings,
                forward=fwd,
                n_particles=particles,
                seed=seed,
                return_std=want_std,
                n_draws=4,
                return_on_screen=True,
            )
            if want_std:
                images, std, fraction = images
                spread = {result.scan_names[0]: std}
            else:
                images, fraction = images
            check_on_screen(images, settings)
            warnings = off_screen_warnings(
                fraction, settings, fwd.names, scan=result.scan_names[0]
            )
            warnings += [a.text() for a in prediction_alarms(result, None, settings)]
    except (FormatError, ValueError, FileNotFoundError, OSError) as err:
        raise click.ClickException(str(err)) from err
    # every refusal before the first file or folder is made
    if std_out is not None and std_out.suffix.lower() == ".npy" and len(spread) != 1:
        raise click.ClickException(
            f"--std-out {std_out}: {len(spread)} scans; write them to an .npz file"
        )
    if suffix == ".npy":
        if dataset_path is not None:
            if len(predicted) != 1:
                raise click.ClickException(
                    f"{dataset_path} holds {len(predicted)} scans; write them to an "
                    ".h5 file (--out PRED.h5)"
                )
            images = next(iter(predicted.values()))
            try:
                check_on_screen(images, other[other.names[0]].settings)
            except ValueError as err:
                raise click.ClickException(str(err)) from err
        array = images.numpy().astype(np.float32)
        out.parent.mkdir(parents=True, exist_ok=True)

        def _save(p: Path) -> None:
            with p.open("wb") as f:
                np.save(f, array)

        atomic_write(out, _save)
        k, h, w = images.shape
        click.echo(f"wrote {out}: {k} images of {h} x {w} pixels")
        if std_out is not None:
            _write_spread(std_out, spread)
        _echo_warnings(warnings)
        return
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        written = write_scans(
            predicted_dataset(
                other, predicted, source=str(result_dir), on_screen=on_screen
            ),
            out,
            overwrite=force,
        )
    except (FormatError, ValueError) as err:
        raise click.ClickException(str(err)) from err
    n = sum(v.shape[0] for v in predicted.values())
    click.echo(
        f"wrote {written}: {n} predicted images in {len(predicted)} scan(s) "
        f"(format version {other.format_version})"
    )
    if std_out is not None:
        _write_spread(std_out, spread)
    _echo_warnings(warnings)
