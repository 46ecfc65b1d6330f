"""A reconstruction as a result folder, and the policy that resumes one.

:func:`write_result` turns a trained :class:`Reconstruction` into the files
of a result folder: ``ensemble.pt``, ``particles.h5`` (openPMD), the figures
(drawn by callbacks, see :class:`ResultFigures`), ``summary.json`` (the
numbers of :func:`~diffaccel.reconstruction.evaluate`) and ``report.md``
(the headline numbers, :func:`report_markdown`). It writes into a
folder it is given, normally the staging folder of
:func:`diffaccel.data.result_folder`, which swaps the files in together.

A run that trains with a checkpoint stores its training settings beside it
(:data:`SELECTION`), so that a resume needs no ``train_indices``; the
``resume_*`` functions decide what a resume continues and refuse what it
cannot (other options, other settings, no checkpoint), each with a one-line
:class:`ResumeError`.

Example:
    >>> import tempfile
    >>> from diffaccel.data import make_synthetic_quad_scan, result_folder
    >>> from diffaccel.reconstruction import (
    ...     ReconstructionConfig, as_scans, reconstruct, training_selection)
    >>> ds = as_scans(make_synthetic_quad_scan(
    ...     "gaussian", n_particles=500, n_settings=4, screen_shape=(16, 16),
    ...     pixel_size=(1e-3, 1e-3), seed=1))
    >>> config = ReconstructionConfig(n_particles=256, steps=4, snapshots=2)
    >>> selection = training_selection(ds, "all")
    >>> result = reconstruct(ds, config, train_indices=selection, uncertainty=False)
    >>> out = Path(tempfile.mkdtemp()) / "run"
    >>> with result_folder(out, command="reconstruct", owned=OWNED) as folder:
    ...     summary = write_result(result, ds, folder.path, dataset_path="scan.h5",
    ...                            train_indices=selection, uncertainty=False)
    >>> sorted(p.name for p in out.iterdir())  # doctest: +NORMALIZE_WHITESPACE
    ['.diffaccel-result', 'ensemble.pt', 'particles.h5', 'report.md', 'summary.json']
"""

from __future__ import annotations

import fnmatch
import json
import math
import os
import shutil
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import torch
import torch.distributed as tdist

from diffaccel.data import (
    FormatError,
    MultiScanDataset,
    QuadScanDataset,
    atomic_write_json,
    atomic_write_text,
    make_synthetic_quad_scan,
    partial_folder,
    read_scans,
)
from diffaccel.data.errors import OptionError
from diffaccel.data.particles_io import write_openpmd_particles
from diffaccel.reconstruction.background import can_fork, in_child
from diffaccel.reconstruction.ensemble import Reconstruction
from diffaccel.reconstruction.evaluation import evaluate, predict_dataset
from diffaccel.reconstruction.forward import ScreenForwardModel
from diffaccel.reconstruction.pipeline import (
    as_scans,
    reconstruct,
    training_selection,
)
from diffaccel.reconstruction.training import (
    CheckpointDataError,
    ReconstructionConfig,
    StepInfo,
    checkpoint_config,
    data_fingerprint,
    load_checkpoint,
)

__all__ = [
    "CHECKPOINT",
    "CONFIG_OPTIONS",
    "DEFAULT_CHARGE_C",
    "OWNED",
    "PARTICLES_SAMPLE",
    "REPORT",
    "SELECTION",
    "OptionError",
    "ResultFigures",
    "ResultWriteError",
    "ResumeError",
    "RunError",
    "RunPlan",
    "bunch_charge",
    "check_finished_run",
    "clean_for_resume",
    "config_options",
    "demo_config",
    "demo_dataset",
    "demo_report_markdown",
    "discard_selection",
    "finding_lines",
    "headline_lines",
    "plan_run",
    "prior_dependence_lines",
    "read_dataset",
    "report_markdown",
    "resume_checkpoint",
    "resume_config",
    "resume_plan",
    "resume_selection",
    "resume_start",
    "run_in_folder",
    "score_lines",
    "stopped_note",
    "store_selection",
    "stored_config",
    "write_result",
]

#: The checkpoint file of a run, in its (staging) folder.
CHECKPOINT = "checkpoint.pt"
#: The training settings of a run, written beside its checkpoint so that a
#: resume needs no ``train_indices``: JSON ``{"train_indices": {scan: [i, ...]}}``.
SELECTION = "selection.json"
#: Files a reconstruction writes (a folder of only these is an earlier result).
OWNED = (
    "ensemble.pt",
    "summary.json",
    "particles.h5",
    "report.md",
    CHECKPOINT,
    SELECTION,
    "checkpoint.rank*.pt",  # the other processes' of a members-split run
    "*.png",
)
#: Config fields that the ``reconstruct`` command sets, and its options for them.
CONFIG_OPTIONS = {
    "dims": "--dims",
    "n_particles": "--particles",
    "steps": "--steps",
    "snapshots": "--snapshots",
    "seed": "--seed",
    "blur_pixels": "--blur",
}
#: The human-readable summary of a result folder (Markdown).
REPORT = "report.md"
#: Bunch charge of ``particles.h5`` [C] where neither the caller nor the
#: dataset gives one.
DEFAULT_CHARGE_C = 1e-12
#: Particles of ``particles.h5``: the sample that :func:`evaluate` compares
#: with the ground truth (drawn once, seed 0).
PARTICLES_SAMPLE = 100_000


class RunError(ValueError):
    """A run into a result folder cannot go on (the message says why, in one line)."""


class ResumeError(RunError):
    """A run cannot be resumed as asked (the message says why, in one line)."""


class ResultWriteError(RunError):
    """The result cannot be written as computed (e.g. particles not moving forward)."""


@dataclass(frozen=True)
class ResultFigures:
    """The figures of a result folder, drawn by callbacks (plotting lives above).

    Attributes:
        summary: ``summary(result, dataset, folder) -> names``: the figures
            that need only the result (corner plot, training curves...). Run
            in a forked child (:func:`~diffaccel.reconstruction.background.in_child`)
            while the parent predicts and evaluates, where that is possible.
        images: ``images(dataset, train_indices, folder, predicted,
            predicted_std) -> names``: the measured-vs-predicted image figures
            (``predicted_std`` None without uncertainty).
    """

    summary: Callable[[Reconstruction, MultiScanDataset, Path], list[str]]
    images: Callable[
        [
            MultiScanDataset,
            Mapping[str, Sequence[int]],
            Path,
            dict[str, torch.Tensor],
            dict[str, torch.Tensor] | None,
        ],
        list[str],
    ]


@contextmanager
def _torch_threads(n: int) -> Iterator[None]:
    """torch's intra-op threads at most ``n`` in the block."""
    before = torch.get_num_threads()
    torch.set_num_threads(min(n, before))
    try:
        yield
    finally:
        torch.set_num_threads(before)


def write_result(
    result: Reconstruction,
    dataset: MultiScanDataset,
    folder: str | os.PathLike,
    *,
    dataset_path: str | os.PathLike,
    train_indices: Mapping[str, Sequence[int]],
    uncertainty: bool = True,
    figures: ResultFigures | None = None,
    fork: bool = True,
    started: float | None = None,
    train_seconds: float | None = None,
    charge_C: float | None = None,
) -> dict[str, Any]:
    """Write a trained reconstruction into ``folder``; returns the summary.

    Writes ``ensemble.pt`` (:meth:`Reconstruction.save`), ``particles.h5``
    (:data:`PARTICLES_SAMPLE` particles in openPMD, seed 0), the figures of
    ``figures``, ``summary.json`` (:func:`evaluate` of the dataset, plus
    ``dataset``, ``particles_file``, ``particles_charge_C`` and its
    ``particles_charge_source``, ``figures`` and the wall times
    ``timings_s.total_wall``/``reconstruct_wall`` [s]) and :data:`REPORT`
    (:func:`report_markdown`), each atomically.
    ``folder`` must exist; files of these names are replaced.

    With ``figures`` and ``uncertainty`` the predicted images carry their
    per-pixel spread (drawn by ``figures.images``; its time is
    ``timings_s.image_spread``). The summary figures are drawn in a forked
    child while this process evaluates (``fork`` and where
    :func:`~diffaccel.reconstruction.background.can_fork`), torch running on
    one thread meanwhile; an error there fails the call.

    Args:
        result: The trained reconstruction (its ``info`` gets ``dataset``).
        dataset: The scans it was trained on (all settings: the held-out ones
            are scored).
        folder: Where to write.
        dataset_path: The dataset's file, recorded in the summary.
        train_indices: The training settings per scan (the others are held out).
        uncertainty: Predict the per-pixel spread for the image figures.
        figures: The figure callbacks; None writes no figure.
        fork: Allow the summary figures to be drawn in a forked child.
        started: ``time.perf_counter()`` at the start of the run (default: now).
        train_seconds: Wall time of training [s] (default: 0 when not given).
        charge_C: Bunch charge of ``particles.h5`` [C] (> 0); default: the
            dataset's metadata ``charge_C`` where recorded, else
            :data:`DEFAULT_CHARGE_C` (see :func:`bunch_charge`).

    Raises:
        ResultWriteError: the particles cannot be written (e.g. no forward
            motion, a wrong calibration) or the bunch charge is not positive.
        RuntimeError: a figure drawn in the child failed (its error as one line).
        OSError: a file cannot be written (the folder's files may be partial:
            write into a staging folder).
    """
    folder = Path(folder)
    t0 = time.perf_counter() if started is None else started
    charge, charge_source = bunch_charge(dataset, charge_C)
    result.info["dataset"] = str(dataset_path)
    result.save(folder, overwrite=True)
    with ExitStack() as stack:
        figures_done = None
        if figures is not None:
            in_fork = fork and can_fork()
            figures_done = stack.enter_context(
                in_child(
                    partial(figures.summary, result, dataset, folder), fork=in_fork
                )
            )
            if in_fork:
                # an OpenMP team that shares its cores with the child waits
                # for it at every kernel
                stack.enter_context(_torch_threads(1))
        spread = None
        if figures is not None and uncertainty:
            t_std = time.perf_counter()
            predicted, spread, on_screen, used = predict_dataset(
                result,
                dataset,
                return_std=True,
                return_on_screen=True,
                return_particles=True,
            )
            result.info["timings_s"]["image_spread"] = time.perf_counter() - t_std
        else:
            predicted, on_screen, used = predict_dataset(
                result, dataset, return_on_screen=True, return_particles=True
            )
        particles = result.sample(PARTICLES_SAMPLE)
        summary = evaluate(
            result,
            dataset,
            train_indices=train_indices,
            predicted=predicted,
            n_sample=PARTICLES_SAMPLE,
            sample=particles,
            on_screen=on_screen,
            prediction_particles=used,
        )
        summary["dataset"] = str(dataset_path)
        try:
            parts = write_openpmd_particles(
                folder / "particles.h5",
                particles,
                dataset.p0c,
                dataset.species,
                charge_C=charge,
                overwrite=True,
            )
        except ValueError as err:
            raise ResultWriteError(str(err)) from err
        summary["particles_file"] = parts.name
        summary["particles_charge_C"] = charge
        summary["particles_charge_source"] = charge_source
        if figures_done is not None:
            images = figures.images(dataset, train_indices, folder, predicted, spread)
            summary["figures"] = figures_done() + images
    summary["timings_s"]["total_wall"] = time.perf_counter() - t0
    summary["timings_s"]["reconstruct_wall"] = (
        0.0 if train_seconds is None else train_seconds
    )
    atomic_write_json(folder / "summary.json", summary)
    atomic_write_text(folder / REPORT, report_markdown(summary))
    return summary


def bunch_charge(
    dataset: MultiScanDataset, charge_C: float | None = None
) -> tuple[float, str]:
    """The bunch charge [C] of a result's particle file, and where it comes from.

    ``charge_C`` if given (``"given"``), else the dataset's metadata
    ``charge_C`` [C] where it holds a positive number (``"dataset"``), else
    :data:`DEFAULT_CHARGE_C` (``"default"``: the images carry no charge, as
    they are normalised to unit sum).

    Raises:
        ResultWriteError: a given or recorded charge that is not a positive
            finite number.
    """
    if charge_C is not None:
        value, source = charge_C, "given"
    elif dataset.metadata.get("charge_C") is not None:
        value, source = dataset.metadata["charge_C"], "dataset"
    else:
        return DEFAULT_CHARGE_C, "default"
    try:
        value = float(value)
    except (TypeError, ValueError):
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        where = "given" if source == "given" else "the dataset's metadata charge_C"
        raise ResultWriteError(
            f"bunch charge ({where}): expected a positive number of coulombs; "
            f"got {charge_C if source == 'given' else dataset.metadata['charge_C']!r}"
        )
    return value, source


def run_in_folder(
    dataset: MultiScanDataset,
    folder: str | os.PathLike,
    config: ReconstructionConfig,
    train_indices: Mapping[str, Sequence[int]],
    *,
    dataset_path: str | os.PathLike,
    device: torch.device | str = "cpu",
    resume: bool = False,
    figures: ResultFigures | None = None,
    distributed: bool = False,
    split: str = "particles",
    uncertainty: bool = True,
    charge_C: float | None = None,
    callback: Callable[[StepInfo], None] | None = None,
    train: Callable[..., Reconstruction] = reconstruct,
) -> dict[str, Any]:
    """Train with a checkpoint in ``folder``, then :func:`write_result` there.

    ``folder`` is normally the staging folder of
    :func:`diffaccel.data.result_folder` (``keep_partial=True`` keeps it, and
    its checkpoint, when the run fails). A fresh run stores its
    ``train_indices`` (:data:`SELECTION`); a ``resume`` first removes every
    file of the earlier attempt but its checkpoints and selection
    (:func:`clean_for_resume`) and continues from :data:`CHECKPOINT`. A run
    stopped before its first checkpoint removes its selection again (nothing
    to resume). With ``distributed`` (an initialised ``torch.distributed``
    group) every process trains its share (``split``) and only process 0
    writes; the others return an empty dict.

    Args:
        dataset: The scans (all settings; the held-out ones are scored).
        folder: Where the checkpoint and the result go.
        config: Training settings (for a resume: the checkpoint's).
        train_indices: Training settings per scan (for a resume: the run's,
            :func:`resume_selection`).
        dataset_path: The dataset's file, recorded in the summary.
        device: Where to train.
        resume: Continue the checkpoint in ``folder``.
        figures, uncertainty, charge_C: As for :func:`write_result`.
        distributed, split: As for :func:`~diffaccel.reconstruction.reconstruct`.
        callback: Progress reports of training (:class:`StepInfo`).
        train: The training function, with the signature of
            :func:`~diffaccel.reconstruction.reconstruct` (the default).

    Returns:
        The summary (empty on processes other than 0).

    Raises:
        ResumeError: the checkpoint was written for other training data.
        RunError: training refused the data or the options (its ``ValueError``
            or ``FloatingPointError`` as one line).
        ResultWriteError: from :func:`write_result`.
    """
    folder = Path(folder)
    writer = not distributed or tdist.get_rank() == 0
    t0 = time.perf_counter()
    ck = folder / CHECKPOINT
    if writer and resume:  # only the checkpoint and selection of a kept attempt
        clean_for_resume(folder)
    stored = resume and (folder / SELECTION).is_file()
    if writer and not resume:  # a resumed run has its own (or, older, none)
        store_selection(folder, train_indices)
    done = False
    try:
        result = train(
            dataset,
            config,
            train_indices=train_indices,
            checkpoint=ck,
            resume=resume,
            callback=callback,
            device=device,
            distributed=distributed,
            split=split,
            uncertainty=uncertainty,
        )
        done = True
    except CheckpointDataError as err:
        # a run without selection.json resumes with the selection given;
        # with it, the settings were the run's own
        hint = (
            " Was the dataset file changed since?"
            if stored
            else " If the interrupted run had --train-indices, give the same "
            "again with --resume."
        )
        raise ResumeError(f"{err}{hint}") from err
    except (ValueError, FloatingPointError) as err:
        raise RunError(str(err)) from err
    finally:
        if writer and not done and not ck.is_file():  # nothing to resume
            discard_selection(folder)
    if not writer:
        return {}
    return write_result(
        result,
        dataset,
        folder,
        dataset_path=dataset_path,
        train_indices=train_indices,
        uncertainty=uncertainty,
        figures=figures,
        fork=not distributed,
        started=t0,
        train_seconds=time.perf_counter() - t0,
        charge_C=charge_C,
    )


# ----------------------------------------------------------------- resume policy
def store_selection(folder: str | os.PathLike, selection: Mapping[str, Any]) -> Path:
    """Write the run's training settings (:data:`SELECTION`) into ``folder``."""
    return atomic_write_json(
        Path(folder) / SELECTION, {"train_indices": dict(selection)}
    )


def discard_selection(folder: str | os.PathLike) -> None:
    """Remove :data:`SELECTION` from ``folder`` (a run that left nothing to resume)."""
    (Path(folder) / SELECTION).unlink(missing_ok=True)


def resume_checkpoint(out: str | os.PathLike) -> Path:
    """The checkpoint a resume into ``out`` continues: staging folder's, else ``out``'s.

    Raises:
        ResumeError: neither holds a checkpoint (naming what to do instead).
    """
    out = Path(out)
    found = [
        d / CHECKPOINT for d in (partial_folder(out), out) if (d / CHECKPOINT).is_file()
    ]
    if not found:
        # a run killed before its first checkpoint leaves a staging folder
        # that a run without --resume refuses until --force discards it
        fresh = "run without --resume"
        if partial_folder(out).exists():
            fresh = "run with --force instead of --resume to discard it"
        raise ResumeError(
            f"--resume: no {CHECKPOINT} in {out} or {partial_folder(out)} (an "
            f"interrupted run keeps it there); {fresh}."
        )
    return found[0]


def stored_config(checkpoint: str | os.PathLike) -> ReconstructionConfig:
    """The config stored in ``checkpoint``.

    Raises:
        ResumeError: the file is not a checkpoint or its config is damaged.
    """
    try:
        return checkpoint_config(checkpoint)
    except ValueError as err:
        raise ResumeError(f"cannot resume: {err}") from err


def resume_config(
    stored: ReconstructionConfig, config: ReconstructionConfig, given: set[str]
) -> ReconstructionConfig:
    """The config to resume with: the checkpoint's (``stored``), checked against
    the options given.

    ``given`` holds the option flags the user gave (:data:`CONFIG_OPTIONS`'
    values); those whose value in ``config`` differs from the checkpoint's are
    refused, naming both values.

    Raises:
        ResumeError: naming each option that differs.
    """
    clash = [
        f"{flag} {getattr(config, key)} (checkpoint: {getattr(stored, key)})"
        for key, flag in CONFIG_OPTIONS.items()
        if flag in given and getattr(config, key) != getattr(stored, key)
    ]
    if clash:
        raise ResumeError(
            "--resume continues the checkpoint's run, which used other options: "
            + "; ".join(clash)
            + ". Drop these options (or give the checkpoint's values) to resume, or "
            "use --force without --resume to start a new run."
        )
    return stored


def resume_selection(
    folder: str | os.PathLike,
    dataset: MultiScanDataset,
    selection: dict[str, list[int]],
    given: bool,
) -> dict[str, list[int]]:
    """The training settings to resume with: those the run stored in ``folder``.

    A run that stored its selection (:data:`SELECTION`) resumes with it:
    without ``train_indices`` given (``given`` False) it is taken from there,
    a different one given is refused naming both. A run without the file
    resumes with the ``selection`` given (default: all).

    Raises:
        ResumeError: the stored file does not fit the dataset, or another
            selection was given.
    """
    path = Path(folder) / SELECTION
    if not path.is_file():
        return selection
    try:
        stored = json.loads(path.read_text())["train_indices"]
        stored = training_selection(dataset, stored)
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise ResumeError(
            f"cannot resume: {path} does not hold this dataset's training settings "
            f"({err}); was the run made with another file?"
        ) from err
    if given and dict(stored) != dict(selection):
        raise ResumeError(
            "--resume continues the checkpoint's run, which trained on other "
            f"settings: --train-indices gives {dict(selection)}, the run used "
            f"{dict(stored)}. Drop --train-indices to resume, or use --force "
            "without --resume to start a new run."
        )
    return stored


def clean_for_resume(folder: str | os.PathLike) -> list[str]:
    """Remove from a kept staging folder all but its checkpoints and :data:`SELECTION`.

    A resumed run then writes every other file anew: figures, particles or a
    summary of an earlier attempt (one that failed while writing) never end up
    in its result. Returns the names removed.
    """
    keep = {CHECKPOINT, SELECTION}
    removed = []
    for p in sorted(Path(folder).iterdir()):
        if p.name in keep or fnmatch.fnmatch(p.name, "checkpoint.rank*.pt"):
            continue
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()
        removed.append(p.name)
    return removed


def check_finished_run(
    checkpoint: str | os.PathLike,
    dataset: MultiScanDataset,
    config: ReconstructionConfig,
    selection: Mapping[str, Sequence[int]],
) -> None:
    """Check that a finished run's ``checkpoint`` was trained on this data.

    A resume of a finished result continues nothing; it is refused (rather
    than reported as done) when the data differ from the run's: other images,
    settings or screen calibration (the checkpoint's data fingerprint, as
    :func:`~diffaccel.reconstruction.reconstruct` computes it).

    Raises:
        ResumeError: the data are not those of the run, or the file is not a
            readable checkpoint.
    """
    names = [name for name in dataset.names if selection.get(name)]
    forwards, measured, settings = [], [], []
    for name in names:
        scan = dataset[name]
        rows = list(selection[name])
        forwards.append(
            ScreenForwardModel.from_dataset(scan, blur_pixels=config.blur_for(scan))
        )
        measured.append(scan.mean_images()[rows])
        settings.append(scan.settings[rows])
    try:
        stored = load_checkpoint(checkpoint).fingerprint
    except (OSError, ValueError, KeyError, RuntimeError) as err:
        raise ResumeError(f"cannot resume: {checkpoint}: {err}") from err
    if stored != data_fingerprint(forwards, measured, settings):
        raise ResumeError(
            f"checkpoint {checkpoint} was written for other training data (another "
            "file, other training settings or another screen calibration); the "
            "finished result beside it is of another run: choose another --out."
        )


def resume_start(
    out: str | os.PathLike, options: Mapping[str, Any], given: set[str]
) -> tuple[Path, ReconstructionConfig, dict[str, Any]]:
    """The checkpoint a resume into ``out`` continues, its config, and the options.

    ``options`` are :class:`ReconstructionConfig` keyword arguments; those of
    :data:`CONFIG_OPTIONS` whose flag is not in ``given`` are replaced by the
    checkpoint's (so that a given ``--steps`` is checked against the
    checkpoint's ``--snapshots``, not against the default's).

    Raises:
        ResumeError: no checkpoint (:func:`resume_checkpoint`) or a damaged one.
    """
    checkpoint = resume_checkpoint(out)
    stored = stored_config(checkpoint)
    merged = dict(options)
    merged.update(
        {k: getattr(stored, k) for k, f in CONFIG_OPTIONS.items() if f not in given}
    )
    return checkpoint, stored, merged


def resume_plan(
    checkpoint: Path,
    stored: ReconstructionConfig,
    config: ReconstructionConfig,
    dataset: MultiScanDataset,
    selection: dict[str, list[int]],
    *,
    given: set[str],
    indices_given: bool,
    out: str | os.PathLike,
) -> tuple[ReconstructionConfig, dict[str, list[int]], bool]:
    """What a resume trains with, and whether the run is already finished.

    The config is the checkpoint's (:func:`resume_config`), the selection the
    run's (:func:`resume_selection`); a checkpoint in ``out`` itself (not in
    its staging folder) is a finished result, checked against the data
    (:func:`check_finished_run`): the third value is True, nothing is to run.

    Raises:
        ResumeError: other options, other settings or other data than the run's.
    """
    config = resume_config(stored, config, given)
    selection = resume_selection(checkpoint.parent, dataset, selection, indices_given)
    finished = checkpoint.parent == Path(out)
    if finished:
        check_finished_run(checkpoint, dataset, config, selection)
    return config, selection, finished


def config_options(
    *,
    dims: str,
    particles: int | None,
    steps: int | None,
    snapshots: int | None,
    seed: int,
    blur: float | None,
    loss_smoothing: str | None,
) -> dict[str, Any]:
    """The options of ``reconstruct`` as :class:`ReconstructionConfig` keywords.

    None (an option not given) is the config's default; ``loss_smoothing`` is
    a number of pixels or ``"auto"``.

    Raises:
        OptionError: a ``--loss-smoothing`` that is neither a number nor ``auto``.
    """
    if loss_smoothing not in (None, "auto"):
        try:
            loss_smoothing = float(loss_smoothing)
        except ValueError:
            raise OptionError(
                f"expected a number of pixels or 'auto'; got {loss_smoothing!r}.",
                "--loss-smoothing",
            ) from None
    return {
        "dims": int(dims),
        "n_particles": particles,
        "steps": steps,
        "snapshots": snapshots,
        "seed": seed,
        "blur_pixels": blur,
        "loss_smoothing": loss_smoothing,
    }


@dataclass(frozen=True)
class RunPlan:
    """What a run into a result folder trains with (:func:`plan_run`).

    Attributes:
        dataset: The scans of the quad-scan file.
        config: The config to train with (a resume's: the checkpoint's).
        selection: Training settings per scan.
        checkpoint: The checkpoint a resume continues; None without ``resume``.
        finished: A resume of a finished result: nothing to run.
    """

    dataset: MultiScanDataset
    config: ReconstructionConfig
    selection: dict[str, list[int]]
    checkpoint: Path | None
    finished: bool


def read_dataset(path: Path) -> MultiScanDataset:
    """The scans of the quad-scan file ``path``.

    Raises:
        RunError: ``cannot read PATH: ...`` naming the problem.
    """
    try:
        return as_scans(read_scans(path))
    except (FormatError, OSError) as err:
        text = str(err)  # reader errors already read "PATH: field: problem"
        if not text.startswith(str(path)):
            text = f"{path}: {text}"
        raise RunError(f"cannot read {text}") from err


def plan_run(
    dataset_path: Path,
    out: Path,
    options: Mapping[str, Any],
    *,
    given: set[str],
    train_indices: str = "all",
    indices_given: bool = False,
    resume: bool = False,
    charge_C: float | None = None,
) -> RunPlan:
    """Check a ``reconstruct`` run into ``out`` and say what it trains with.

    ``options``: :class:`ReconstructionConfig` keywords (None: the default);
    ``given``: the flags of :data:`CONFIG_OPTIONS` given on the command line
    (a resume takes the others from its checkpoint, :func:`resume_start`);
    ``train_indices``: the rule of :func:`training_selection`, given by the
    user where ``indices_given`` (else the default, whose refusal names the
    file's settings); ``charge_C``: the bunch charge [C] checked by
    :func:`bunch_charge`. In this order: the checkpoint (``resume``), the
    config, the file, the charge, the selection, and what the resume continues
    (:func:`resume_plan`).

    Raises:
        OptionError: training settings ``train_indices`` does not select.
        RunError: the first other refusal, in one line (a
            :class:`ResumeError` for what a resume cannot continue).
    """
    checkpoint = stored = None
    if resume:  # options not given are the checkpoint's
        checkpoint, stored, options = resume_start(out, options, given)
    try:
        config = ReconstructionConfig(**options)
    except ValueError as err:
        raise RunError(str(err)) from err
    ds = read_dataset(dataset_path)
    try:
        bunch_charge(ds, charge_C)  # a bad recorded charge refused before training
    except ResultWriteError as err:
        raise RunError(f"{dataset_path}: {err}") from err
    try:
        selection = training_selection(ds, train_indices)
    except ValueError as err:
        if not indices_given:  # the file's own settings: no option to blame
            text = str(err).replace("train_indices select", "its settings hold", 1)
            raise RunError(f"{dataset_path}: {text}") from err
        raise OptionError(str(err), "--train-indices") from err
    finished = False
    if checkpoint is not None and stored is not None:
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
    return RunPlan(ds, config, selection, checkpoint, finished)


# ------------------------------------------------------------------ summary text
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


#: Headline quantities: (summary key, index or None, label, unit, scale to unit)
_HEADLINE = {
    "emittance (normalised)": [
        ("norm_emit_x", None, "x", "mm mrad", 1e6),
        ("norm_emit_y", None, "y", "mm mrad", 1e6),
    ],
    "twiss": [
        ("beta_x", None, "beta_x", "m", 1.0),
        ("alpha_x", None, "alpha_x", "", 1.0),
        ("beta_y", None, "beta_y", "m", 1.0),
        ("alpha_y", None, "alpha_y", "", 1.0),
    ],
    "rms": [
        ("rms", 0, "x", "mm", 1e3),
        ("rms", 1, "px", "mrad", 1e3),
        ("rms", 2, "y", "mm", 1e3),
        ("rms", 3, "py", "mrad", 1e3),
    ],
}
_HEADLINE_6D = {
    "rms": [("rms", 4, "z", "mm", 1e3), ("rms", 5, "pz", "1e-3", 1e3)],
    "emittance (geometric)": [
        ("emit_z", None, "z", "mm mrad", 1e6),
        ("emit_6d", None, "6D", "m^3", 1.0),
    ],
}


def _headline_rows(
    summary: Mapping[str, Any],
) -> list[tuple[str, str, float, float, str]]:
    """(group, label, mean, std, unit) of the headline numbers, in display units."""
    moments = summary["moments"]
    groups = {k: list(v) for k, v in _HEADLINE.items()}
    if summary.get("config", {}).get("dims") == 6:
        groups["rms"] += _HEADLINE_6D["rms"]
        groups["emittance (geometric)"] = _HEADLINE_6D["emittance (geometric)"]
    rows = []
    for group, items in groups.items():
        for key, index, label, unit, scale in items:
            entry = moments.get(key)
            if entry is None:
                continue
            mean, std = entry["mean"], entry["std"]
            if index is not None:
                mean, std = mean[index], std[index]
            mean = math.nan if mean is None else scale * mean
            std = math.nan if std is None else scale * std
            rows.append((group, label, mean, std, unit))
    return rows


def _std(std: float) -> str:
    """A std for display: two digits, ``n/a`` where the summary has none."""
    return f"{std:.2g}" if math.isfinite(std) else "n/a"


def headline_lines(summary: Mapping[str, Any]) -> list[str]:
    """The headline numbers of a summary, one line per group, each with its std.

    Normalised emittances [mm mrad], Twiss beta [m] and alpha, rms sizes [mm]
    and divergences [mrad] (6D: also z [mm], pz [1e-3] and the z and 6D
    emittances), as ``mean +- std`` (``std``: the summary's, calibrated
    where the result carries the moment-space posterior; ``n/a`` where the
    summary holds none).
    """
    lines: dict[str, list[str]] = {}
    for group, label, mean, std, unit in _headline_rows(summary):
        text = f"{label} {mean:.4g} +- {_std(std)}" + (f" {unit}" if unit else "")
        lines.setdefault(group, []).append(text)
    return [f"{group}: " + ", ".join(items) for group, items in lines.items()]


def noise_note(errors: Mapping[str, Any]) -> str:
    """What an image error holds besides the beam: the predictions' own noise
    and the data's floor (from its shots), as a parenthesis; ``""`` when the
    errors carry neither.

    Example:
        >>> noise_note({"prediction_noise_l1": 0.021, "data_noise_l1": None})
        " (predictions' own noise 0.021; data floor unknown: single shots)"
    """
    own = errors.get("prediction_noise_l1")
    if own is None and "data_noise_l1" not in errors:
        return ""
    floor = errors.get("data_noise_l1")
    parts = [] if own is None else [f"predictions' own noise {own:.3f}"]
    if floor is None:
        parts.append("data floor unknown: single shots")
    else:
        parts.append(f"data floor {floor:.3f}")
    return " (" + "; ".join(parts) + ")"


def score_lines(summary: Mapping[str, Any]) -> list[str]:
    """The image fit of a summary: held-out (where any) and training relative L1,
    each with its :func:`noise_note`.

    Example:
        >>> score_lines({"metrics": {"images_train": {"relative_l1": 0.0123}}})
        ['train image relative L1: 0.0123']
    """
    m = summary["metrics"]
    lines = []
    if "images_held_out" in m:
        held = m["images_held_out"]
        lines.append(
            f"held-out image relative L1: {held['relative_l1']:.4f}" + noise_note(held)
        )
    train = m["images_train"]
    lines.append(
        f"train image relative L1: {train['relative_l1']:.4f}" + noise_note(train)
    )
    return lines


def finding_lines(summary: Mapping[str, Any]) -> list[str]:
    """What a summary found, as lines of text.

    The coordinates the scans do not constrain, the headline numbers
    (:func:`headline_lines`), the unseen correlations set by the prior
    (:func:`prior_dependence_lines`), the scans whose smallest spot is below
    their point spread and the observability note, in 6D with
    the command that ranks the settings to add where it leaves quantities to
    the prior; each line only where the summary holds it.
    """
    lines = []
    if summary["unconstrained_coordinates"]:
        lines.append(
            "not constrained by the scan: "
            + ", ".join(summary["unconstrained_coordinates"])
        )
    lines += headline_lines(summary)
    lines += prior_dependence_lines(summary.get("prior_dependence", []))
    lines += summary.get("point_spread", [])
    if summary.get("observability"):
        lines.append(summary["observability"])
        six = summary.get("config", {}).get("dims") == 6
        if six and "left to the prior" in summary["observability"]:
            lines.append(
                "settings that would see them: diffaccel design "
                f"{summary.get('dataset', 'DATA.h5')} --knob ELEMENT.PARAMETER=LOW:HIGH"
                " (ranked by the std they remove; diffaccel design --help)"
            )
    return lines


def stopped_note(
    out: str | os.PathLike, interrupted: bool, checkpoint_every: int
) -> str | None:
    """What is left of a run into ``out`` that stopped (refused, failed, interrupted).

    Args:
        out: The run's result folder.
        interrupted: The run was interrupted (Ctrl-C), not stopped by an error.
        checkpoint_every: Steps between the run's checkpoints.

    Returns:
        A ``note: ...`` line naming the checkpoint kept in the staging folder,
        or (interrupted before the first checkpoint) saying that nothing is
        left to resume; None where neither applies. Call it only for a run
        that had the folder (not one refused at the lock): a checkpoint there
        would be another run's.
    """
    staging = partial_folder(out)
    if (staging / CHECKPOINT).is_file():
        return (
            f"note: the run's checkpoint is kept in {staging}; --resume continues "
            f"it ({out} is unchanged)"
        )
    if interrupted:
        return (
            "note: interrupted before the first checkpoint (written every "
            f"{checkpoint_every} steps): nothing to resume, {out} is unchanged"
        )
    return None


def report_markdown(summary: Mapping[str, Any]) -> str:
    """``report.md`` of a result folder: headline numbers, fit quality, warnings.

    A table of the headline quantities (:func:`headline_lines`) with their std
    and, where the dataset holds the true beam, the relative error; the image
    errors (training, held out), the warnings, the coordinates the scans do not
    constrain, and the figures and files of the folder.
    """
    m = summary["metrics"]
    gt = m.get("ground_truth", {})
    truth_key = {"x": "rms_x", "px": "rms_px", "y": "rms_y", "py": "rms_py"}
    truth_key.update({"z": "rms_z", "pz": "rms_pz"})
    lines = [
        "# diffaccel reconstruction",
        "",
        f"Dataset: `{summary.get('dataset', '')}`; {summary.get('snapshots', '?')} "
        "ensemble members. Uncertainties are 1 std "
        + (
            "(calibrated, moment-space posterior)."
            if summary.get("uncertainty")
            else "(ensemble scatter only)."
        ),
        "",
        "| quantity | value +- std | error vs truth |",
        "|---|---|---|",
    ]
    for group, label, mean, std, unit in _headline_rows(summary):
        key = truth_key.get(label) if group == "rms" else None
        if group.startswith("emittance"):
            key = {"x": "emit_x", "y": "emit_y", "z": "emit_z", "6D": "emit_6d"}[label]
        err = gt.get(key) if key else None
        e = f"{100 * err:+.1f} %" if isinstance(err, int | float) else "n/a"
        u = f" [{unit}]" if unit else ""
        lines.append(f"| {group} {label}{u} | {mean:.4g} +- {_std(std)} | {e} |")
    lines += [""]
    held_errors = m.get("images_held_out", {})
    train_errors = m.get("images_train", {})
    held = held_errors.get("relative_l1")
    train = train_errors.get("relative_l1")
    fit = (
        f"Training image relative L1: {train:.4f}" + noise_note(train_errors)
        if train is not None
        else ""
    )
    if held is not None:
        fit += f"; held out: {held:.4f}" + noise_note(held_errors)
    lines += [fit + ".", ""]
    warnings = summary.get("warnings", [])
    lines += ["Warnings: " + ("none" if not warnings else ""), ""]
    lines += [f"- {w}" for w in warnings] + ([""] if warnings else [])
    lines += [
        "Not constrained by the scans (their values follow the prior): "
        + (", ".join(summary.get("unconstrained_coordinates", [])) or "none"),
        "",
    ]
    figures = summary.get("figures", [])
    if figures:
        lines += ["Figures: " + " ".join(f"![{f}]({f})" for f in figures), ""]
    lines.append(
        "All numbers: `summary.json`; ensemble: `ensemble.pt` "
        "(`diffaccel.reconstruction.load`); particles: "
        f"`{summary.get('particles_file', 'particles.h5')}` (openPMD, bunch charge "
        f"{summary.get('particles_charge_C', DEFAULT_CHARGE_C):.4g} C)."
    )
    return "\n".join(lines) + "\n"


def demo_dataset(seed: int = 0) -> QuadScanDataset:
    """The scan of ``diffaccel demo``: a correlated 6D beam, chromatic tracking.

    20 quadrupole settings (k1 -20 ... 20 1/m^2) of 20 000 particles of the
    preset ``correlated`` on a 64 x 64 screen of 0.5 mm pixels, 5 % noise.
    """
    return make_synthetic_quad_scan(
        "correlated",
        n_particles=20_000,
        screen_shape=(64, 64),
        pixel_size=(0.5e-3, 0.5e-3),
        k1_range=(-20.0, 20.0),
        noise=0.05,
        seed=seed,
    )


def demo_config(seed: int = 0) -> ReconstructionConfig:
    """The reconstruction of ``diffaccel demo``: 6D, 300 steps of 4096 particles.

    6D tracking is chromatic (slower than the 4D linear maps): fewer, smaller
    steps keep the demo well under a minute on two quiet CPU cores. The file
    records its screen resolution (KDE of one-pixel bandwidth), which the
    reconstruction models by default; 5 cycles, the first dropped (the 6D
    defaults are sized for the quadrupole x TDC x dipole scans, see
    :class:`ReconstructionConfig`).
    """
    return ReconstructionConfig(
        dims=6, seed=seed, steps=300, snapshots=5, burn_in=1, n_particles=4096
    )


def demo_report_markdown(
    summary: Mapping[str, Any], dataset_name: str, seconds: float
) -> str:
    """``report.md`` of ``diffaccel demo``: the 6D reconstruction of its synthetic scan.

    The rms sizes [mm, mrad, 1e-3] and emittances (mean +- ensemble std, error
    vs the known beam), the image errors on the held-out (odd) and training
    (even) settings, the unconstrained coordinates and the figures.

    Args:
        summary: ``summary.json`` of the run (:func:`write_result`).
        dataset_name: File name of the simulated scan.
        seconds: Wall time of the whole demo [s].
    """
    m = summary["metrics"]
    mo = summary["moments"]
    lines = [
        "# diffaccel demo: phase-space reconstruction of a synthetic quad scan",
        "",
        f"Dataset: `{dataset_name}` (preset `correlated` 6D beam, 0.5 % energy spread,"
        " chromatic quadrupole, 20 settings, Poisson noise); trained on the even"
        f" settings, tested on the odd ones. Total time {seconds:.0f} s.",
        "",
        "| quantity | reconstruction (mean +- ensemble std) | error vs truth |",
        "|---|---|---|",
    ]
    gt = m.get("ground_truth", {})
    names = ("x", "px", "y", "py", "z", "pz")
    units = (1e3, 1e3, 1e3, 1e3, 1e3, 1e3)
    labels = ("mm", "mrad", "mm", "mrad", "mm", "1e-3")
    for i, c in enumerate(names):
        v, s = mo["rms"]["mean"][i], mo["rms"]["std"][i]
        err = gt.get(f"rms_{c}")
        e = f"{100 * err:+.1f} %" if err is not None else "n/a"
        lines.append(
            f"| rms {c} [{labels[i]}] | {v * units[i]:.4g} "
            f"+- {s * units[i]:.2g} | {e} |"
        )
    for key, unit in (("emit_x", "m"), ("emit_y", "m"), ("emit_6d", "m^3")):
        v, s = mo[key]["mean"], mo[key]["std"]
        err = gt.get(key)
        e = f"{100 * err:+.1f} %" if err is not None else "n/a"
        lines.append(f"| {key} [{unit}] | {v:.4g} +- {s:.2g} | {e} |")
    lines += [
        "",
        f"Held-out image relative L1: {m['images_held_out']['relative_l1']:.4f}; "
        f"training: {m['images_train']['relative_l1']:.4f}.",
        "",
        "Not constrained by the scan (values follow the prior; treat them as "
        "unknown): " + (", ".join(summary["unconstrained_coordinates"]) or "none"),
        "",
        "Figures: ![phase space](phase_space.png) ![images](images.png) "
        "![training](training.png) ![rms](rms_evolution.png)",
        "",
        "All numbers: `summary.json`; ensemble: `ensemble.pt` "
        "(`diffaccel.reconstruction.load`); particles: `particles.h5` (openPMD).",
    ]
    return "\n".join(lines) + "\n"
