"""Snapshot ensembles of beam generators: sampling, image prediction, moments, I/O."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Mapping, Sequence
from functools import partial
from pathlib import Path

import torch
from torch import Tensor

from diffaccel.data import atomic_write
from diffaccel.dynamics import is_integer, is_real
from diffaccel.reconstruction.forward import ScreenForwardModel
from diffaccel.reconstruction.generator import BeamGenerator
from diffaccel.reconstruction.metrics import (
    COORDINATES,
    beam_moments,
    prediction_noise_l1,
)
from diffaccel.reconstruction.training import ReconstructionConfig, load_tensors
from diffaccel.reconstruction.uncertainty import MomentUncertainty

ENSEMBLE_FILE = "ensemble.pt"
#: 2: one forward model per scan (``forwards``); 1 (still read): one ``forward``.
ENSEMBLE_VERSION = 2
_READ_VERSIONS = (1, 2)
#: Scan name of a version-1 ensemble's forward model (as ``data.SINGLE_SCAN_NAME``).
_SINGLE_SCAN = "scan"
#: Particles per member imaged at once when predictions add particles to reach
#: their noise target (bounds the memory of tracking ``K`` settings).
_PREDICTION_CHUNK = 262_144


def unconstrained_coordinates(
    maps: list[Tensor], dims: int, tolerance: float = 1e-3
) -> list[str]:
    """Coordinates that the affine maps ``(K_s, 7, 7)`` of the scans do not see.

    See :meth:`Reconstruction.unconstrained_coordinates`.
    """
    if not maps:
        return []
    rows = torch.stack(
        [r[:, [0, 2], :6].abs().amax(dim=(0, 1)) for r in maps]  # (6,) per scan
    ).amax(0)
    pos_ref = float(rows[[0, 2]].max())
    mom_ref = float(rows[[1, 3]].max())
    ref = (pos_ref, mom_ref, pos_ref, mom_ref, pos_ref, mom_ref)
    return [
        c
        for i, c in enumerate(COORDINATES)
        if not (dims == 4 and i >= 4) and float(rows[i]) < tolerance * ref[i]
    ]


class Reconstruction:
    """A reconstructed beam: one generator per snapshot of the cyclic schedule.

    The ensemble stands for the distribution over beams that fit the images;
    its spread is the (under-covering) uncertainty.

    Args:
        config: Settings the ensemble was trained with.
        snapshots: Generator state dicts, one per ensemble member ``E``.
        forward: Forward model of each training scan ``{scan name: model}`` (a
            single model is stored under the name ``"scan"``).
        history: Training curves (``loss``, ``image_loss``, ``entropy``, ``lr``,
            ``penalty``, ``rms`` per step; ``snapshot_steps``).
        info: JSON-serialisable extras (train indices, timings, dataset path).

    Shapes:
        ``sample(n)`` -> ``(n, 6)``; ``sample(n, per_snapshot=True)`` ->
        ``(E, n, 6)``; ``predict_images(settings (K, P))`` -> ``(K, H, W)``.
    """

    def __init__(
        self,
        config: ReconstructionConfig,
        snapshots: list[dict],
        forward: ScreenForwardModel | Mapping[str, ScreenForwardModel],
        history: dict,
        info: dict | None = None,
        *,
        training_maps: Sequence[Tensor] | None = None,
    ) -> None:
        if not snapshots:
            raise ValueError("a reconstruction needs at least one snapshot.")
        self.config = config
        self.snapshots = snapshots
        if isinstance(forward, ScreenForwardModel):
            forward = {_SINGLE_SCAN: forward}
        self.forwards: dict[str, ScreenForwardModel] = dict(forward)
        if not self.forwards:
            raise ValueError("a reconstruction needs at least one forward model.")
        self.history = history
        self.info = dict(info or {})
        self._generators = [self._build(s) for s in snapshots]
        # the maps of training_maps(), when the caller has them already
        self._training_maps = None if training_maps is None else list(training_maps)

    def _build(self, state: dict) -> BeamGenerator:
        c = self.config
        gen = BeamGenerator(
            c.dims, width=c.width, depth=c.depth, scale=torch.ones(c.dims)
        )
        gen.load_state_dict(state)
        gen.requires_grad_(False)
        return gen

    @property
    def forward(self) -> ScreenForwardModel:
        """Forward model of the first (or only) training scan."""
        return next(iter(self.forwards.values()))

    @property
    def scan_names(self) -> list[str]:
        """Names of the training scans (keys of :attr:`forwards`)."""
        return list(self.forwards)

    @property
    def n_snapshots(self) -> int:
        """Number of ensemble members ``E``."""
        return len(self._generators)

    @property
    def generators(self) -> list[BeamGenerator]:
        """The ensemble members (gradients disabled)."""
        return list(self._generators)

    def sample(
        self,
        n: int,
        *,
        per_snapshot: bool = False,
        seed: int = 0,
        device: str | torch.device | None = None,
    ) -> Tensor:
        """Draw particles from the ensemble in Bmad coordinates.

        Args:
            n: Particles (per member if ``per_snapshot``).
            per_snapshot: Return each member's sample separately.
            seed: Seed of the sampling generator (same seed, same particles).
            device: Device of the result (default CPU).

        Returns:
            ``(n, 6)`` particles of the ensemble mixture (members contribute
            equal shares), or ``(E, n, 6)``.
        """
        _count("n", n)
        device = torch.device(device or "cpu")
        rng = torch.Generator(device=device).manual_seed(seed)
        e = self.n_snapshots
        with torch.no_grad():
            if per_snapshot:
                return torch.stack(
                    [g.to(device)(n, generator=rng) for g in self._generators]
                )
            counts = [n // e + (1 if i < n % e else 0) for i in range(e)]
            parts = [
                g.to(device)(c, generator=rng)
                for g, c in zip(self._generators, counts, strict=True)
                if c > 0
            ]
            x = torch.cat(parts)
            perm = torch.randperm(n, generator=rng, device=device)
            return x[perm]

    def predict_images(
        self,
        settings: Tensor,
        *,
        forward: ScreenForwardModel | None = None,
        scan: str | None = None,
        n_particles: int = 50_000,
        per_snapshot: bool = False,
        seed: int = 0,
        return_std: bool = False,
        n_draws: int = 8,
        draw_particles: int = 10_000,
        maps: Tensor | None = None,
        return_on_screen: bool = False,
        noise_l1: float | None = None,
        measured: Tensor | None = None,
        max_particles: int = 1_000_000,
        return_particles: bool = False,
    ) -> Tensor | tuple[Tensor, ...]:
        """Ensemble-mean screen images for arbitrary settings.

        The beamline is rebuilt from the settings passed on every call (no state
        is kept between calls, so predictions never show earlier settings).

        Args:
            settings: Values of the scanned parameters, one row per setting.
            forward: Another forward model (e.g. a different screen grid or
                beamline); defaults to the training scan's.
            scan: Name of the training scan whose forward model to use
                (default the first); ignored when ``forward`` is given.
            n_particles: Particles per ensemble member.
            per_snapshot: Return ``(E, K, H, W)`` instead of the mean.
            seed: Sampling seed.
            return_std: Also return the per-pixel spread: the std over the
                members and, when the reconstruction carries a moment-space
                posterior (:attr:`uncertainty`), over ``n_draws`` posterior
                beams per member (each member's particles linearly mapped to a
                drawn centroid and covariance), combined as the variance of
                the mixture (between members plus the mean within-member
                variance over draws).
            n_draws: Posterior beams per member for ``return_std``.
            draw_particles: Particles of each member imaged per posterior
                draw (the first ones of its sample: the draws of a member share
                them, so their shot noise cancels in the spread).
            maps: The forward model's ``transfer_maps(settings)`` when the
                caller has them (a 4D reconstruction images through them where
                they are exact, instead of tracking).
            return_on_screen: Also return the fraction of the beam on the screen
                at each setting (dimensionless, in [0, 1]): the sum of each
                member's image before it is normalised to 1 (particles deposited
                inside the screen's pixel area, as the forward model deposits
                and blurs them), averaged over the members. Taken from the same
                images: no extra tracking, and the images are unchanged.
            noise_l1: Largest expected relative L1 that the predicted images'
                own sampling noise may add
                (:func:`~diffaccel.reconstruction.metrics.prediction_noise_l1`
                of the ensemble-mean images, mean over the settings).
                ``n_particles`` per member are imaged first; when their noise
                exceeds the target, every member images more particles (a
                fresh sample, in blocks) up to ``max_particles``. None:
                ``n_particles`` only. Fine pixels need this: a 300 x 300 px
                screen imaged with 50 000 particles per member carries ~0.1-0.15
                relative L1 of noise of its own.
            measured: Measured images ``(K, H, W)`` of these settings. With
                ``noise_l1`` the target becomes a third of the error the
                predictions measure against them, its own noise removed
                (:data:`MEASURED_ERROR_SHARE`), so that the noise adds ~5 % to a
                reported image error; ``noise_l1`` where they are empty.
            max_particles: Upper bound of the particles per member that
                ``noise_l1`` may use.
            return_particles: Also return the particles per member behind the
                images (an int, last in the tuple).

        Shapes:
            ``settings (K, P)`` -> ``(K, H, W)`` float32, each image summing to 1
            (all-zero if no particle reaches the screen); with ``return_std``
            a pair ``(mean, std)`` of that shape; with ``return_on_screen`` the
            fractions ``(K,)`` (``(E, K)`` with ``per_snapshot``) come next:
            ``(mean, fraction)`` or ``(mean, std, fraction)``; with
            ``return_particles`` the particle count per member comes last.

        Raises:
            ValueError: if ``settings`` has the wrong number of columns or NaNs.
        """
        # the spread recolours members by their covariance: enough particles
        _count("n_particles", n_particles, least=64 if return_std else 1)
        if noise_l1 is not None and not (is_real(noise_l1) and noise_l1 > 0):
            raise ValueError(f"noise_l1 must be a number > 0; got {noise_l1!r}.")
        if noise_l1 is not None:
            _count("max_particles", max_particles)
        if return_std:
            _count("n_draws", n_draws, least=0)  # 0: the members alone
            _count("draw_particles", draw_particles, least=64)
        if forward is not None:
            if not isinstance(forward, ScreenForwardModel):
                kind = type(forward).__name__
                raise ValueError(f"forward must be a ScreenForwardModel; got {kind}.")
            fwd = forward
        elif scan is not None:
            if scan not in self.forwards:
                raise ValueError(
                    f"no training scan named {scan!r}; scans are {self.scan_names}."
                )
            fwd = self.forwards[scan]
        else:
            fwd = self.forward
        settings = fwd.check_settings(settings)
        if maps is not None and (
            maps.ndim != 3
            or maps.shape[0] != settings.shape[0]
            or tuple(maps.shape[1:]) not in ((6, 6), (7, 7))
        ):
            raise ValueError(
                f"maps {tuple(maps.shape)} must be the forward model's "
                f"transfer_maps(settings): (K, 7, 7) with K = {settings.shape[0]}."
            )
        beams = self.sample(n_particles, per_snapshot=True, seed=seed)
        # a 4D beam (pz = 0) through a beamline whose affine maps are exact for
        # it: one matrix product per beam instead of tracking (the same images
        # up to the paraxial px^2 terms of the exact drift, see images_linear)
        if self.config.dims == 4:
            maps = fwd.linear_maps(settings, monochromatic=True, maps=maps)
        else:
            maps = None

        def image(b: Tensor) -> Tensor:
            if maps is None:
                return fwd.images(b, settings)
            return fwd.images_linear(b, maps)

        with torch.no_grad():
            imgs = torch.stack([image(b) for b in beams])
            used = n_particles
            if noise_l1 is not None:
                need = _particles_needed(
                    imgs, measured, fwd, n_particles, noise_l1, max_particles
                )
                imgs, used = self._sharpened(imgs, n_particles, need, image, seed)
            on_screen = imgs.sum((-2, -1))  # (E, K): before normalising
            if not per_snapshot:
                on_screen = on_screen.mean(0)
            imgs = _unit_sum(imgs)
            tail = ((on_screen,) if return_on_screen else ()) + (
                (used,) if return_particles else ()
            )
            if not return_std:
                mean = imgs if per_snapshot else imgs.mean(0)
                return (mean, *tail) if tail else mean
            var = _var0(imgs) if len(beams) > 1 else torch.zeros_like(imgs[0])
            unc = self.uncertainty
            if unc is not None and n_draws > 1:
                g = torch.Generator().manual_seed(seed + 1)
                mu, cov = unc.draw(n_draws, g)
                # drawn beams keep pz = 0 only if the posterior is 4D
                draw_image = (
                    image if unc.dims == 4 else partial(fwd.images, settings=settings)
                )
                within = torch.zeros_like(var)
                for b in beams:
                    drawn = _recolour(b[:draw_particles], unc.dims, mu, cov)
                    within += _var0(
                        _unit_sum(torch.stack([draw_image(d) for d in drawn]))
                    )
                var = var + within / len(beams)
            std = var.sqrt()
        mean = imgs if per_snapshot else imgs.mean(0)
        return (mean, std, *tail)

    def _sharpened(
        self,
        images: Tensor,
        n: int,
        need: int,
        image: Callable[[Tensor], Tensor],
        seed: int,
    ) -> tuple[Tensor, int]:
        """Members' images ``(E, K, H, W)`` of ``n`` particles each, remade of
        ``need`` particles each (the ``n`` plus a fresh sample) where ``need >
        n``.

        Returns the images (each still summing to its fraction on the screen)
        and the particles per member behind them.
        """
        if need <= n:
            return images, n
        # a sample of its own (seed + 1 draws the posterior beams)
        rng = torch.Generator().manual_seed(seed + 2)
        total = images * n
        for member, gen in zip(total, self._generators, strict=True):
            left = need - n
            while left > 0:
                c = min(left, _PREDICTION_CHUNK)
                member += image(gen.to("cpu")(c, generator=rng)).mul_(c)
                left -= c
        return total.div_(need), need

    @property
    def uncertainty(self) -> MomentUncertainty | None:
        """Moment-space posterior stored by ``reconstruct`` (None if absent)."""
        d = self.info.get("uncertainty")
        return MomentUncertainty.from_dict(d) if isinstance(d, dict) else None

    def moments(self, n: int = 100_000, seed: int = 0) -> dict[str, dict]:
        """Mean and calibrated 1-sigma uncertainty of the beam moments.

        ``std`` combines (in quadrature) the spread over ensemble members
        (``std_ensemble``: optimisation scatter) and, when the reconstruction
        carries a moment-space posterior (:attr:`uncertainty`, written by
        ``reconstruct``), the posterior std of the same moment
        (``std_posterior``: measurement error and the directions the scans do
        not constrain, see :mod:`diffaccel.reconstruction.uncertainty`).

        Args:
            n: Particles per member used to compute the moments.
            seed: Sampling seed.

        Returns:
            ``{name: {"mean": value, "std": value, "std_ensemble": value,
            "std_posterior": value or None, "unit": str}}`` with values floats
            or nested lists (``centroid``, ``rms`` per coordinate, ``cov``,
            ``corr``); normalised emittances use ``p0c`` and the species mass of
            the forward model.
        """
        beams = self.sample(n, per_snapshot=True, seed=seed)
        per = [beam_moments(b) for b in beams]
        bg = self.forward.beta_gamma()
        for m in per:
            m["norm_emit_x"] = m["emit_x"] * bg
            m["norm_emit_y"] = m["emit_y"] * bg
        unc = self.uncertainty
        post = unc.moment_std(seed=seed) if unc is not None else None
        if post is not None:
            post["norm_emit_x"] = post["emit_x"] * bg
            post["norm_emit_y"] = post["emit_y"] * bg
        units = {
            "centroid": "m, 1, m, 1, m, 1",
            "rms": "m, 1, m, 1, m, 1",
            "cov": "Bmad units squared",
            "corr": "1",
            "emit_x": "m",
            "emit_y": "m",
            "emit_z": "m",
            "emit_4d": "m^2",
            "emit_6d": "m^3",
            "norm_emit_x": "m",
            "norm_emit_y": "m",
            "beta_x": "m",
            "beta_y": "m",
            "alpha_x": "1",
            "alpha_y": "1",
        }
        out: dict[str, dict] = {}
        for key, unit in units.items():
            stack = torch.stack([m[key] for m in per])
            ens = stack.std(0) if len(per) > 1 else torch.zeros_like(stack[0])
            pst = post[key] if post is not None else None
            std = ens if pst is None else (ens**2 + pst**2).sqrt()
            out[key] = {
                "mean": stack.mean(0).tolist(),
                "std": std.tolist(),
                "std_ensemble": ens.tolist(),
                "std_posterior": None if pst is None else pst.tolist(),
                "unit": unit,
            }
        out["coordinates"] = {"mean": list(COORDINATES), "std": None, "unit": ""}
        return out

    def unconstrained_coordinates(self, tolerance: float = 1e-3) -> list[str]:
        """Coordinates the scan does not see to first order.

        A coordinate is flagged when its column of the linear transfer matrices
        to the screen's x and y is below ``tolerance`` times the largest
        column of the same unit group at every setting of the training scan (e.g.
        ``z`` always; ``pz`` without dispersion), so images constrain it only
        through weak chromatic or no effects at all: its reconstruction is set by
        the prior and the ensemble spread understates its uncertainty.
        """
        stored = self.info.get("unconstrained_coordinates")
        if tolerance == 1e-3 and isinstance(stored, list):
            return list(stored)  # computed by reconstruct() from its maps
        return unconstrained_coordinates(
            self.training_maps(), self.config.dims, tolerance
        )

    def training_maps(self) -> list[Tensor]:
        """Each scan's affine maps ``(K_s, 7, 7)`` at its training settings
        (scans without recorded training settings left out); computed once."""
        if self._training_maps is not None:
            return list(self._training_maps)
        per_scan = self.info.get("scans")
        if not isinstance(per_scan, dict):
            per_scan = {self.scan_names[0]: self.info}
        maps = []
        for name, fwd in self.forwards.items():
            sets = torch.as_tensor(
                per_scan.get(name, {}).get("train_settings", []), dtype=torch.float64
            )
            if sets.numel():
                maps.append(fwd.transfer_maps(sets))
        self._training_maps = maps
        return list(maps)

    def save(self, directory: str | os.PathLike, *, overwrite: bool = False) -> Path:
        """Write the ensemble to ``directory/ensemble.pt`` atomically.

        Raises:
            FileExistsError: if the file exists and ``overwrite`` is False.
        """
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        path = d / ENSEMBLE_FILE
        if path.exists() and not overwrite:
            raise FileExistsError(f"{path} exists; pass overwrite=True to replace it.")
        payload = {
            "ensemble_version": ENSEMBLE_VERSION,
            "config": self.config.to_dict(),
            "snapshots": self.snapshots,
            "forwards": json.dumps(
                {name: f.to_spec() for name, f in self.forwards.items()}
            ),
            "history": json.dumps(self.history),
            "info": json.dumps(self.info),
        }
        return atomic_write(path, lambda p: torch.save(payload, p))


def load(directory: str | os.PathLike) -> Reconstruction:
    """Load a reconstruction written by :meth:`Reconstruction.save`.

    Args:
        directory: Output directory of ``diffaccel reconstruct`` (or the
            ``ensemble.pt`` file itself).

    Raises:
        FileNotFoundError: if there is no ensemble file.
        ValueError: if the file is not a diffaccel ensemble.
    """
    p = Path(directory)
    path = p if p.is_file() else p / ENSEMBLE_FILE
    if not path.exists():
        raise FileNotFoundError(f"no {ENSEMBLE_FILE} in {p}")
    d = load_tensors(path, "ensemble")
    if not isinstance(d, dict) or d.get("ensemble_version") not in _READ_VERSIONS:
        raise ValueError(
            f"{path} is not a diffaccel ensemble (versions {_READ_VERSIONS})."
        )
    try:
        if d["ensemble_version"] == 1:
            specs = {_SINGLE_SCAN: json.loads(d["forward"])}
        else:
            specs = json.loads(d["forwards"])
        forwards = {
            name: ScreenForwardModel.from_spec(spec) for name, spec in specs.items()
        }
        return Reconstruction(
            config=ReconstructionConfig.from_dict(d["config"]),
            snapshots=list(d["snapshots"]),
            forward=forwards,
            history=json.loads(d["history"]),
            info=json.loads(d["info"]),
        )
    except (KeyError, TypeError, ValueError, AttributeError, RuntimeError) as exc:
        # missing entries, wrong types, state dicts that do not fit the config
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        raise ValueError(
            f"{path} is a damaged diffaccel ensemble ({type(exc).__name__}: {first})."
        ) from exc


#: Most particles one call draws per member: 10^9 x 6 float32 is 24 GB.
MAX_PARTICLES = 10**9


def _count(name: str, value: object, least: int = 1) -> None:
    """Refuse a particle or draw count that is not an integer >= ``least``."""
    if not (is_integer(value) and least <= value <= MAX_PARTICLES):
        raise ValueError(
            f"{name} must be an integer in [{least}, {MAX_PARTICLES:.0e}]; "
            f"got {value!r}."
        )


#: With measured images, predictions add particles until their own noise is at
#: most this share of the error they measure (its noise removed in quadrature):
#: in quadrature the noise then adds ``sqrt(1 + 1/9) - 1``, ~5 %, to it.
MEASURED_ERROR_SHARE = 1.0 / 3.0


def _particles_needed(
    images: Tensor,
    measured: Tensor | None,
    fwd: ScreenForwardModel,
    n: int,
    noise_l1: float,
    max_particles: int,
) -> int:
    """Particles per member that bring the own noise of the members' images
    ``(E, K, H, W)`` of ``n`` particles each to its target (relative L1, mean
    over the settings; noise goes as ``1/sqrt(N)``), at most ``max_particles``;
    see :meth:`Reconstruction.predict_images`."""
    mean = _unit_sum(images).mean(0)
    own = prediction_noise_l1(mean, fwd.pixel_kernel_sum_sq(), n * images.shape[0])
    own_l1 = float(own.mean()) if own.numel() else 0.0
    target = noise_l1
    if measured is not None:
        m = measured.detach().to(torch.float64)
        sums = m.sum((-2, -1), keepdim=True)
        if m.shape == mean.shape and bool((sums > 0).all()):
            error = (mean.to(torch.float64) - m / sums).abs().sum((-2, -1)).mean()
            beam = math.sqrt(max(float(error) ** 2 - own_l1**2, 0.0))
            target = MEASURED_ERROR_SHARE * beam
    if own_l1 <= target:
        return n
    if target <= 0:
        return max_particles
    return min(max_particles, math.ceil(n * (own_l1 / target) ** 2))


def _unit_sum(images: Tensor) -> Tensor:
    return images / images.sum((-2, -1), keepdim=True).clamp_min(1e-30)


def _var0(x: Tensor) -> Tensor:
    """``x.var(0)`` (unbiased) in two passes: ~15x faster than torch's
    reduction over the leading dimension of ``(E, K, H, W)`` image stacks on
    the CPU; equal to it to float rounding."""
    return (x - x.mean(0)).square_().sum(0).div_(x.shape[0] - 1)


def _sym_sqrt(c: Tensor, floor: float = 1e-6) -> Tensor:
    """Symmetric square root of covariances ``(..., d, d)`` (eigenvalues clipped)."""
    vals, vecs = torch.linalg.eigh(0.5 * (c + c.transpose(-1, -2)))
    low = floor * vals.amax(-1, keepdim=True).clamp_min(1e-300)
    root = vals.clamp_min(0).maximum(low).sqrt()
    return (vecs * root[..., None, :]) @ vecs.transpose(-1, -2)


def _recolour(particles: Tensor, dims: int, mu: Tensor, cov: Tensor) -> Tensor:
    """Particles linearly mapped to drawn centroids and covariances.

    ``x -> mu_d + T_d (x - mean)`` on the first ``dims`` coordinates with
    ``T_d = C_d^(1/2) C^(-1/2)`` (symmetric roots of the drawn and the
    particles' covariance; the identity when they agree), so the mapped beam
    has exactly the drawn centroid and covariance and otherwise keeps its
    shape.

    Shapes:
        ``particles (N, 6)``, ``mu (D, 6)``, ``cov (D, 6, 6)`` -> ``(D, N, 6)``.
    """
    x = particles.to(torch.float64)
    d = dims
    m = x[:, :d].mean(0)
    xc = x[:, :d] - m
    c = xc.T @ xc / (x.shape[0] - 1)
    t = _sym_sqrt(cov[:, :d, :d]) @ torch.linalg.inv(_sym_sqrt(c, 1e-12))
    out = x.expand(mu.shape[0], -1, -1).clone()
    out[..., :d] = xc @ t.transpose(-1, -2) + mu[:, None, :d]
    return out.to(particles.dtype)
