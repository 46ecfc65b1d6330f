"""Training loop: entropy-regularised image fitting with snapshot ensembling."""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import pickle
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
import torch.distributed as tdist
from torch import Tensor

from diffaccel.data import atomic_write
from diffaccel.dynamics import finite_checks, is_integer
from diffaccel.dynamics.images import gaussian_blur
from diffaccel.reconstruction.config import ReconstructionConfig as ReconstructionConfig
from diffaccel.reconstruction.forward import (
    MAX_BLUR_PIXELS,
    ScanImages,
    ScreenForwardModel,
)
from diffaccel.reconstruction.generator import BeamGenerator, FlatGenerator
from diffaccel.reconstruction.graphed_step import (
    GRAPH_WARMUP_STEPS as GRAPH_WARMUP_STEPS,
)
from diffaccel.reconstruction.graphed_step import TrainingSteps
from diffaccel.reconstruction.hold import MomentHold, held_moments
from diffaccel.reconstruction.initial import GaussianGuess
from diffaccel.reconstruction.losses import (
    ImagePenalty,
    MomentMatch,
    RelativeEntropy,
    off_screen_allowance,
)
from diffaccel.reconstruction.optimiser import FlatAdam
from diffaccel.reconstruction.uncertainty import MOMENT_WINDOW, moment_window
from diffaccel.reconstruction.unseen import UnseenHold

logger = logging.getLogger(__name__)

CHECKPOINT_VERSION = 2  # 2: optimiser state of one flat parameter vector
#: Default steps between checkpoints (and reads of the losses from the device).
CHECKPOINT_EVERY = 100
REPORT_EVERY = 10


class CheckpointDataError(ValueError):
    """A checkpoint to resume was written for other training data."""


@dataclass
class StepInfo:
    """Progress report handed to the training callback.

    The callback runs every ``report_every`` steps and at snapshots,
    checkpoints and the last step, with the values of that step.
    """

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
    fingerprint: str = ""
    hold_moments: Tensor | None = None


def data_fingerprint(
    forwards: Sequence[ScreenForwardModel],
    measured: Sequence[Tensor],
    settings: Sequence[Tensor],
) -> str:
    """SHA-256 of the training data: forward models, images and settings.

    Stored in checkpoints so that a resume refuses other data (another file, other
    training settings, another screen calibration).
    """
    h = hashlib.sha256()
    for fwd, meas, sets in zip(forwards, measured, settings, strict=True):
        h.update(json.dumps(fwd.to_spec(), sort_keys=True, default=str).encode())
        for t in (meas, sets):
            t = t.detach().to("cpu").contiguous()
            h.update(f"{t.dtype}{tuple(t.shape)}".encode())
            h.update(t.numpy().tobytes())
    return h.hexdigest()


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


class _SumOverProcesses(torch.autograd.Function):
    """Sum of a tensor over all processes; every process gets the sum.

    Every process then computes the same loss from the sum, so the gradient of
    that one loss with respect to each process's part is the incoming gradient
    itself (not its sum over processes).
    """

    @staticmethod
    def forward(ctx, x: Tensor) -> Tensor:  # type: ignore[override]
        y = x.clone()
        tdist.all_reduce(y)
        return y

    @staticmethod
    def backward(ctx, grad: Tensor) -> Tensor:  # type: ignore[override]
        return grad


def _as_list(value: Any) -> list:
    return list(value) if isinstance(value, list | tuple) else [value]


def _kl_offset(c: float, forward: ScreenForwardModel, n: int) -> float:
    """``c kappa / n``: KL offset of ``n`` particles' images (``sampling_offset``)."""
    return c * forward.pixel_kernel_sum_sq() / n if c > 0 else 0.0


def image_rms_pixels(measured: Tensor) -> Tensor:
    """Rms beam sizes [pixels] ``(K, 2)`` (x, y) of images ``(K, H, W)``.

    Negative pixels (noise left by a background subtraction) count as zero.

    Example:
        >>> im = torch.zeros(1, 5, 5); im[0, 2, 1] = im[0, 2, 3] = 0.5
        >>> image_rms_pixels(im)
        tensor([[1., 0.]], dtype=torch.float64)
    """
    w = measured.detach().to(torch.float64).clamp_min(0.0)
    total = w.sum((-2, -1)).clamp_min(1e-300)
    rms = []
    for axis, n in ((-1, w.shape[-1]), (-2, w.shape[-2])):
        marginal = w.sum(-2 if axis == -1 else -1) / total[:, None]  # (K, n)
        idx = torch.arange(n, dtype=torch.float64, device=w.device)
        mean = (marginal * idx).sum(-1, keepdim=True)
        rms.append(((marginal * (idx - mean) ** 2).sum(-1)).sqrt())
    return torch.stack(rms, -1).cpu()


def sampling_smoothing(
    measured: Tensor, n_particles: int, floor: float = 0.0
) -> Tensor:
    """Rms [pixels] ``(K, 2)`` of the Gaussian that compares ``n_particles``'
    image of each setting with the measured one fairly.

    An image of ``N`` sampled particles is a histogram whose pixel noise grows as
    the pixels get finer or the beam larger; a divergence between such a sparse
    image and a measured one is lowest for a beam wider than the one sampled
    (its tails cover more measured pixels), so the fitted beam would depend on
    the camera's pixel size. Smoothing both images with the bandwidth at which
    a kernel density estimate of ``N`` samples is consistent removes that
    dependence: Scott's rule for a product kernel in two dimensions, ``h =
    sigma N^(-1/6)`` per axis, with ``sigma`` that image's rms size along the
    axis (:func:`image_rms_pixels`), so that every image is compared at the
    resolution its sample supports. Both sides get the same Gaussian, so
    second moments are unchanged (each gains ``h^2``); the result depends on
    the beam size and ``N`` only, not on how finely the camera samples it.
    ``floor`` (the point spread the images need anyway) is added in
    quadrature.

    Args:
        measured: Measured images of one scan ``(K, H, W)``.
        n_particles: Particles per training step ``N``.
        floor: Smoothing applied regardless [pixels].

    Returns:
        ``hypot(floor, sigma N^(-1/6))`` [pixels], ``(K, 2)`` float64.

    Example:
        >>> im = torch.zeros(1, 64, 64); im[0, 32, 22] = im[0, 32, 42] = 0.5
        >>> sampling_smoothing(im, 4096)
        tensor([[2.5000, 0.0000]], dtype=torch.float64)
    """
    if n_particles < 1:
        raise ValueError(f"n_particles must be >= 1; got {n_particles}.")
    h = image_rms_pixels(measured) * float(n_particles) ** (-1.0 / 6.0)
    return torch.hypot(torch.full_like(h, float(floor)), h).clamp_max(MAX_BLUR_PIXELS)


def scan_smoothing(
    measured: Tensor, n_particles: int, floor: float = 0.0, point_spread: float = 0.0
) -> float:
    """Loss smoothing [camera pixels] of one scan sized by its images and the
    number of particles per step.

    Two limits set it. The sample's: an image of ``N`` particles resolves a
    beam of rms ``sigma`` only to Scott's bandwidth ``sigma N^(-1/6)``
    (:func:`sampling_smoothing`); compared more finely, the sparse simulated
    image favours beams wider than the one sampled, so the scan's largest
    bandwidth (its widest image) is the finest consistent comparison. The
    scan's: smoothing by ``h`` leaves a beam spot of rms ``s`` only the
    fraction ``s^2 / (s^2 + h^2)`` of its width's sensitivity to the beam, so
    ``h`` never exceeds the beam's smallest spot of the scan along either axis
    (its waist: the smallest rms image size with the screen's
    ``point_spread`` taken out in quadrature), beyond which the images stop
    telling beam sizes apart and the entropy would fill in what they lost.
    The result is the smaller of the two, in quadrature with ``floor``. Where
    the first limit exceeds the second the comparison is finer than the
    sample resolves, and
    :func:`~diffaccel.reconstruction.evaluation.resolution_warnings` says when
    that leaves too much of an image's variance on pixels that fewer than one
    simulated particle reaches.

    Args:
        measured: Measured images of the scan ``(K, H, W)``.
        n_particles: Particles per training step ``N``.
        floor: Smoothing applied regardless [pixels].
        point_spread: Rms point spread of the measured images [pixels] (the
            simulated images' ``blur_pixels``).

    Returns:
        ``hypot(floor, min(max sigma N^(-1/6), s_min))`` [pixels], at most
        :data:`MAX_BLUR_PIXELS`.

    Example:
        >>> im = torch.zeros(2, 64, 64)
        >>> im[0, 12, 12] = im[0, 52, 52] = 0.5  # 20 pixels rms per axis
        >>> im[1, 31, 31] = im[1, 33, 33] = 0.5  # a waist: 1 pixel rms
        >>> scan_smoothing(im, 4096)  # the waist caps Scott's 5 pixels
        1.0
        >>> round(scan_smoothing(im, 4096, point_spread=0.6), 6)  # its beam: 0.8
        0.8
        >>> scan_smoothing(im[:1], 4096)  # without it: Scott's rule
        5.0
    """
    sampled = float(sampling_smoothing(measured, n_particles).max())
    beam = smallest_spot(measured, point_spread)
    return min(math.hypot(floor, min(sampled, beam)), MAX_BLUR_PIXELS)


def smallest_spot(measured: Tensor, point_spread: float = 0.0) -> float:
    """The beam's smallest rms spot [pixels] in images ``(K, H, W)``: the
    smallest rms size along x or y, ``point_spread`` [pixels] taken out in
    quadrature (0 where the image is no wider than the point spread)."""
    smallest = float(image_rms_pixels(measured).min())
    return math.sqrt(max(smallest**2 - float(point_spread) ** 2, 0.0))


def loss_smoothing_for(
    config: ReconstructionConfig,
    measured: Sequence[Tensor],
    point_spreads: Sequence[float] | None = None,
) -> list[float]:
    """Loss smoothing [pixels] of each scan: ``config.loss_smoothing``, or with
    ``"auto"`` :func:`scan_smoothing` at ``n_particles`` and the scan's point
    spread (``point_spreads``, one per scan [pixels]; 0 if None), with the
    fixed smoothing of ``config.dims`` as its floor (0 for 4D, 1 pixel for
    6D)."""
    if config.loss_smoothing != "auto":
        return [float(config.loss_smoothing)] * len(measured)
    floor = config.smoothing_floor
    spreads = [0.0] * len(measured) if point_spreads is None else list(point_spreads)
    return [
        scan_smoothing(m, config.n_particles, floor, b)
        for m, b in zip(measured, spreads, strict=True)
    ]


def compared_for(
    config: ReconstructionConfig,
    forwards: list[ScreenForwardModel],
    measured: list[Tensor],
) -> tuple[list[ScreenForwardModel], list[Tensor]]:
    """Forward models and measured images as ``config``'s image term compares
    them: :func:`smoothed_for_loss` by :func:`loss_smoothing_for`, each scan's
    point spread taken from its forward model (``blur_pixels``)."""
    spreads = [f.blur_pixels for f in forwards]
    return smoothed_for_loss(
        forwards, measured, loss_smoothing_for(config, measured, spreads)
    )


#: Loss-smoothing rms per pixel of the compared images: a scan whose smoothing
#: is ``sigma`` camera pixels is compared on pixels ``p = floor(sigma /
#: LOSS_SMOOTHING_PER_PIXEL)`` times larger (sums of ``p x p`` camera pixels),
#: where the Gaussian is still sampled by two pixels per rms; the comparison
#: keeps its resolution and costs ``p^2`` times fewer pixels.
LOSS_SMOOTHING_PER_PIXEL = 2.0


def pool_images(images: Tensor, factor: int) -> tuple[Tensor, tuple[int, int]]:
    """Sums of ``factor x factor`` pixels of images ``(*K, H, W)``.

    The images are padded with zeros to a multiple of ``factor`` (half of the
    padding before, the rest after, per axis). Returns the pooled images
    ``(*K, ceil(H / f), ceil(W / f))`` and the padding before ``(rows,
    columns)``, from which :func:`pooled_screen` places the coarse pixels.

    Example:
        >>> pool_images(torch.ones(1, 4, 5), 2)[0]
        tensor([[[4., 4., 2.],
                 [4., 4., 2.]]])
    """
    f = int(factor)
    h, w = images.shape[-2:]
    ph, pw = (-h) % f, (-w) % f
    before = (ph // 2, pw // 2)
    padded = torch.nn.functional.pad(
        images, (before[1], pw - before[1], before[0], ph - before[0])
    )
    lead = padded.shape[:-2]
    hp, wp = padded.shape[-2:]
    pooled = padded.reshape(*lead, hp // f, f, wp // f, f).sum((-3, -1))
    return pooled, before


def pooled_screen(
    forward: ScreenForwardModel, factor: int, before: tuple[int, int]
) -> tuple[tuple[int, int], tuple[float, float], tuple[float, float]]:
    """Shape, pixel size [m] and centre [m] of ``forward``'s screen pooled by
    ``factor`` with the padding ``before`` of :func:`pool_images`."""
    f = int(factor)
    h, w = forward.screen.shape
    psx, psy = forward.screen.pixel_size
    cx, cy = forward.screen.center
    hc, wc = -(-h // f), -(-w // f)
    shift_y = ((hc * f - h) / 2 - before[0]) * psy
    shift_x = ((wc * f - w) / 2 - before[1]) * psx
    return (hc, wc), (f * psx, f * psy), (cx + shift_x, cy + shift_y)


def smoothed_for_loss(
    forwards: list[ScreenForwardModel],
    measured: list[Tensor],
    sigma_px: float | Sequence[float | Tensor],
) -> tuple[list[ScreenForwardModel], list[Tensor]]:
    """Forward models and measured images both smoothed by ``sigma_px`` camera
    pixels, as the image term compares them: one value for all scans, or per
    scan one value or one ``(x, y)`` pair per image ``(K_s, 2)``.

    A scan whose every image is smoothed by at least ``2
    LOSS_SMOOTHING_PER_PIXEL`` pixels is compared on pooled pixels
    (:func:`pool_images`): the measured images are summed over ``p x p``
    pixels and the simulated ones are deposited on the coarse pixels, with
    point spreads that keep both sides' total variance equal: the camera's own
    (``blur_pixels``), the pooling's ``(p^2 - 1) / 12`` and the smoothing's
    ``sigma^2`` [camera pixels^2].
    """
    per_scan = (
        [float(sigma_px)] * len(forwards)
        if isinstance(sigma_px, int | float)
        else list(sigma_px)
    )
    out_f, out_m = [], []
    for f, m, sigma in zip(forwards, measured, per_scan, strict=True):
        s = torch.as_tensor(sigma, dtype=torch.float64).cpu()
        s = s.reshape(-1, 1).expand(m.shape[0], 2) if s.dim() < 2 else s
        if not bool((s > 0).any()):
            out_f.append(f)
            out_m.append(m)
            continue
        p = max(1, int(float(s.min()) // LOSS_SMOOTHING_PER_PIXEL))
        beamline = f.beamline
        if p > 1:
            m, before = pool_images(m, p)
            shape, pixel, center = pooled_screen(f, p, before)
            beamline = beamline.with_screen(f.screen.name, shape, pixel, center)
        base = math.sqrt(f.blur_pixels**2 + (p * p - 1) / 12.0) / p
        out_f.append(
            ScreenForwardModel(
                beamline,
                f.names,
                f.p0c,
                species=f.species,
                blur_pixels=min(base, MAX_BLUR_PIXELS),
                image_smoothing=s / p,
            )
        )
        fine = torch.tensor(f.screen.pixel_size, dtype=torch.float64)
        coarse = tuple(float(v) * p for v in f.screen.pixel_size)
        blurred = gaussian_blur(m, (s * fine).to(m.device), coarse)
        # not renormalised: mass blurred off the screen is lost on both sides
        out_m.append(blurred)
    return out_f, out_m


#: Steps between updates of the prior point of the ``unseen_weight`` term
#: (:class:`~diffaccel.reconstruction.unseen.UnseenHold`).
HOLD_EVERY = 10


def _host_reads_cheap(device: torch.device) -> bool:
    """Whether reading a value back from ``device`` costs no synchronisation."""
    return device.type == "cpu"


def _per_scan(
    forward: ScreenForwardModel | Sequence[ScreenForwardModel],
    measured: Tensor | Sequence[Tensor],
    settings: Tensor | Sequence[Tensor],
) -> tuple[list[ScreenForwardModel], list[Tensor], list[Tensor]]:
    """Forward models, measured images and settings as one list entry per scan.

    Raises:
        ValueError: if the numbers of forward models, image stacks and settings
            differ (or are 0).
    """
    forwards, images, sets = _as_list(forward), _as_list(measured), _as_list(settings)
    if not (len(forwards) == len(images) == len(sets) >= 1):
        raise ValueError(
            f"need one forward model, image stack and settings tensor per scan; got "
            f"{len(forwards)}, {len(images)} and {len(sets)}."
        )
    return forwards, images, sets


def _new_generator(
    guess: GaussianGuess,
    config: ReconstructionConfig,
    device: torch.device,
    shard: tuple[int, int],
) -> tuple[BeamGenerator, FlatGenerator, torch.Generator, tuple[Tensor, ...]]:
    """The generator at the Gaussian ``guess``, its flat form and the entropy's
    scales.

    Args:
        guess: Gaussian fitted to the image moments.
        config: Training settings (``dims``, network size, ``seed``).
        device: Device to train on.
        shard: ``(rank, world)``: this process's share of the particles.

    Returns:
        The :class:`BeamGenerator` (weights from ``config.seed``), its
        :class:`FlatGenerator` drawing this process's share of
        ``n_particles`` (Sobol points; the processes draw blocks of one
        sequence), the random generator of their digital shifts and, float64
        on ``device``, the coordinate scales ``(D,)`` [Bmad units], the
        prior's mean and rms ``(D,)`` [Bmad units].
    """
    dims = config.dims
    rng = torch.Generator(device=device).manual_seed(config.seed)
    scale, offset, corr, prior = guess.generator_init(dims, config.longitudinal_scale)
    model = BeamGenerator(
        dims,
        width=config.width,
        depth=config.depth,
        scale=scale.float(),
        offset=offset.float(),
        correlation=corr,
        generator=torch.Generator().manual_seed(config.seed),
    ).to(device)
    net = FlatGenerator(model, config.n_particles, quasi_random=True, shard=shard)
    scales = tuple(
        t.to(device=device, dtype=torch.float64) for t in (scale, offset, prior)
    )
    return model, net, rng, scales


def _loss_terms(
    config: ReconstructionConfig,
    forwards: Sequence[ScreenForwardModel],
    measured: Sequence[Tensor],
    scales: tuple[Tensor, ...],
    distributed: bool,
) -> tuple[list[Callable[[Tensor], Tensor]], RelativeEntropy]:
    """Each scan's image term and the entropy term of the loss.

    Every image of every scan weighs the same (each scan's
    :class:`ImagePenalty` is its share of the mean image distance ``D``),
    each with the KL offset against the sampling noise of ``n_particles``'
    images (its scan's point spread sets the noise). ``H - C`` is the
    :class:`RelativeEntropy` of ``n_particles`` with the coordinate scales and
    the prior of ``scales`` (from :func:`_new_generator`), its moments summed
    over processes when ``distributed``.
    """
    n = config.n_particles
    n_images = sum(m.shape[0] for m in measured)
    penalties: list[Callable[[Tensor], Tensor]] = [
        ImagePenalty(
            m,
            "kl",
            off_screen_allowance(m),
            1.0 / n_images,
            offset=_kl_offset(config.sampling_offset, f, n),
        )
        for f, m in zip(forwards, measured, strict=True)
    ]
    if config.moment_weight > 0:
        penalties = [
            _WithMoments(p, _moment_match(m, config.moment_weight / n_images))
            for p, m in zip(penalties, measured, strict=True)
        ]
    norm, prior_mean, prior_std = scales
    relative_entropy = RelativeEntropy(
        n,
        norm,
        prior_mean,
        prior_std,
        reduce=tdist.all_reduce if distributed else None,
    )
    return penalties, relative_entropy


def _moment_match(measured: Tensor, weight: float) -> MomentMatch:
    """The moment term of one scan's images, in a box of ``MOMENT_WINDOW`` rms
    of each measured image around its centroid."""
    h, w = measured.shape[-2:]
    xs = torch.arange(w, dtype=torch.float64)
    ys = torch.arange(h, dtype=torch.float64)
    window = moment_window(measured.detach().cpu(), xs, ys, MOMENT_WINDOW)
    return MomentMatch(measured, window.to(measured.device), weight)


class _WithMoments:
    """A scan's image term: the image distance plus its moment term."""

    def __init__(self, penalty: ImagePenalty, moments: MomentMatch) -> None:
        self.penalty, self.moments = penalty, moments

    def __call__(self, simulated: Tensor) -> Tensor:
        return self.penalty(simulated) + self.moments(simulated)


def _beam_hold(
    config: ReconstructionConfig,
    forwards: Sequence[ScreenForwardModel],
    settings: Sequence[Tensor],
    maps: Sequence[Tensor] | None,
    norm: Tensor,
) -> MomentHold | None:
    """The prior term on the unseen directions (6D), or None.

    With ``dims = 6`` and ``unseen_weight > 0`` an
    :class:`~diffaccel.reconstruction.unseen.UnseenHold` on the directions the
    scans do not see (from each scan's transfer maps, ``maps`` where given).
    """
    n = config.n_particles
    if not (config.dims == 6 and config.unseen_weight > 0):
        return None
    map_list = [None] * len(forwards) if maps is None else list(maps)
    return UnseenHold(
        [
            (f.transfer_maps(s) if r is None else r).cpu()
            for f, s, r in zip(forwards, settings, map_list, strict=True)
        ],
        config.unseen_weight,
        norm,
        n,
    )


class _StepLoss:
    """Gradient of one training step's loss with respect to the flat parameters.

    The loss ``lam D - (H - C)`` (less a hold's surrogate) of one fresh sample
    of the generator: ``D`` the mean image distance over every image of every
    scan, ``H - C`` the relative entropy of the sample. Called as
    :data:`~diffaccel.reconstruction.graphed_step.Gradient`.

    Args:
        net: Flat generator (its share of the particles per sample).
        images: Every scan's simulated images of a sample.
        penalties: Each scan's image term (its share of ``D``).
        relative_entropy: The ``H - C`` term.
        hold: Quadratic hold on the covariance, or None.
        state: The run's state: its step (in error messages) and the hold's
            prior point (``hold_moments``, set at the first step).
        device: Device of the training; off CPUs the particle checks are off
            (they read the device; a non-finite loss still stops training).
        distributed: Sum the simulated images over processes.
    """

    def __init__(
        self,
        net: FlatGenerator,
        images: ScanImages,
        penalties: Sequence[Callable[[Tensor], Tensor]],
        relative_entropy: RelativeEntropy,
        hold: MomentHold | None,
        state: TrainingState,
        device: torch.device,
        distributed: bool,
    ) -> None:
        self.net, self.images, self.penalties = net, images, penalties
        self.relative_entropy, self.hold, self.state = relative_entropy, hold, state
        self.distributed = distributed
        self.checks_on = _host_reads_cheap(device)

    def __call__(
        self, lam: float | Tensor, rng: torch.Generator
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor | None]:
        """The step's gradient, image penalty, H - C, moments and the hold's
        moments (None without a hold) at penalty weight ``lam``."""
        x = self.net.sample(rng)  # (N, dims)
        dist = None
        with finite_checks(self.checks_on):  # off on GPUs: no device reads
            try:
                sims = self.images(x)
            except ValueError as err:  # the particle checks: which particles?
                if bool(torch.isfinite(x).all()):
                    raise
                raise FloatingPointError(
                    f"training diverged at step {self.state.step}: the generator "
                    "produced non-finite particles. Use more particles "
                    "(n_particles) or a lower learning rate (lr_max)."
                ) from err
        for sim, penalty in zip(sims, self.penalties, strict=True):
            if self.distributed:
                sim = _SumOverProcesses.apply(sim)
            d = penalty(sim)  # this scan's share of the mean image penalty D
            dist = d if dist is None else dist + d
        rel, moments = self.relative_entropy(x)  # H - C; plain moments
        if isinstance(lam, Tensor):  # a captured step's device scalar
            objective = rel - lam * dist
        else:
            objective = torch.sub(rel, dist, alpha=lam)
        held, hold = None, self.hold
        if hold is not None:  # the hold's gradient
            held = held_moments(moments)
            if not hold.ready:  # its prior point: the checkpoint's or this
                if self.state.hold_moments is None:  # sample's, then every
                    self.state.hold_moments = held.cpu()  # HOLD_EVERY steps
                hold.update(self.state.hold_moments)  # (refresh_hold)
            objective = objective - hold.surrogate(x, held)
        # loss lam D - (H - C): the gradient of (H - C) - lam D, negated. One
        # scalar with the implicit seed: explicit seed tensors made
        # torch.autograd import torch.fx.experimental.symbolic_shapes and
        # sympy, ~0.5 s of a default ``reconstruct`` (of the whole
        # process); sub(alpha=) costs fewer ATen ops than lam * D - (H - C)
        (grad,) = torch.autograd.grad(objective, [self.net.flat])
        grad.neg_()
        return grad, dist, rel, moments, held

    def refresh_hold(self, done: int, held: Tensor | None) -> None:
        """Move the hold's prior point to the moments ``held`` of the latest
        beam after every :data:`HOLD_EVERY` of the ``done`` steps (a host
        read; with the default ``report_every`` it coincides with the losses'
        read)."""
        hold = self.hold
        if hold is not None and done % HOLD_EVERY == 0:
            self.state.hold_moments = held.cpu()
            hold.update(self.state.hold_moments)


class _StepRecord:
    """Per-step values kept on the device until the host reads them.

    Each step copies its image penalty, ``H - C`` and the plain moments of the
    entropy into one row of a ``(rows, 2 + (dims + 1)^2)`` float64 device
    buffer (:meth:`slot`); :meth:`read` transfers the rows of the steps not
    read yet at once (one host transfer) and derives each step's loss,
    entropy and rms sizes for the history.

    Args:
        rows: Steps held at most between reads (``report_every``).
        dims: Generator dimensions.
        device: Device of the training.
        relative_entropy: The entropy term (derives ``H`` and the rms sizes).
    """

    def __init__(
        self,
        rows: int,
        dims: int,
        device: torch.device,
        relative_entropy: RelativeEntropy,
    ) -> None:
        self.record = torch.zeros(
            rows, 2 + (dims + 1) ** 2, dtype=torch.float64, device=device
        )
        self.slots = [  # views made once (every view is an ATen op of the step)
            (r[0], r[1], r[2:].view(dims + 1, dims + 1)) for r in self.record.unbind(0)
        ]
        self.pending: list[tuple[int, float, float]] = []  # (step, lr, penalty)
        self.relative_entropy = relative_entropy

    def slot(self) -> tuple[Tensor, Tensor, Tensor]:
        """Views ``()``, ``()``, ``(dims + 1, dims + 1)`` for the next step."""
        return self.slots[len(self.pending)]

    def add(self, step: int, lr: float, lam: float) -> None:
        """Note that step ``step`` (learning rate ``lr``, penalty weight
        ``lam``) has filled its slot."""
        self.pending.append((step, lr, lam))

    def read(self, history: dict[str, list], model: BeamGenerator) -> None:
        """Append the loss, image loss, entropy, learning rate, penalty weight
        and rms sizes of every step not read yet to ``history``.

        Raises:
            FloatingPointError: if a step's loss is not finite (with
                non-finite weights of ``model``: training diverged).
        """
        rows = self.record[: len(self.pending)].tolist()  # the host read
        for (s, lr_s, lam_s), row in zip(self.pending, rows, strict=True):
            dist_s, rel_s = row[0], row[1]
            loss_s = (dist_s - rel_s / lam_s) * lam_s  # lam D - (H - C)
            if not math.isfinite(loss_s):
                if not all(bool(p.isfinite().all()) for p in model.parameters()):
                    raise FloatingPointError(
                        f"training diverged at step {s}: loss {loss_s} and "
                        "non-finite generator weights. Use more particles "
                        "(n_particles) or a lower learning rate (lr_max)."
                    )
                raise FloatingPointError(
                    f"loss became {loss_s} at step {s}; the beam may have left "
                    "the screen entirely. Check the screen calibration and settings."
                )
            entropy, rms = self.relative_entropy.entropy_and_rms(rel_s, row[2:])
            history["loss"].append(loss_s)
            history["image_loss"].append(dist_s)
            history["entropy"].append(entropy)
            history["lr"].append(lr_s)
            history["penalty"].append(lam_s)
            history["rms"].append(rms)
        self.pending.clear()


def _take_member(state: TrainingState, model: BeamGenerator) -> None:
    """Keep the generator's weights (CPU) as the next ensemble member."""
    state.snapshots.append(_cpu_state(model.state_dict()))
    state.history["snapshot_steps"].append(state.step)


def _step_info(
    state: TrainingState, total: int, lr: float, lam: float, snapshot: bool
) -> StepInfo:
    """The callback's report of the latest step (its learning rate ``lr`` and
    penalty weight ``lam``) of ``total``."""
    hist = state.history
    return StepInfo(
        step=state.step,
        total=total,
        loss=hist["loss"][-1],
        image_loss=hist["image_loss"][-1],
        entropy=hist["entropy"][-1],
        lr=lr,
        penalty=lam,
        snapshot_taken=snapshot,
    )


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
    distributed: bool = False,
    maps: Sequence[Tensor] | None = None,
    initial_model: dict | None = None,
    checkpoint_every: int = CHECKPOINT_EVERY,
    report_every: int = REPORT_EVERY,
    cuda_graph: bool = True,
) -> TrainingState:
    """Fit a :class:`BeamGenerator` to screen images and collect snapshot members.

    Minimises ``-(H - C) + lambda(t) [D + moment term] + w sum_j t_j^2``
    (docs/methods/reconstruction_6d.md): ``H`` the tail-robust Gaussian entropy
    bound of the generated particles, ``C`` the cross-entropy of a broad
    Gaussian prior, ``D`` the mean image distance over the images of all scans
    (:class:`~diffaccel.reconstruction.losses.ImagePenalty`; the simulated
    images unnormalised, so beam off the screen costs), the moment term of
    ``config.moment_weight``, and in 6D the prior term of
    ``config.unseen_weight`` on the directions the scans cannot see, over
    ``n_particles`` fresh particles per step. Adam, cosine learning-rate cycles:
    the generator at the end of each cycle after the burn-in is one member.

    Args:
        forward: Screen forward model of each scan (tracking + imaging); a single
            model for a single scan.
        measured: Sum-normalised measured images of each scan (float32).
        settings: Scan settings of those images, one tensor per scan.
        guess: Gaussian fitted to the image moments (initialises the generator).
        config: Training settings.
        checkpoint: File for atomic checkpoints; None disables them.
        resume: Continue from ``checkpoint`` if it exists.
        callback: Called with a :class:`StepInfo` every ``report_every`` steps
            (and at snapshots, checkpoints and the end); an exception raised
            there stops training (the last checkpoint stays valid).
        device: Device to train on; default that of the first ``measured``.
        distributed: Split every step's particles across the processes of the
            initialised ``torch.distributed`` group (gloo on CPUs, NCCL on GPUs):
            images, entropy moments and gradients are all-reduced, so every
            process takes the same step, equal to a single-process run up to the
            rounding of the sums (docs/distributed.md). Process 0 checkpoints.
        maps: Each scan's :meth:`ScreenForwardModel.transfer_maps` of its
            settings when the caller has computed them.
        initial_model: Generator state dict to start from instead of the
            Gaussian ``guess`` (which still sets the entropy's prior).
        checkpoint_every: Steps between checkpoints (also at every snapshot).
        report_every: Steps between reads of the losses from the device (the
            only host synchronisation of training; the callback runs then).
            Does not change the result.
        cuda_graph: On a CUDA device, capture the step as a CUDA graph after a
            few eager steps and replay it (:mod:`~diffaccel.reconstruction.
            graphed_step`, docs/gpu.md; 4D, not ``distributed``); where the
            capture fails the run goes on eagerly with a warning. Ignored on
            CPUs; does not change the result beyond rounding.

    Shapes:
        Scan ``s``: ``measured (K_s, H_s, W_s)``, ``settings (K_s, P_s)``.

    Returns:
        The final :class:`TrainingState` (``snapshots`` holds one CPU state dict
        per cycle, ``history`` the per-step curves).

    Raises:
        ValueError: if the numbers of forward models, image stacks and settings
            differ, or for a ``checkpoint_every`` or ``report_every`` below 1.
    """
    for name, every in (
        ("checkpoint_every", checkpoint_every),
        ("report_every", report_every),
    ):
        if not (is_integer(every) and every >= 1):
            raise ValueError(f"{name} must be an integer >= 1; got {every!r}.")
    forwards, measured_list, settings_list = _per_scan(forward, measured, settings)
    fingerprint = data_fingerprint(forwards, measured_list, settings_list)
    device = torch.device(device) if device is not None else measured_list[0].device
    measured_list = [m.to(device=device, dtype=torch.float32) for m in measured_list]
    settings_list = [s.to(device=device) for s in settings_list]
    forwards, measured_list = compared_for(config, forwards, measured_list)
    forwards = [f.to(device) for f in forwards]
    n, dims, total = config.n_particles, config.dims, config.steps
    rank, world = (tdist.get_rank(), tdist.get_world_size()) if distributed else (0, 1)
    model, net, gen_rng, scales = _new_generator(guess, config, device, (rank, world))
    opt = FlatAdam(net.flat)
    state = TrainingState(history=_new_history(), fingerprint=fingerprint)
    ckpt = Path(checkpoint) if checkpoint is not None else None
    if initial_model is not None:
        model.load_state_dict(initial_model)  # copies into net.flat
    if resume and ckpt is not None and ckpt.exists():
        state = _resumed(ckpt, fingerprint, model, opt, gen_rng)
    if distributed and rank != 0:
        ckpt = None  # process 0 writes the checkpoints
    images = ScanImages(
        forwards, settings_list, maps, dims, net.n, device, n if world > 1 else None
    )
    penalties, entropy = _loss_terms(
        config, forwards, measured_list, scales, distributed
    )
    hold = _beam_hold(config, forwards, settings_list, maps, norm=scales[0])
    loss = _StepLoss(net, images, penalties, entropy, hold, state, device, distributed)
    schedule = config.schedule
    capture = cuda_graph and not distributed
    reduce = tdist.all_reduce if distributed else None
    steps = TrainingSteps(
        loss,
        opt,
        schedule,
        gen_rng,
        state.step,
        total,
        dims,
        device,
        capture,
        reduce,
        hold=hold,
    )
    # per-step values stay on the device, read every report_every steps, at
    # cycle ends, checkpoints and the end
    record = _StepRecord(report_every, dims, device, entropy)
    t0 = time.perf_counter() - state.elapsed_s
    while state.step < total:
        step = state.step
        lr, lam = schedule.lr(step), schedule.penalty(step)
        held = steps(step, lr, lam, record.slot())
        record.add(step, lr, lam)
        state.step = step + 1
        loss.refresh_hold(state.step, held)
        cycle_end = schedule.cycle_end(state.step)
        member = schedule.member(state.step)
        save = ckpt is not None and (cycle_end or state.step % checkpoint_every == 0)
        report = state.step % report_every == 0 or state.step == total
        if not (report or cycle_end or save):
            continue
        record.read(state.history, model)
        if member:
            _take_member(state, model)
        if save:
            _checkpoint(state, config, ckpt, model, opt, steps.rng, t0)
        if callback is not None:
            callback(_step_info(state, total, lr, lam, member))
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
        "fingerprint": state.fingerprint,
        "hold_moments": state.hold_moments,
    }
    atomic_write(path, lambda p: torch.save(payload, p))


def load_tensors(path: str | os.PathLike, what: str) -> object:
    """``torch.load(path, weights_only=True)`` with a one-line error.

    Raises:
        ValueError: ``cannot read {what} {path}: ...`` for a corrupt, empty or
            foreign file (torch raises several types, with multi-line messages).
    """
    try:
        with warnings.catch_warnings():  # torch's pickle-protocol notice
            warnings.simplefilter("ignore", UserWarning)
            return torch.load(Path(path), weights_only=True, map_location="cpu")
    except Exception as exc:  # corrupt or foreign file
        damaged = "not written by diffaccel, or damaged since"
        if isinstance(exc, pickle.UnpicklingError):
            # torch's text invites weights_only=False (arbitrary code): never
            reason = f"not a tensor file that is safe to load ({damaged})"
        elif isinstance(exc, EOFError) or not str(exc).strip():
            reason = f"empty or truncated file ({damaged})"
        elif "zip archive" in str(exc):
            reason = f"not a readable torch archive ({damaged})"
        elif isinstance(exc, FileNotFoundError | IsADirectoryError | PermissionError):
            reason = exc.strerror or type(exc).__name__
        elif isinstance(exc, OSError):  # e.g. EINVAL seeking in a cut file
            reason = f"unreadable file: {exc.strerror} ({damaged})"
        else:
            reason = f"{type(exc).__name__}: {str(exc).strip().splitlines()[0]}"
        raise ValueError(f"cannot read {what} {path}: {reason}") from exc


def _read_checkpoint(path: str | os.PathLike) -> dict:
    d = load_tensors(path, "checkpoint")
    if not isinstance(d, dict) or d.get("checkpoint_version") != CHECKPOINT_VERSION:
        raise ValueError(f"{path} is not a diffaccel reconstruction checkpoint.")
    return d


def load_checkpoint(path: str | os.PathLike) -> TrainingState:
    """Read a checkpoint written by :func:`save_checkpoint` (``weights_only``).

    Raises:
        ValueError: if the file is not a complete diffaccel training checkpoint.
    """
    d = _read_checkpoint(path)
    try:
        return TrainingState(
            step=int(d["step"]),
            model=dict(d["model"]),
            optimizer=dict(d["optimizer"]),
            rng=d["rng"],
            snapshots=list(d["snapshots"]),
            history={k: list(v) for k, v in d["history"].items()},
            elapsed_s=float(d["elapsed_s"]),
            fingerprint=str(d.get("fingerprint", "")),
            hold_moments=d.get("hold_moments"),
        )
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise ValueError(
            f"{path} is a damaged checkpoint ({type(exc).__name__}: {exc})."
        ) from exc


def _resumed(
    path: Path,
    fingerprint: str,
    model: BeamGenerator,
    opt: FlatAdam,
    rng: torch.Generator,
) -> TrainingState:
    """The state of the checkpoint at ``path``, its generator weights,
    optimiser state and random state loaded into ``model``, ``opt`` and
    ``rng``.

    Raises:
        CheckpointDataError: if the checkpoint was written for other training
            data (its :func:`data_fingerprint` is not ``fingerprint``).
        ValueError: if it is not a complete checkpoint or its generator lacks
            parameters of ``model``.
    """
    state = load_checkpoint(path)
    if state.fingerprint != fingerprint:
        raise CheckpointDataError(
            f"checkpoint {path} was written for other training data (another "
            "file, other training settings or another screen calibration); "
            "resume with the same data, or start a new run."
        )
    missing = sorted(set(model.state_dict()) - set(state.model))
    if missing:  # e.g. a 6D run checkpointed before the quadratic term
        raise ValueError(
            f"checkpoint {path} was written by an earlier diffaccel: its "
            f"generator lacks {missing}, so its optimiser state does not fit; "
            "start a new run."
        )
    model.load_state_dict(state.model)  # copies into the flat parameters
    opt.load_state_dict(state.optimizer)
    rng.set_state(state.rng)
    logger.info("resumed from %s at step %d", path, state.step)
    return state


def _checkpoint(
    state: TrainingState,
    config: ReconstructionConfig,
    path: Path,
    model: BeamGenerator,
    opt: FlatAdam,
    rng: torch.Generator,
    t0: float,
) -> None:
    """Store the generator, optimiser and random state in ``state`` and write
    it to ``path`` (:func:`save_checkpoint`); ``t0`` is the run's start on
    :func:`time.perf_counter`'s clock (earlier by the time of the steps
    before a resume)."""
    state.model = _cpu_state(model.state_dict())
    state.optimizer = opt.state_dict()
    state.rng = rng.get_state()
    state.elapsed_s = time.perf_counter() - t0
    save_checkpoint(state, config, path)


def checkpoint_config(path: str | os.PathLike) -> ReconstructionConfig:
    """The :class:`ReconstructionConfig` stored in a checkpoint.

    Raises:
        ValueError: if the file is not a checkpoint or its config is damaged.
    """
    d = _read_checkpoint(path)
    try:
        return ReconstructionConfig.from_dict(d["config"])
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise ValueError(
            f"{path}: damaged config ({type(exc).__name__}: {exc})."
        ) from exc
