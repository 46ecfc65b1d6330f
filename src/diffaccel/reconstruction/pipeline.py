"""End-to-end reconstruction of a quad-scan dataset (one or several scans)."""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Literal

import torch
import torch.distributed as tdist
from torch import Tensor

from diffaccel.data.quad_scan import QuadScanDataset
from diffaccel.data.scans import MultiScanDataset, parse_selection
from diffaccel.dynamics import is_integer
from diffaccel.reconstruction.ensemble import (
    Reconstruction,
    unconstrained_coordinates,
)
from diffaccel.reconstruction.forward import ScreenForwardModel
from diffaccel.reconstruction.initial import check_guess, fit_gaussian
from diffaccel.reconstruction.metrics import beam_moments
from diffaccel.reconstruction.rank_members import (
    gather_members,
    member_checkpoint,
    member_seed,
)
from diffaccel.reconstruction.training import (
    CHECKPOINT_EVERY,
    REPORT_EVERY,
    ReconstructionConfig,
    StepInfo,
    checkpoint_config,
    train_generator,
)
from diffaccel.reconstruction.uncertainty import analyse_moments

TrainIndices = Sequence[int] | Mapping[str, Sequence[int]] | str | None


def as_scans(dataset: QuadScanDataset | MultiScanDataset) -> MultiScanDataset:
    """A dataset as scans of one beam (a single scan is named ``"scan"``)."""
    if isinstance(dataset, MultiScanDataset):
        return dataset
    if isinstance(dataset, QuadScanDataset):
        return MultiScanDataset.from_scan(dataset)
    raise TypeError(
        f"dataset: expected a QuadScanDataset or MultiScanDataset; got "
        f"{type(dataset).__name__}"
    )


class TrainingSelection(dict[str, list[int]]):
    """Checked training settings ``{scan name: indices}`` of one dataset.

    Returned by :func:`training_selection`; passing it back (e.g. from the CLI,
    which checks its options before the run starts) skips a second check.
    """

    @property
    def names(self) -> tuple[str, ...]:
        """The scan names, in the dataset's order."""
        return tuple(self)


def _indices(given: object, scan: str) -> list[int]:
    """A scan's training indices as ints; text, floats and booleans refused."""
    if isinstance(given, str | bytes):
        raise ValueError(
            f"train_indices of scan {scan!r}: expected a list of integer indices; "
            f"got the text {given!r} (a rule such as 'even' applies to every scan: "
            "pass it as train_indices itself)."
        )
    try:
        items = list(given)  # type: ignore[call-overload]
    except TypeError:
        raise ValueError(
            f"train_indices of scan {scan!r}: expected a list of integer indices; "
            f"got {given!r}."
        ) from None
    out = []
    for i in items:
        if isinstance(i, Tensor) and i.numel() == 1:
            i = i.item()
        if not is_integer(i):
            raise ValueError(
                f"train_indices of scan {scan!r}: {i!r} is not an integer index."
            )
        out.append(int(i))
    return out


def training_selection(
    dataset: MultiScanDataset, train_indices: TrainIndices
) -> TrainingSelection:
    """Training settings per scan, checked, from any accepted form.

    Args:
        dataset: The scans.
        train_indices: None (every setting of every scan); a rule string for
            :func:`~diffaccel.data.parse_selection`; a list of indices (applied
            to every scan); or ``{scan: indices}`` (scans not named: none).

    Returns:
        ``{scan name: indices}`` (a :class:`TrainingSelection`) for every scan, at
        least one index in total.

    Raises:
        ValueError: naming the scan for an index out of range, a repeated
            index, an unknown scan, or an empty selection; naming the scans and
            values when every scan that scans a quadrupole's ``k1`` is selected
            at a single value of it (the divergence is then unconstrained).
    """
    if isinstance(train_indices, TrainingSelection) and train_indices.names == tuple(
        dataset.names
    ):
        return train_indices  # checked already (the CLI checks before its run)
    selection = _selection(dataset, train_indices)
    _check_quadrupole_values(dataset, selection)
    return selection


def _check_quadrupole_values(
    dataset: MultiScanDataset, selection: TrainingSelection
) -> None:
    """Refuse a selection that holds one value of the scanned quadrupoles in
    every scan that scans one: one focusing strength sees a single projection
    of (x, px), so the divergence and its correlation are not constrained (the
    fit then finds no positive definite beam, and tracking loses particles)."""
    single = {}
    for name, scan in dataset:
        idx = selection[name]
        if not idx:
            continue
        types = {e["name"]: e["type"] for e in scan.beamline_spec}
        cols = [
            j
            for j, n in enumerate(scan.setting_names)
            if n.partition(".")[2] == "k1"
            and types.get(n.partition(".")[0]) == "Quadrupole"
        ]
        if not cols:
            continue
        values = scan.settings[idx][:, cols]
        if torch.unique(values, dim=0).shape[0] > 1:
            return
        names = [scan.setting_names[j] for j in cols]
        single[name] = ", ".join(
            f"{n} = {v:g}" for n, v in zip(names, values[0].tolist(), strict=True)
        )
    if single:
        where = "; ".join(f"scan {n!r}: {v}" for n, v in single.items())
        raise ValueError(
            "train_indices select a single value of the scanned quadrupole in "
            f"every scan ({where}): one focusing strength leaves the beam's "
            "divergence unconstrained; select settings with at least 2 (better 3 "
            "or more) distinct quadrupole values."
        )


def _scans_focusing(dataset: MultiScanDataset, used: Sequence[str]) -> bool:
    """Whether any of the ``used`` scans varies a quadrupole's k1 or a
    solenoid's ks."""
    focusing = {"Quadrupole": "k1", "Solenoid": "ks"}
    for name in used:
        scan = dataset[name]
        types = {e["name"]: e["type"] for e in scan.beamline_spec}
        for j, n in enumerate(scan.setting_names):
            element, _, param = n.partition(".")
            if focusing.get(types.get(element, "")) == param and bool(
                (scan.settings[:, j] != scan.settings[0, j]).any()
            ):
                return True
    return False


def _selection(
    dataset: MultiScanDataset, train_indices: TrainIndices
) -> TrainingSelection:
    """The selection of :func:`training_selection`, before the quadrupole check."""
    if train_indices is None:
        sel = {name: list(range(scan.n_settings)) for name, scan in dataset}
        return TrainingSelection(sel)
    if isinstance(train_indices, str):
        return TrainingSelection(parse_selection(train_indices, dataset))
    if isinstance(train_indices, Mapping):
        unknown = sorted(set(train_indices) - set(dataset.names))
        if unknown:
            raise ValueError(
                f"train_indices: unknown scan(s) {unknown}; scans are {dataset.names}."
            )
        raw = {name: train_indices.get(name, []) for name in dataset.names}
    else:
        raw = {name: train_indices for name in dataset.names}
    out = {}
    for name, given in raw.items():
        k = dataset[name].n_settings
        idx = _indices(given, name)
        if any(i < 0 or i >= k for i in idx) or len(set(idx)) != len(idx):
            raise ValueError(
                f"train_indices of scan {name!r} must be distinct integers in "
                f"[0, {k}); got {idx}."
            )
        out[name] = idx
    if not any(out.values()):
        raise ValueError("train_indices select no setting in any scan.")
    return TrainingSelection(out)


def _usable_device(device: str | torch.device) -> torch.device:
    """``device`` as a torch device this machine has (a one-line error otherwise)."""
    try:
        dev = torch.device(device)
    except (RuntimeError, ValueError, TypeError) as err:
        raise ValueError(
            f"device {device!r} is not a torch device (cpu, cuda, cuda:1, mps...)."
        ) from err
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {device!r}: CUDA is not available on this machine.")
    if dev.type == "cuda" and (dev.index or 0) >= torch.cuda.device_count():
        raise ValueError(
            f"device {device!r}: this machine has {torch.cuda.device_count()} CUDA "
            "device(s)."
        )
    return dev


def reconstruct(
    dataset: QuadScanDataset | MultiScanDataset,
    config: ReconstructionConfig | None = None,
    *,
    train_indices: TrainIndices = None,
    checkpoint: str | os.PathLike | None = None,
    resume: bool = False,
    callback: Callable[[StepInfo], None] | None = None,
    device: str | torch.device = "cpu",
    distributed: bool = False,
    split: Literal["particles", "members"] = "particles",
    uncertainty: bool = True,
    checkpoint_every: int = CHECKPOINT_EVERY,
    report_every: int = REPORT_EVERY,
    cuda_graph: bool = True,
) -> Reconstruction:
    """Reconstruct the initial phase space of a beam from one or several scans.

    Builds the forward model of every scan (beamline, screen, scanned names),
    fits a Gaussian to the image moments of all training images as a starting
    point, and trains a snapshot ensemble of beam generators on the
    shot-averaged, sum-normalised training images of every scan.

    Args:
        dataset: One scan (images ``(K, S, H, W)``, settings ``(K, P)``) or
            several (:class:`~diffaccel.data.MultiScanDataset`).
        config: Training settings; defaults to :class:`ReconstructionConfig`.
        train_indices: Training settings, see :func:`training_selection`
            (default all settings of all scans).
        checkpoint: Checkpoint file (written atomically during training).
        resume: Continue from ``checkpoint`` if it exists (the stored config
            must equal ``config``).
        callback: Progress callback, see
            :func:`~diffaccel.reconstruction.training.train_generator`.
        device: ``"cpu"``, ``"cuda"``...
        distributed: Split every step's particles across the processes of the
            initialised ``torch.distributed`` group (see
            :func:`~diffaccel.reconstruction.training.train_generator`); every
            process returns the same reconstruction.
        split: With ``distributed``: ``"particles"`` (default) splits every
            step's particles across the processes; ``"members"`` trains one
            independent ensemble per process (process ``r`` with seed
            ``config.seed + 7919 r`` and its own checkpoint, ``<stem>.rank<r>``
            beside ``checkpoint``) and gathers all members into one ensemble
            (see :mod:`diffaccel.reconstruction.rank_members`).
        uncertainty: Attach the moment-space posterior of
            :func:`attach_uncertainty` (calibrated ``std`` of the moments;
            about 1 s on two CPU cores).
        checkpoint_every: Steps between checkpoints (a runtime choice of
            :func:`~diffaccel.reconstruction.training.train_generator`, as are
            the next two; none changes the result).
        report_every: Steps between reads of the losses from the device.
        cuda_graph: Capture the training step as a CUDA graph on a GPU.

    Returns:
        The :class:`Reconstruction`; ``info["scans"][name]`` holds each scan's
        ``train_indices`` and ``train_settings``; for a single scan they are
        also at the top level of ``info``, with timings [s]; ``info
        ["uncertainty"]`` the moment-space posterior.

    Raises:
        ValueError: for bad indices, a device this machine lacks, a checkpoint
            path that is a folder, or a checkpoint written with a different
            config or for other data (naming the scan where one is concerned).
            Images are checked by the dataset (finite, positive sums).
    """
    config = config or ReconstructionConfig()
    device = _usable_device(device)
    if checkpoint is not None and Path(checkpoint).is_dir():
        raise ValueError(
            f"checkpoint {checkpoint} is a folder; give a file name in it, e.g. "
            f"{Path(checkpoint) / 'checkpoint.pt'}."
        )
    if split not in ("particles", "members"):
        raise ValueError(f"split must be 'particles' or 'members'; got {split!r}.")
    members = distributed and split == "members"
    run_config = config  # the settings this process trains with
    if members:
        # each process trains the whole beam with its own seed and checkpoint
        run_config = member_seed(config, tdist.get_rank())
        checkpoint = member_checkpoint(checkpoint, tdist.get_rank())
    scans = as_scans(dataset)
    selection = training_selection(scans, train_indices)
    used = [name for name in scans.names if selection[name]]
    measured, settings, forwards = [], [], {}
    for name in used:
        scan = scans[name]
        images = scan.mean_images()  # finite, positive sums: checked by the dataset
        measured.append(images[selection[name]])
        settings.append(scan.settings[selection[name]])
    if resume and checkpoint is not None and Path(checkpoint).exists():
        stored = checkpoint_config(checkpoint)
        if stored != run_config:
            raise ValueError(
                f"checkpoint {checkpoint} was written with a different config "
                f"({stored}); resume with the same options."
            )
    t0 = time.perf_counter()
    for name in used:
        forwards[name] = ScreenForwardModel.from_dataset(
            scans[name], blur_pixels=config.blur_for(scans[name])
        )
    # the affine maps of every training setting, once per run: the initial fit,
    # the 4D training step, the unconstrained flags and the uncertainty analysis
    maps = [
        fwd.transfer_maps(s) for fwd, s in zip(forwards.values(), settings, strict=True)
    ]
    guess = fit_gaussian(list(forwards.values()), measured, settings, maps=maps)
    check_guess(guess, used, focusing_scanned=_scans_focusing(scans, used))
    t1 = time.perf_counter()
    state = train_generator(
        list(forwards.values()),
        [m.to(device) for m in measured],
        settings,
        guess,
        run_config,
        checkpoint=checkpoint,
        resume=resume,
        callback=callback,
        device=device,
        distributed=distributed and not members,
        maps=maps,
        checkpoint_every=checkpoint_every,
        report_every=report_every,
        cuda_graph=cuda_graph,
    )
    for fwd in forwards.values():
        fwd.to("cpu")
    snapshots = state.snapshots
    if members:
        snapshots = gather_members(snapshots)
    per_scan = {
        name: {
            "train_indices": selection[name],
            "train_settings": scans[name].settings[selection[name]].tolist(),
            "blur_pixels": forwards[name].blur_pixels,
            "setting_names": list(scans[name].setting_names),
        }
        for name in used
    }
    info: dict = {
        "scans": per_scan,
        "initial_guess_mean": guess.mean.tolist(),
        "initial_guess_cov": guess.cov.tolist(),
        "timings_s": {
            "initial_fit": t1 - t0,
            "training": state.elapsed_s,
        },
        "device": str(device),
        "member_processes": tdist.get_world_size() if members else 1,
        "unconstrained_coordinates": unconstrained_coordinates(maps, config.dims),
    }
    if len(scans) == 1:
        info.update(per_scan[used[0]])
    result = Reconstruction(
        config, snapshots, forwards, state.history, info, training_maps=maps
    )
    if uncertainty:
        t2 = time.perf_counter()
        attach_uncertainty(
            result,
            dict(zip(used, measured, strict=True)),
            dict(zip(used, settings, strict=True)),
            maps=dict(zip(used, maps, strict=True)),
        )
        result.info["timings_s"]["uncertainty"] = time.perf_counter() - t2
    return result


def psf_excess(fwd: ScreenForwardModel) -> tuple[float, float]:
    """Variance ``(x, y)`` [m^2] the forward model's point spread adds beyond
    ``blur_pixels``.

    The model deposits with cloud-in-cell (variance 1/6 pixel^2 per axis) and
    blurs only what ``blur_pixels`` asks beyond that, so a ``blur_pixels``
    below ``sqrt(1/6)`` (the 6D default ``sqrt(1/12)`` of histogram images)
    images every particle wider than the data: ``(1/6 - blur^2)`` pixel^2.

    Example:
        >>> from diffaccel.data import make_synthetic_quad_scan
        >>> ds = make_synthetic_quad_scan("gaussian", n_particles=100)
        >>> psf_excess(ScreenForwardModel.from_dataset(ds, blur_pixels=1.0))
        (0.0, 0.0)
    """
    extra = max(1.0 / 6.0 - fwd.blur_pixels**2, 0.0)
    psx, psy = fwd.screen.pixel_size
    return (extra * psx**2, extra * psy**2)


def attach_uncertainty(
    result: Reconstruction,
    measured: Mapping[str, torch.Tensor],
    settings: Mapping[str, torch.Tensor],
    *,
    n_particles: int = 20_000,
    seed: int = 0,
    maps: Mapping[str, torch.Tensor] | None = None,
    **options: float | bool,
) -> Reconstruction:
    """Store the moment-space posterior of a reconstruction in ``info``.

    Predicts the training images, compares their moments with the measured
    ones and runs :func:`~diffaccel.reconstruction.uncertainty.analyse_moments`
    (``options`` are passed on); the result lands in
    ``result.info["uncertainty"]`` and from then on enters
    :meth:`Reconstruction.moments` and ``predict_images(return_std=True)``.

    Args:
        result: The reconstruction (changed in place and returned).
        measured: Sum-normalised training images per scan ``(K_s, H_s, W_s)``.
        settings: Their settings per scan ``(K_s, P_s)``.
        n_particles: Particles per member for the predicted images.
        seed: Sampling seed.
        maps: Each scan's ``transfer_maps(settings)`` ``(K_s, 7, 7)`` when the
            caller has them (computed here otherwise).
    """
    jacobians, meas, pred, axes, excess = [], [], [], [], []
    for name, images in measured.items():
        fwd = result.forwards[name]
        sets = settings[name]
        r = fwd.transfer_maps(sets) if maps is None else maps[name]
        jacobians.append(r[..., :6, :6])
        meas.append(images.detach().cpu())
        pred.append(
            result.predict_images(
                sets, scan=name, n_particles=n_particles, seed=seed, maps=r
            )
        )
        axes.append(fwd.screen.pixel_centers(dtype=torch.float64))
        excess.append(psf_excess(fwd))
    options.setdefault("psf_excess", excess)  # type: ignore[arg-type]
    m = beam_moments(result.sample(max(n_particles, 50_000), seed=seed))
    unc = analyse_moments(
        jacobians,
        meas,
        pred,
        axes,
        m["centroid"],
        m["cov"],
        result.config.dims,
        **options,  # type: ignore[arg-type]
    )
    result.info["uncertainty"] = unc.to_dict()
    return result
