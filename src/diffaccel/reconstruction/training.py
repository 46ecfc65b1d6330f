"""Training loop: entropy-regularised image fitting with snapshot ensembling."""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from diffaccel.data import atomic_write
from diffaccel.dynamics.images import gaussian_blur
from diffaccel.reconstruction.forward import ScreenForwardModel
from diffaccel.reconstruction.generator import BeamGenerator
from diffaccel.reconstruction.initial import GaussianGuess
from diffaccel.reconstruction.losses import (
    ImageLoss,
    cyclic_cosine_lr,
    gaussian_entropy,
    gaussian_prior_term,
    image_penalty,
    off_screen_allowance,
    penalty_schedule,
)

logger = logging.getLogger(__name__)

CHECKPOINT_VERSION = 1


#: Defaults of ``(blur_pixels, loss_smoothing)`` by ``dims``. 4D: tuned on the
#: GPSR 4D benchmark (KDE images of one-pixel bandwidth). 6D: scans with a
#: deflecting cavity and a dipole image small spots (down to ~1 pixel); images
#: rendered without a point spread (histograms) are matched with a
#: 0.5-pixel blur, and the 1-pixel loss smoothing keeps the KL distance
#: unbiased for sparse simulated images (see ``loss_smoothing``). Measured
#: against its own validation split (k1 = -6, 6 held out) of the shared 6D
#: training file: blur 1.0 without smoothing left even the true beam at
#: relative L1 0.15-0.3 on small spots, and rms sizes came out ~10 % large.
_DIMS_DEFAULTS: dict[int, tuple[float, float]] = {4: (1.0, 0.0), 6: (0.5, 1.0)}


@dataclass(frozen=True)
class ReconstructionConfig:
    """Settings of a phase-space reconstruction (everything but the data).

    Defaults are sized so that a 4D reconstruction of a 20-setting, 100 x 100 pixel
    quad scan takes ~2-2.5 s on two quiet CPU cores (``benchmarks/reconstruction.py``):
    6144 fresh quasi-random particles x 300 steps of ~7 ms, MLP 2 x 48. On the
    GPSR 4D benchmark (seeds 0, 1, 2) 300 steps gave rms sizes within 1.9 %,
    x/y emittances within 3.3 % and held-out relative L1 0.079-0.087 (gpsr:
    0.117); 400 steps gave rms within 1.9 %, emittances within 3.9 % and
    held-out L1 0.070-0.076 at 4/3 of the time.

    Args:
        dims: 4 reconstructs (x, px, y, py) with ``z = pz = 0``; 6 also generates
            (z, pz), which a quad scan barely constrains (they stay near their prior).
        n_particles: Fresh particles drawn at every step.
        width: MLP hidden width.
        depth: MLP hidden layers.
        steps: Total optimisation steps (one step sees every training image).
        snapshots: Cosine learning-rate cycles; one ensemble member per cycle.
        lr_max: Learning rate at the start of each cycle.
        lr_min: Learning rate at the end of each cycle (snapshot point).
        penalty_start: Image-penalty weight at step 0.
        penalty_end: Image-penalty weight from the end of the first cycle on.
            The entropy term has gradient 1 per unit ``log sigma`` of each
            coordinate, so at weight ``lambda`` it can move a size until the
            image mismatch rises by ~``1 / lambda`` per unit ``log sigma``. At
            1e3 that still inflated the x emittance of the GPSR benchmark by
            7-12 % (its x waist is 0.6 pixel rms, so a wider waist barely shows
            in the images); at 1e4 the final images match to within their noise
            and the emittances came out within 0-4 % (three seeds), while
            coordinates the images do not see are still set by the entropy.
        image_loss: ``"kl"`` (default), ``"l1"`` or ``"l2"``. Measured images
            carry shot noise; L1 is minimised by the pixel-wise *median* of that
            noise, which is below the mean in the sparse tails, so L1 fits come
            out narrow (rms sizes 2-4 % low on the GPSR benchmark). KL is the
            Poisson log-likelihood of the image, minimised by the mean, and gave
            sizes within ~1.5 % on the same data.
        quasi_random: Draw the fresh base samples of each step from a newly
            scrambled Sobol sequence (less image noise, hence less of the L1
            bias towards narrow beams) instead of i.i.d. normals.
        blur_pixels: Total point-spread rms of the simulated images [pixels],
            cloud-in-cell deposition (1/6 pixel^2 of variance) included; 1
            matches screens with a ~1 pixel resolution and the 1-pixel KDE of the
            GPSR benchmark. None: 1.0 for ``dims = 4``, 0.5 for ``dims = 6``.
        entropy_radius: Mahalanobis scale of the redescending weights of the
            tail-robust covariance (see ``robust_covariance``).
        loss_smoothing: Rms [pixels] of a Gaussian applied to both the measured
            and the simulated images before they are compared (the simulated
            ones get it on top of ``blur_pixels``). A sample of N particles makes
            sparse, noisy images, and the KL distance of noisy images is lower
            for a wider beam (its tails cover more measured pixels): on the 6D
            benchmark, 6144 truth particles imaged at 0.5 pixel scored better
            10 % wider than true. Smoothing by one pixel averages the noise over
            ~12 pixels and puts the minimum back at the true size. 0 compares
            the images as they are. None: 0 for ``dims = 4``, 1 for ``dims = 6``.
        longitudinal_scale: Initial and prior rms of (z [m], pz [1]) when
            ``dims = 6`` and the scans do not see them (with a deflecting cavity
            or dispersion they come from the fitted image moments).
        prior_factor: Transverse prior widths are this factor times the widths of
            the Gaussian fitted to the image moments.
        seed: Seed of the explicit ``torch.Generator`` (weights and samples).
        checkpoint_every: Steps between checkpoints (also at every snapshot).
    """

    dims: int = 4
    n_particles: int = 6144
    width: int = 48
    depth: int = 2
    steps: int = 300
    snapshots: int = 5
    lr_max: float = 1e-2
    lr_min: float = 1e-4
    penalty_start: float = 10.0
    penalty_end: float = 1e4
    image_loss: ImageLoss = "kl"
    quasi_random: bool = True
    blur_pixels: float | None = None
    entropy_radius: float = 4.0
    loss_smoothing: float | None = None
    longitudinal_scale: tuple[float, float] = (1e-3, 1e-3)
    prior_factor: float = 3.0
    seed: int = 0
    checkpoint_every: int = 100

    def __post_init__(self) -> None:
        if self.dims not in (4, 6):
            raise ValueError(f"dims must be 4 or 6; got {self.dims}.")
        if self.blur_pixels is None:
            object.__setattr__(self, "blur_pixels", _DIMS_DEFAULTS[self.dims][0])
        if self.loss_smoothing is None:
            object.__setattr__(self, "loss_smoothing", _DIMS_DEFAULTS[self.dims][1])
        if self.snapshots < 1 or self.steps < self.snapshots:
            raise ValueError(
                f"need 1 <= snapshots <= steps; got snapshots={self.snapshots}, "
                f"steps={self.steps}."
            )
        if self.steps % self.snapshots:
            raise ValueError(
                f"steps ({self.steps}) must be a multiple of snapshots "
                f"({self.snapshots}) so that every cycle has the same length."
            )
        if self.n_particles < 16:
            raise ValueError(f"n_particles must be >= 16; got {self.n_particles}.")
        if self.image_loss not in ("l1", "l2", "kl"):
            raise ValueError(
                f"image_loss must be 'l1', 'l2' or 'kl'; got {self.image_loss!r}."
            )
        if not self.loss_smoothing >= 0 or not self.blur_pixels >= 0:
            raise ValueError(
                f"blur_pixels and loss_smoothing must be >= 0; got "
                f"{self.blur_pixels}, {self.loss_smoothing}."
            )
        if not self.lr_max > 0 or not self.lr_min >= 0:
            raise ValueError("learning rates must be positive.")

    @property
    def cycle_length(self) -> int:
        """Steps per learning-rate cycle."""
        return self.steps // self.snapshots

    def to_dict(self) -> dict:
        """Plain-Python form (JSON and ``weights_only`` safe)."""
        d = asdict(self)
        d["longitudinal_scale"] = list(self.longitudinal_scale)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> ReconstructionConfig:
        """Inverse of :meth:`to_dict`."""
        d = dict(d)
        if "epochs" in d:  # files written before the rename to ``steps``
            d["steps"] = d.pop("epochs")
        d["longitudinal_scale"] = tuple(d["longitudinal_scale"])
        return cls(**d)


@dataclass
class StepInfo:
    """Progress report handed to the training callback after every step."""

    step: int
    total: int
    loss: float
    image_loss: float
    entropy: float
    lr: float
    penalty: float
    snapshot_taken: bool


@dataclass
class TrainingState:
    """Everything a checkpoint holds: resuming from it reproduces the run exactly."""

    step: int = 0
    model: dict = field(default_factory=dict)
    optimizer: dict = field(default_factory=dict)
    rng: Tensor | None = None
    snapshots: list[dict] = field(default_factory=list)
    history: dict[str, list] = field(default_factory=dict)
    elapsed_s: float = 0.0


def _cpu_state(state: dict) -> dict:
    return {k: v.detach().to("cpu").clone() for k, v in state.items()}


def _new_history() -> dict[str, list]:
    return {
        "loss": [],
        "image_loss": [],
        "entropy": [],
        "lr": [],
        "penalty": [],
        "rms": [],
        "snapshot_steps": [],
    }


def _as_list(value: Any) -> list:
    return list(value) if isinstance(value, list | tuple) else [value]


def _smoothed(
    forwards: list[ScreenForwardModel], measured: list[Tensor], sigma_px: float
) -> tuple[list[ScreenForwardModel], list[Tensor]]:
    """Forward models and measured images both smoothed by ``sigma_px`` pixels."""
    out_f, out_m = [], []
    for f, m in zip(forwards, measured, strict=True):
        total = math.hypot(f.blur_pixels, sigma_px)
        out_f.append(
            ScreenForwardModel(
                f.beamline, f.names, f.p0c, species=f.species, blur_pixels=total
            )
        )
        psx, psy = f.screen.pixel_size
        blurred = gaussian_blur(m, (sigma_px * psx, sigma_px * psy), (psx, psy))
        # not renormalised: mass blurred off the screen is lost on both sides
        out_m.append(blurred)
    return out_f, out_m


def train_generator(
    forward: ScreenForwardModel | Sequence[ScreenForwardModel],
    measured: Tensor | Sequence[Tensor],
    settings: Tensor | Sequence[Tensor],
    guess: GaussianGuess,
    config: ReconstructionConfig,
    *,
    checkpoint: str | os.PathLike | None = None,
    resume: bool = False,
    callback: Callable[[StepInfo], None] | None = None,
    device: str | torch.device | None = None,
) -> TrainingState:
    """Fit a :class:`BeamGenerator` to screen images and collect snapshot members.

    Loss at step ``t``: ``-(H(x) - C(x)) + lambda(t) * mean_k D(sim_k, meas_k)``
    with ``H`` the tail-robust Gaussian entropy bound of the generated particles
    (float64), ``C`` the cross-entropy of a broad Gaussian prior (bounds
    coordinates the images do not see), ``D`` the image distance of
    :func:`~diffaccel.reconstruction.losses.image_distance` between the
    *unnormalised* simulated images (sum = fraction on screen) and the
    sum-normalised measured ones, averaged over the images of all scans (each
    image weighs the same), and ``lambda(t)`` the schedule of
    :func:`~diffaccel.reconstruction.losses.penalty_schedule`. Adam with a cosine
    cyclic learning rate; the generator weights at the end of each cycle are one
    ensemble member.

    Every step draws one fresh sample of ``n_particles`` and images it through
    every scan (a Python loop over the scans, fixed shapes within each). With
    ``dims = 4`` (``pz = 0`` exactly) a scan whose affine maps are exact (see
    :meth:`ScreenForwardModel.linear_maps`) uses them
    (:meth:`ScreenForwardModel.images_linear`); otherwise, and with
    ``dims = 6``, scans track exactly (chromatic quadrupoles, RF curvature of a
    deflecting cavity, bends).

    Args:
        forward: Screen forward model of each scan (tracking + imaging); a single
            model for a single scan.
        measured: Sum-normalised measured images of each scan (float32).
        settings: Scan settings of those images, one tensor per scan.
        guess: Gaussian fitted to the image moments (initialises the generator).
        config: Training settings.
        checkpoint: File for atomic checkpoints; None disables them.
        resume: Continue from ``checkpoint`` if it exists.
        callback: Called with a :class:`StepInfo` after every step; an exception
            raised there stops training (the last checkpoint stays valid).
        device: Device to train on; default that of the first ``measured``.

    Shapes:
        Scan ``s``: ``measured (K_s, H_s, W_s)``, ``settings (K_s, P_s)``.

    Returns:
        The final :class:`TrainingState` (``snapshots`` holds one CPU state dict
        per cycle, ``history`` the per-step curves).

    Raises:
        ValueError: if the numbers of forward models, image stacks and settings
            differ.
    """
    forwards = _as_list(forward)
    measured_list = _as_list(measured)
    settings_list = _as_list(settings)
    if not (len(forwards) == len(measured_list) == len(settings_list) >= 1):
        raise ValueError(
            f"need one forward model, image stack and settings tensor per scan; got "
            f"{len(forwards)}, {len(measured_list)} and {len(settings_list)}."
        )
    device = torch.device(device) if device is not None else measured_list[0].device
    measured_list = [m.to(device=device, dtype=torch.float32) for m in measured_list]
    settings_list = [s.to(device=device) for s in settings_list]
    if config.loss_smoothing > 0:
        forwards, measured_list = _smoothed(
            forwards, measured_list, config.loss_smoothing
        )
    forwards = [f.to(device) for f in forwards]
    gen_rng = torch.Generator(device=device).manual_seed(config.seed)
    init_rng = torch.Generator().manual_seed(config.seed)
    dims = config.dims
    scale, offset, corr, prior = guess.generator_init(
        dims, config.longitudinal_scale, config.prior_factor
    )
    model = BeamGenerator(
        dims,
        width=config.width,
        depth=config.depth,
        scale=scale.float(),
        offset=offset.float(),
        correlation=corr,
        generator=init_rng,
    ).to(device)
    opt = torch.optim.Adam(model.parameters(), lr=config.lr_max)
    norm = scale.to(device=device, dtype=torch.float64)
    prior_std = prior.to(device=device, dtype=torch.float64)
    prior_mean = offset.to(device=device, dtype=torch.float64)
    state = TrainingState(history=_new_history())
    ckpt = Path(checkpoint) if checkpoint is not None else None
    if resume and ckpt is not None and ckpt.exists():
        state = load_checkpoint(ckpt)
        model.load_state_dict(state.model)
        opt.load_state_dict(state.optimizer)
        gen_rng.set_state(state.rng)
        logger.info("resumed from %s at step %d", ckpt, state.step)

    # dims = 4: pz = 0 exactly, so affine maps reproduce the tracking where the
    # beamline allows it (no cavity on, no bend); otherwise (and in 6D) track
    maps: list[Tensor | None] = [
        f.linear_maps(s, monochromatic=True) if dims == 4 else None
        for f, s in zip(forwards, settings_list, strict=True)
    ]
    maps = [m.to(device) if m is not None else None for m in maps]
    allowances = [off_screen_allowance(m) for m in measured_list]
    scans = list(
        zip(forwards, measured_list, settings_list, maps, allowances, strict=True)
    )
    total = config.steps
    cyc = config.cycle_length
    hist = state.history
    t0 = time.perf_counter() - state.elapsed_s
    while state.step < total:
        step = state.step
        lr = cyclic_cosine_lr(step, cyc, config.lr_max, config.lr_min)
        lam = penalty_schedule(step, cyc, config.penalty_start, config.penalty_end)
        for g in opt.param_groups:
            g["lr"] = lr
        particles = model(
            config.n_particles, generator=gen_rng, quasi_random=config.quasi_random
        )
        per_image = []
        for fwd, meas, sets, lin, allow in scans:
            if lin is not None:
                sim = fwd.images_linear(particles, lin)
            else:
                sim = fwd.images(particles, sets)
            per_image.append(image_penalty(sim, meas, config.image_loss, allow))
        dist = torch.cat(per_image).mean()
        xs = particles[:, :dims].to(torch.float64)  # one conversion for both terms
        entropy = gaussian_entropy(xs, radius=config.entropy_radius, scale=norm)
        cross = gaussian_prior_term(xs - prior_mean, prior_std)
        loss = -(entropy - cross) + lam * dist.to(torch.float64)
        # one host transfer per step for the loss, its parts and the rms sizes
        with torch.no_grad():
            rms = xs.detach().std(0)
            if dims < 6:  # the other coordinates are exactly zero
                rms = torch.cat([rms, rms.new_zeros(6 - dims)])
            scalars = torch.cat([torch.stack([loss, dist.double(), entropy]), rms])
        loss_v, dist_v, entropy_v, *rms_v = scalars.to("cpu").tolist()
        if not math.isfinite(loss_v):
            raise FloatingPointError(
                f"loss became {loss_v} at step {step}; the beam may have left "
                "the screen entirely. Check the screen calibration and settings."
            )
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        state.step = step + 1
        hist["loss"].append(loss_v)
        hist["image_loss"].append(dist_v)
        hist["entropy"].append(entropy_v)
        hist["lr"].append(lr)
        hist["penalty"].append(lam)
        hist["rms"].append(rms_v)
        snap = state.step % cyc == 0
        if snap:
            state.snapshots.append(_cpu_state(model.state_dict()))
            hist["snapshot_steps"].append(state.step)
        if ckpt is not None and (snap or state.step % config.checkpoint_every == 0):
            state.model = _cpu_state(model.state_dict())
            state.optimizer = opt.state_dict()
            state.rng = gen_rng.get_state()
            state.elapsed_s = time.perf_counter() - t0
            save_checkpoint(state, config, ckpt)
        if callback is not None:
            callback(
                StepInfo(
                    step=state.step,
                    total=total,
                    loss=hist["loss"][-1],
                    image_loss=hist["image_loss"][-1],
                    entropy=hist["entropy"][-1],
                    lr=lr,
                    penalty=lam,
                    snapshot_taken=snap,
                )
            )
    state.model = _cpu_state(model.state_dict())
    state.elapsed_s = time.perf_counter() - t0
    return state


def save_checkpoint(
    state: TrainingState, config: ReconstructionConfig, path: str | os.PathLike
) -> None:
    """Write a training checkpoint atomically (temp file + ``os.replace``)."""
    opt = state.optimizer
    opt_cpu = {
        "state": {
            k: {n: (t.to("cpu") if torch.is_tensor(t) else t) for n, t in v.items()}
            for k, v in opt.get("state", {}).items()
        },
        "param_groups": opt.get("param_groups", []),
    }
    payload = {
        "checkpoint_version": CHECKPOINT_VERSION,
        "config": config.to_dict(),
        "step": state.step,
        "model": state.model,
        "optimizer": opt_cpu,
        "rng": state.rng.to("cpu") if state.rng is not None else None,
        "snapshots": state.snapshots,
        "history": state.history,
        "elapsed_s": state.elapsed_s,
    }
    atomic_write(path, lambda p: torch.save(payload, p))


def load_checkpoint(path: str | os.PathLike) -> TrainingState:
    """Read a checkpoint written by :func:`save_checkpoint` (``weights_only``).

    Raises:
        ValueError: if the file is not a diffaccel training checkpoint.
    """
    try:
        d = torch.load(Path(path), weights_only=True, map_location="cpu")
    except Exception as exc:  # corrupt or foreign file
        raise ValueError(f"cannot read checkpoint {path}: {exc}") from exc
    if not isinstance(d, dict) or d.get("checkpoint_version") != CHECKPOINT_VERSION:
        raise ValueError(f"{path} is not a diffaccel reconstruction checkpoint.")
    return TrainingState(
        step=int(d["step"]),
        model=d["model"],
        optimizer=d["optimizer"],
        rng=d["rng"],
        snapshots=list(d["snapshots"]),
        history={k: list(v) for k, v in d["history"].items()},
        elapsed_s=float(d["elapsed_s"]),
    )


def checkpoint_config(path: str | os.PathLike) -> ReconstructionConfig:
    """The :class:`ReconstructionConfig` stored in a checkpoint."""
    d = torch.load(Path(path), weights_only=True, map_location="cpu")
    return ReconstructionConfig.from_dict(d["config"])
