"""Settings of a phase-space reconstruction: the model, the schedule, the image
term and the prior (:class:`ReconstructionConfig`).

Runtime choices that do not change the result (device, checkpoints, how often
the losses are read, CUDA graphs) are arguments of
:func:`~diffaccel.reconstruction.training.train_generator` and
:func:`~diffaccel.reconstruction.pipeline.reconstruct`, not settings.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from typing import Literal

from diffaccel.dynamics import is_integer, is_real
from diffaccel.reconstruction.forward import MAX_BLUR_PIXELS
from diffaccel.reconstruction.losses import StepSchedule

#: Learning rate at the end of each cycle, in units of ``lr_max``.
LR_END_RATIO = 1e-2
#: Image-penalty weight ``lambda`` at step 0 (it rises to ``penalty_end`` over
#: the first cycle, so that the entropy first shapes a smooth beam).
PENALTY_START = 10.0

#: The groups of :class:`ReconstructionConfig`'s fields, in the order of its
#: docstring.
GROUPS = ("model", "schedule", "image term", "prior")


@dataclass(frozen=True)
class _DimsDefaults:
    """Defaults of :class:`ReconstructionConfig` that depend on ``dims``."""

    n_particles: int
    width: int
    depth: int
    steps: int
    snapshots: int
    blur_pixels: float
    loss_smoothing: float
    burn_in: int
    sampling_offset: float
    penalty_end: float
    unseen_weight: float
    moment_weight: float
    smoothing: float | Literal["auto"]  # loss_smoothing when None ("auto": by the data)


#: 4D: where held-out settings of synthetic camera scans put them
#: (``benchmarks/validate_defaults.py``, one setting at a time, seeds 0, 1),
#: checked on the GPSR 4D benchmark (KDE images of one-pixel bandwidth) and on
#: ``benchmarks/camera_4d.py``. At the defaults the held-out rms error is
#: 0.19 % (relative L1 0.150). The validation keeps width 96, depth 3, 6144
#: particles and moment_weight 3 against their neighbours (width 48 / 128:
#: 0.63 / 0.30 %, depth 2 / 4: 0.19 % with an L1 13 % higher / 0.33 %, 3072 /
#: 12288 particles: 0.20 / 0.25 %, moment_weight 1 / 10: 0.37 % / 0.17 % with
#: an L1 23 % higher). Known limits: it prefers 2400 steps, whose held-out
#: images fit 7 % better (L1 0.140) at a worse rms error (0.29 %) and twice
#: the time, and penalty_end 3e4 (0.175 %, within the seeds' scatter).
#: 6D: set on the shared 6D *training* file (its ground truth) and on
#: synthetic AWA 6D beams of other shapes; see ``ReconstructionConfig``. On the
#: held-out scans of two fresh beams of those families
#: (``benchmarks/validate_defaults.py``, seeds 0, 1) the defaults of
#: penalty_end, n_particles, steps, loss_smoothing and moment_weight give a
#: held-out rms-size error of 0.20 %; their neighbours one step down and up
#: give 0.19-0.21 %, except 180 steps and a loss smoothing of 0.5 pixel
#: (0.23 % each, the latter with a held-out L1 3 % higher): the held-out
#: images barely tell the others apart (8192 or 32768 particles, 720 steps:
#: 0.19 % at twice the time), and they cannot tell the unseen-direction
#: prior's strength at all.
#: Scans with a deflecting cavity and a dipole image small spots (down to ~1
#: pixel at a waist), so the point spread sets the emittance: the default
#: assumes images that are histograms of particle positions (nearest-pixel
#: deposition, variance 1/12 pixel^2), reproduced exactly in training through
#: the 1-pixel loss smoothing (see ``loss_smoothing``), which also keeps the KL
#: distance unbiased for sparse simulated images. Measured on a validation
#: split of the shared 6D training file (k1 = -6, 6 held out): blur 1.0 without
#: smoothing left rms sizes ~10 % large; blur 0.5 with smoothing gave rms
#: within 3 % but each member's y emittance 27-32 % low (a 0.35 mm waist is
#: 1.3 pixels); sqrt(1/12) gave members within -3 ... -10 %. The first member
#: (end of the first cycle, which ramps the image penalty) was under-fit in 6D
#: (y emittance +85 %, 6D emittance +188 %), hence ``burn_in >= 1``.
_DIMS_DEFAULTS: dict[int, _DimsDefaults] = {
    4: _DimsDefaults(6144, 96, 3, 1200, 5, 1.0, 0.0, 0, 0.0, 1e4, 0.0, 3.0, "auto"),
    6: _DimsDefaults(
        16384, 48, 2, 360, 6, math.sqrt(1.0 / 12.0), 1.0, 3, 0.25, 3e4, 1e3, 1.0, 1.0
    ),
}

#: Lower ends of the measured training memory (see ReconstructionConfig.memory_bytes).
_BYTES_PER_PARTICLE = 1536
_BYTES_PER_PARTICLE_IMAGE_6D = 512


def _group(name: str) -> dict[str, str]:
    return {"group": name}


@dataclass(frozen=True)
class ReconstructionConfig:
    """Settings of a phase-space reconstruction (everything but the data).

    The reconstruction minimises, over the generator weights,
    ``-(H - C) + lambda(t) [D_KL + moment term] + unseen_weight sum_j t_j^2``
    (docs/methods/reconstruction_6d.md). The fields come in four groups
    (:data:`GROUPS`, :meth:`groups`). A default 4D reconstruction of the
    GPSR 4D benchmark (10 training settings, 100 x 100 pixels; 6144 fresh
    quasi-random particles x 1200 steps, MLP 3 x 96) takes ~15 s on two CPU
    cores (``benchmarks/reconstruction.py``) and gives rms sizes within 0.4 %,
    emittances within 0.3 % (seeds 0-2) and held-out relative L1 0.053 (seed
    0; gpsr: 0.117).

    **Model** (the beam generator):

    Args:
        dims: 4 reconstructs (x, px, y, py) with ``z = pz = 0``; 6 also generates
            (z, pz), which a quad scan barely constrains (they stay near their prior).
        n_particles: Fresh particles drawn at every step (Sobol points with a
            new random digital shift). None: 6144 for ``dims = 4``, 16384 for
            ``dims = 6``. The image distance of a finite sample is a biased
            estimate, and in 6D the bias lands on the smallest-eigenvalue
            quantities: on the shared 6D training file (truth known) the y
            emittance (y-py correlation 0.98) came out -5 to -8 % with 6144
            particles (three seeds), -1.5 % with 12288 and +1.5 to +1.7 % with
            16384 (two seeds each); at the true beam the same loss is minimal
            at the true y emittance.
        width: MLP hidden width. None: 96 for ``dims = 4``, 48 for ``dims =
            6``.
        depth: MLP hidden layers. None: 3 for ``dims = 4``, 2 for ``dims =
            6``. The generator must be able to take the beam's tails: on the
            held-out settings of ``benchmarks/validate_defaults.py`` (4D,
            three beams, seeds 0-3) 2 x 48 gave held-out rms errors of 0.64 /
            0.79 % (seeds 0, 1 / 2, 3) and relative L1 0.157 / 0.164, 3 x 96
            0.37 / 0.37 % and 0.145 / 0.147, 3 x 128 0.47 / 0.45 % and 0.146 /
            0.142; on a 360 x 320 pixel scan whose smallest spot is 2 pixels
            rms (21 settings, 11 trained, a 12 % halo) 2 x 48 left the y
            emittance 12-14 % low (seeds 0, 1), 3 x 96 5.6-7.2 % (seeds 0, 1)
            and 3 x 128 2-5 % (seeds 0-2), all with ``moment_weight`` 1 (the
            benchmark ``benchmarks/camera_4d.py`` is that scan). The 4D step
            costs about twice the time of 2 x 48 on 100 x 100 pixel images and
            little more on camera images. 6D keeps 2 x 48, where its
            benchmarks were validated.

    **Schedule** (Adam with a cyclic cosine learning rate, one ensemble member
    per cycle; the learning rate falls to ``LR_END_RATIO lr_max`` at the end
    of each cycle and ``lambda`` rises from ``PENALTY_START`` to
    ``penalty_end`` over the first one):

    Args:
        steps: Total optimisation steps (one step sees every training image).
            None: 1200 for ``dims = 4``, 360 for ``dims = 6``. 4D: on held-out
            settings of three synthetic camera scans (320 x 320 pixels, seeds
            0, 1; ``benchmarks/validate_defaults.py``, ``moment_weight`` 1)
            the held-out rms sizes were off by 0.64 % on average with 1200
            steps, 0.84 % with 600, 1.53 % with 300 and 0.42 % with 2400, the
            held-out images fitting better with every doubling (relative L1
            0.157, 0.175, 0.210, 0.152); a three-mode beam with curvature is
            not converged at 600 (its held-out L1 0.13 against 0.095 at 1200).
            At the 4D defaults (3 x 96, ``moment_weight`` 3) 600, 1200
            and 2400 steps give 0.49, 0.19 and 0.29 % (L1 0.170, 0.150,
            0.140): 2400 fits the held-out images 7 % better at twice the
            time and a larger rms error.
            Without the moment term (``moment_weight = 0``) 600 steps took the
            GPSR 4D benchmark's x emittance, a 0.6-pixel waist behind a
            1-pixel point spread, to -6.4 % (seed 0); with it (1200 steps),
            -1.3 / -0.9 / -0.7 % (seeds 0-2).
        snapshots: Cosine learning-rate cycles; one ensemble member per cycle
            after the ``burn_in``. None: 5 for ``dims = 4``, 6 for ``dims = 6``
            (240- and 60-step cycles). The 6D emittance converges over cycles
            (shared 6D training file, 16384 particles: the members of cycles 3
            to 6 had +26, +18, +8 and +5 %), so 6D keeps the last three.
        burn_in: Cycles whose end is not kept as an ensemble member (the first
            cycle ramps the image penalty). None: 0 for ``dims = 4``, 3 for
            ``dims = 6`` (at most ``snapshots - 1``); the ensemble has
            ``snapshots - burn_in`` members.
        lr_max: Learning rate at the start of each cycle.
        seed: Seed of the explicit ``torch.Generator`` (weights and samples).

    **Image term** (``lambda [D + moment term]``, ``D`` the KL distance of the
    sum-normalised simulated images from the measured ones: the images'
    Poisson log-likelihood up to a constant, minimised by the mean of their
    shot noise; an L1 distance is minimised by its pixel-wise median, below
    the mean in the sparse tails, and gave rms sizes 2-4 % low on the GPSR
    benchmark where KL gave sizes within ~1.5 %. The distance carries an
    offset against the sampling noise of the simulated images,
    :attr:`sampling_offset`):

    Args:
        penalty_end: Weight ``lambda`` of the image term from the end of the
            first cycle on. The entropy term has gradient 1 per unit ``log
            sigma`` of each coordinate, so at weight ``lambda`` it can move a
            size until the image mismatch rises by ~``1 / lambda`` per unit
            ``log sigma``. At 1e3 that still inflated the x emittance of the
            GPSR benchmark by 7-12 % (its x waist is 0.6 pixel rms); at 1e4 the
            final images match to within their noise and the emittances came
            out within 0-4 % (three seeds), while coordinates the images do not
            see are still set by the entropy. None: 1e4 for ``dims = 4``, 3e4
            for ``dims = 6``: 1e4 left the shared 6D file's y emittance (y-py
            0.98) at +4.5 / +7.0 / +5.3 % (seeds 0-2), 3e4 at +1.8 / +3.2 /
            +2.9 %.
        blur_pixels: Total point-spread rms of the simulated images [pixels],
            cloud-in-cell deposition (1/6 pixel^2 of variance) included; 1
            matches screens with a ~1 pixel resolution and the 1-pixel KDE of the
            GPSR benchmark. None (default): each scan's recorded screen
            resolution (``QuadScanDataset.resolution_pixels``, the file's
            ``screen.resolution_pixels``) where the file has one, else 1.0 for
            ``dims = 4`` and sqrt(1/12) ~ 0.29 (images that are histograms, no
            point spread) for ``dims = 6``; see :meth:`blur_for`.
        loss_smoothing: Rms [pixels] of a Gaussian applied to both the measured
            and the simulated images before they are compared (the simulated
            ones get it on top of ``blur_pixels``), or ``"auto"``: sized per scan
            by the data (:func:`~diffaccel.reconstruction.training.scan_smoothing`).
            A sample of N particles makes sparse, noisy images, and the KL
            distance of noisy images is lower for a wider beam (its tails cover
            more measured pixels), so compared pixel by pixel the fitted beam
            depends on the camera's pixel size and on N. ``"auto"`` smooths by
            Scott's bandwidth of the scan's widest image (the finest comparison
            the sample supports), capped by the beam's smallest rms spot on the
            screen (the finest detail the scan must resolve); where that spans
            several camera pixels the images are compared on pooled pixels
            (:func:`~diffaccel.reconstruction.training.smoothed_for_loss`). One
            beam imaged on 64-400 pixels per axis with a 12 % halo
            (``benchmarks/resolution.py``, 6k-64k particles) comes out within
            1.2 % of its emittances this way, 12-300 % high compared pixel by
            pixel. On the GPSR 4D benchmark (100 pixels, a 0.6-pixel x waist
            behind a 1-pixel point spread) the cap sets 0.58 pixels, and the x
            emittance comes out as compared pixel by pixel (-1.3 / -0.9 / -0.7
            % against -0.8 / -1.0 / -1.6 % at seeds 0-2, 2 threads); both sides
            gain exactly the same variance from the smoothing
            (:meth:`~diffaccel.reconstruction.forward.ScreenForwardModel.images`
            sizes the simulated side's kernel by
            :func:`~diffaccel.dynamics.images.blur_variance`). A
            number fixes the smoothing; 0 compares the images as they are.
            None: ``"auto"`` for ``dims = 4``; 1 for ``dims = 6``, whose waists
            of ~1 pixel the 1-pixel smoothing also keeps unbiased for sparse
            simulated images (on the 6D benchmark, 6144 truth particles imaged
            at 0.5 pixel scored better 10 % wider than true; smoothed by one
            pixel, within 0.4-1.4 % at 16 384 particles, and the sampling
            offset removes the rest); ``"auto"`` in 6D adds ``scan_smoothing``
            in quadrature to that pixel.
        moment_weight: Strength ``mu`` of the moment term of the image term:
            ``mu / K sum_k sum_a ((S_ka - M_ka) / s_ka)^2`` over the training
            images, with ``S`` and ``M`` the simulated and measured images'
            second central moments (xx, yy, xy) in a box of 6 rms of the
            measured image (:class:`~diffaccel.reconstruction.losses.MomentMatch`),
            weighed by the image penalty ``lambda`` like the image distance.
            The KL distance fits the images' shapes; where the generator
            cannot take the true shape exactly its optimum trades a few
            tenths of a percent of second moment for shape, which a strong
            z-pz chirp turns into 10-25 % of z emittance, and a heavy halo
            into a wrong x-px shape. None: 3 for ``dims = 4``, 1 for ``dims =
            6``. 4D, on the held-out settings of three synthetic camera scans
            (``benchmarks/validate_defaults.py``, seeds 0, 1; the benchmark
            keeps the lowest rms error among the values within 5 % of the
            lowest L1): with the 3 x 96 generator 0.3, 1, 3 and 10 gave
            held-out rms errors of 0.93, 0.37, 0.19 and 0.17 % (relative L1
            0.143, 0.145, 0.150 and 0.184); on the 360 x 320 pixel scan with
            a 2-pixel waist described under ``depth``, 1 leaves the emittances
            -5.9 / -7.2 % and -4.2 / -5.6 % (x / y, seeds 0, 1), 3 -2.6 /
            +0.4 % and -2.7 / -1.7 %. Without the term (2 x 48, 300 steps)
            the held-out rms sizes were off by 2.45 % on average and a beam
            with a 15 % halo three times as wide came out +4.6 / +6.9 % in
            emittance. 6D: on five
            beams of ``benchmarks/reconstruction_6d_beams.py`` that missed a
            limit without it (seeds 1, 2): 0 left 7 of 10 runs outside a
            limit, 1 left 2 (a three-mode beam's 6D emittance), 3 left 1 (its
            held-out images at 0.152 relative L1), 10 and 100 left 4 and 7
            (held-out images up to 0.39: the moments then outweigh the
            shapes).

    **Prior** (``C``, the broad Gaussian of the entropy term, whose
    transverse widths are ``PRIOR_FACTOR`` times those fitted to the image
    moments, and the prior term on the unseen directions):

    Args:
        longitudinal_scale: Initial and prior rms of (z [m], pz [1]) when
            ``dims = 6`` and the scans do not see them (with a deflecting cavity
            or dispersion they come from the fitted image moments).
        unseen_weight: Strength ``w`` of the prior term on the longitudinal covariance
            directions the scans cannot see (AWA 6D layout: pz variance against the
            px-pz covariance, z variance against py-z), a term of the training
            objective, toward zero partial correlation of the pair each direction trades
            given the other coordinates
            (:func:`~diffaccel.reconstruction.unseen.place_unseen`): ``w sum_k t_k^2``
            with ``t_k`` the displacement of the beam's covariance from the prior point
            along each unseen direction, in correlation units
            (:class:`~diffaccel.reconstruction.unseen.UnseenHold`). It is flat along
            every direction the screens see, so it decides what the images leave free
            and nothing they see; without it the entropy widens the beam along them (pz
            8-44 % high on synthetic beams). Where the scans leave no direction unseen
            (4D, or a 6D scan that sees every longitudinal entry or none) it holds
            nothing. None: 1e3 for ``dims = 6`` (0 for 4D). With the moment term
            (``moment_weight``), 31 of the 33 runs of
            ``benchmarks/reconstruction_6d_beams.py`` (11 beams, seeds 0-2, one thread,
            39 s of training each) meet every limit, a beam whose px-pz partial
            correlation is 0.27 where the prior says 0 included (z emittance -4.4, -1.9,
            -0.8 %).
    """

    # model
    dims: int = field(default=4, metadata=_group("model"))
    n_particles: int | None = field(default=None, metadata=_group("model"))
    width: int | None = field(default=None, metadata=_group("model"))
    depth: int | None = field(default=None, metadata=_group("model"))
    # schedule
    steps: int | None = field(default=None, metadata=_group("schedule"))
    snapshots: int | None = field(default=None, metadata=_group("schedule"))
    burn_in: int | None = field(default=None, metadata=_group("schedule"))
    lr_max: float = field(default=1e-2, metadata=_group("schedule"))
    seed: int = field(default=0, metadata=_group("schedule"))
    # image term
    penalty_end: float | None = field(default=None, metadata=_group("image term"))
    blur_pixels: float | None = field(default=None, metadata=_group("image term"))
    loss_smoothing: float | Literal["auto"] | None = field(
        default=None, metadata=_group("image term")
    )
    moment_weight: float | None = field(default=None, metadata=_group("image term"))
    # prior
    longitudinal_scale: tuple[float, float] = field(
        default=(1e-3, 1e-3), metadata=_group("prior")
    )
    unseen_weight: float | None = field(default=None, metadata=_group("prior"))

    def __post_init__(self) -> None:
        self._check_types()
        if self.dims not in (4, 6):
            raise ValueError(f"dims must be 4 or 6; got {self.dims}.")
        defaults = _DIMS_DEFAULTS[self.dims]
        for name in (
            "n_particles",
            "width",
            "depth",
            "steps",
            "snapshots",
            "penalty_end",
            "unseen_weight",
            "moment_weight",
        ):
            if getattr(self, name) is None:
                object.__setattr__(self, name, getattr(defaults, name))
        if not self.penalty_end > 0:
            raise ValueError(f"penalty_end must be > 0; got {self.penalty_end}.")
        if self.burn_in is None:  # never all members
            burn_in = min(defaults.burn_in, max(self.snapshots - 1, 0))
            object.__setattr__(self, "burn_in", burn_in)
        if not 0 <= self.burn_in < self.snapshots:
            raise ValueError(
                f"burn_in must be in [0, snapshots = {self.snapshots}); got "
                f"{self.burn_in}."
            )
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
        for name in ("moment_weight", "unseen_weight"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be finite and >= 0; got {value}.")
        if self.n_particles < 16:
            raise ValueError(f"n_particles must be >= 16; got {self.n_particles}.")
        if self.loss_smoothing is None:
            object.__setattr__(self, "loss_smoothing", defaults.smoothing)
        if self.loss_smoothing != "auto" and not (
            math.isfinite(self.loss_smoothing)
            and 0 <= self.loss_smoothing <= MAX_BLUR_PIXELS
        ):
            raise ValueError(
                f"loss_smoothing must be in [0, {MAX_BLUR_PIXELS:g}] pixels or "
                f"'auto' (sized by the data); got {self.loss_smoothing!r}."
            )
        if (
            self.blur_pixels is not None
            and not 0 <= self.blur_pixels <= MAX_BLUR_PIXELS
        ):
            raise ValueError(
                f"blur_pixels must be in [0, {MAX_BLUR_PIXELS:g}] pixels; got "
                f"{self.blur_pixels}."
            )
        if not self.lr_max > 0:
            raise ValueError(f"lr_max must be > 0; got {self.lr_max}.")
        if not all(v > 0 for v in self.longitudinal_scale):
            raise ValueError(
                "longitudinal_scale (rms z [m], pz [1]) must be > 0; got "
                f"{tuple(self.longitudinal_scale)}."
            )
        for name in ("width", "depth"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1; got {getattr(self, name)}.")

    def _check_types(self) -> None:
        """Every field a number of its kind (finite): a wrong type or a NaN
        fails here, naming the field, instead of deep in training."""
        for f in fields(self):
            value = getattr(self, f.name)
            if value is None or (f.name == "loss_smoothing" and value == "auto"):
                continue  # None: the dims default, set below; text checked below
            if f.name in _INT_FIELDS:
                ok = is_integer(value)
                kind = "an integer"
            elif f.name == "longitudinal_scale":
                ok = (
                    isinstance(value, tuple | list)
                    and len(value) == 2
                    and all(is_real(v) for v in value)
                )
                kind = "two finite numbers (rms z [m], pz [1])"
            else:
                ok = is_real(value)
                kind = "a finite number"
            if not ok:
                raise ValueError(f"{f.name} must be {kind}; got {value!r}.")
        if isinstance(self.longitudinal_scale, list):
            object.__setattr__(
                self, "longitudinal_scale", tuple(self.longitudinal_scale)
            )

    @property
    def sampling_offset(self) -> float:
        """Offset ``c`` of the KL image distance against the sampling noise of
        the simulated images.

        ``eps = c kappa / N`` is added to every pixel of each sum-normalised
        simulated image (``kappa``: the squared deposit weights of one particle
        summed over pixels,
        :meth:`~diffaccel.reconstruction.forward.ScreenForwardModel.pixel_kernel_sum_sq`;
        ``N``: ``n_particles``); see
        :class:`~diffaccel.reconstruction.losses.ImagePenalty`. Without it the
        KL distance of ``N`` sampled particles is lowest for a beam wider than
        the one they were drawn from: for six synthetic AWA 6D beams (truth
        scaled by 0.985-1.025, 8 draws of 16 384 particles) the least expected
        distance lies at a scale of 1.004-1.014 with ``c = 0``, 1.000-1.002
        with 0.125, 0.997-1.000 with 0.25 and 0.993-0.998 with the
        first-order value 1/2. 0.25 in 6D; 0 in 4D (its benchmark was
        tuned without it).
        """
        return _DIMS_DEFAULTS[self.dims].sampling_offset

    @property
    def smoothing_floor(self) -> float:
        """Loss smoothing [pixels] that ``"auto"`` adds its data-sized part to
        in quadrature (0 in 4D, 1 pixel in 6D)."""
        return _DIMS_DEFAULTS[self.dims].loss_smoothing

    def groups(self) -> dict[str, dict]:
        """The fields by group (:data:`GROUPS`), each a ``{name: value}`` dict.

        Example:
            >>> list(ReconstructionConfig().groups())
            ['model', 'schedule', 'image term', 'prior']
            >>> ReconstructionConfig().groups()["model"]
            {'dims': 4, 'n_particles': 6144, 'width': 96, 'depth': 3}
        """
        out: dict[str, dict] = {g: {} for g in GROUPS}
        for f in fields(self):
            out[f.metadata["group"]][f.name] = getattr(self, f.name)
        return out

    def memory_bytes(self, n_images: int) -> int:
        """Rough peak memory [bytes] of training on ``n_images`` images (CPU).

        Measured peak RSS growth of a 2-step CPU run (float32, 32 x 32 and
        64 x 64 pixels, 20k-320k particles): ~1.5-2 kB per particle in 4D,
        not growing with the number of images (exact linear maps), plus
        ~0.55 kB per particle and training image in 6D (tracked particles
        and their autograd buffers per setting). The estimate uses the lower
        ends, so a run it refuses would not have fitted.

        Example:
            >>> ReconstructionConfig(dims=4, n_particles=1000).memory_bytes(20)
            1536000
            >>> ReconstructionConfig(dims=6, n_particles=1000).memory_bytes(20)
            11776000
        """
        per_particle = _BYTES_PER_PARTICLE
        if self.dims == 6:
            per_particle += _BYTES_PER_PARTICLE_IMAGE_6D * n_images
        return int(self.n_particles) * per_particle

    @property
    def cycle_length(self) -> int:
        """Steps per learning-rate cycle."""
        return self.steps // self.snapshots

    @property
    def schedule(self) -> StepSchedule:
        """Learning rate, penalty weight and members of every training step."""
        return StepSchedule(
            self.cycle_length,
            self.lr_max,
            self.lr_max * LR_END_RATIO,
            PENALTY_START,
            self.penalty_end,
            self.burn_in,
        )

    def blur_for(self, scan: object | None = None) -> float:
        """Point-spread rms [pixels] to image ``scan`` with.

        ``blur_pixels`` when given, else the scan's recorded screen resolution
        (``resolution_pixels``, when it has one), else the default by ``dims``
        (1.0 for 4D, sqrt(1/12) for 6D).

        Example:
            >>> ReconstructionConfig(dims=4).blur_for()
            1.0
            >>> ReconstructionConfig(dims=6, blur_pixels=0.7).blur_for()
            0.7
        """
        if self.blur_pixels is not None:
            return float(self.blur_pixels)
        recorded = getattr(scan, "resolution_pixels", None)
        if recorded is not None:
            return float(min(recorded, MAX_BLUR_PIXELS))
        return float(_DIMS_DEFAULTS[self.dims].blur_pixels)

    def to_dict(self) -> dict:
        """Plain-Python form (JSON and ``weights_only`` safe)."""
        d = asdict(self)
        d["longitudinal_scale"] = list(self.longitudinal_scale)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> ReconstructionConfig:
        """Inverse of :meth:`to_dict`; also reads the configs of older result
        folders and checkpoints.

        Those may carry settings that are now fixed (:data:`FIXED_FIELDS`, the
        values of which are in the module constants), runtime choices
        (:data:`RUNTIME_FIELDS`, arguments of training now) and the settings of
        stages that moved members after training (:data:`AFTER_TRAINING_FIELDS`;
        the moves are in the stored members): all three are dropped.
        """
        d = dict(d)
        if "epochs" in d:  # the name of ``steps`` in older files
            d["steps"] = d.pop("epochs")
        for name in (*FIXED_FIELDS, *RUNTIME_FIELDS, *AFTER_TRAINING_FIELDS):
            d.pop(name, None)
        if "hold_unseen" in d:  # the prior term's name in older files
            d["unseen_weight"] = d.pop("hold_unseen")
        d.setdefault("unseen_weight", 0.0)  # runs trained without the prior term
        d.setdefault("moment_weight", 0.0)  # runs trained without the moment term
        d["longitudinal_scale"] = tuple(d["longitudinal_scale"])
        return cls(**d)


_INT_FIELDS = frozenset(
    ("dims", "n_particles", "width", "depth", "steps", "snapshots", "burn_in", "seed")
)

#: Settings of older configs that are fixed now: the quasi-random base
#: samples, the learning rate at the cycles' ends (``LR_END_RATIO``), the first
#: image-penalty weight (``PENALTY_START``), the entropy's robust radius
#: (:class:`~diffaccel.reconstruction.losses.RelativeEntropy`), the prior
#: factor (:data:`~diffaccel.reconstruction.initial.PRIOR_FACTOR`) and the KL
#: sampling offset (:attr:`ReconstructionConfig.sampling_offset`), the image
#: distance (KL) and the prior point of the unseen directions (zero partial
#: correlation of the traded pair).
FIXED_FIELDS = (
    "quasi_random",
    "lr_min",
    "penalty_start",
    "entropy_radius",
    "prior_factor",
    "sampling_offset",
    "image_loss",
    "unseen_prior",
)
#: Runtime choices of older configs, arguments of training now.
RUNTIME_FIELDS = ("checkpoint_every", "report_every", "cuda_graph")
#: Settings of the stages that moved members after training, in older configs.
AFTER_TRAINING_FIELDS = (
    "place_unseen",
    "place_coupling",
    "refit_steps",
    "refit_lr",
    "refit_hold",
    "probe_unseen",
    "probe_gain",
    "probe_points",
    "probe_away",
    "polish_moments",
)
