"""Screen forward model: track a beam through a scanned beamline and image it."""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import cached_property
from typing import Any

import torch
from torch import Tensor

from diffaccel.data.quad_scan import check_setting_limits
from diffaccel.dynamics import as_p0c, as_real_tensor, check_particles
from diffaccel.dynamics.beamline import Beamline
from diffaccel.dynamics.elements.element import Coords
from diffaccel.dynamics.elements.screen import Screen
from diffaccel.dynamics.images import (
    blur_rms_for_variance,
    blur_variance,
    cic_image,
    gaussian_blur,
)
from diffaccel.dynamics.species import Species

#: Largest point-spread rms [pixels]: beyond it every image is flat.
MAX_BLUR_PIXELS = 100.0


class ScreenForwardModel:
    """Simulated screen images of a beam for any scan settings.

    Tracks Bmad particles through ``beamline`` with the scanned parameters set
    from each row of ``settings`` (a fresh copy of the beamline per call: no
    stale state), deposits them on the screen with cloud-in-cell and blurs with a
    Gaussian of ``blur_pixels`` pixels. Images are *not* renormalised: each sums
    to the fraction of the beam that lands on the screen.

    Args:
        beamline: Beamline with exactly one ``Screen`` whose geometry is set.
        names: Scanned parameters, e.g. ``["Q1.k1"]``.
        p0c: Reference momentum times c [eV].
        species: Species name (``"electron"``, ``"positron"``, ``"proton"``).
        blur_pixels: Total point-spread rms of the images [pixels]. Cloud-in-cell
            deposition already spreads each particle with variance 1/6 pixel^2
            per axis, so the Gaussian blur applied afterwards adds variance
            ``blur_pixels^2 - 1/6`` pixel^2 (none below ``sqrt(1/6)``).
        image_smoothing: Optional extra Gaussian rms per image ``(K, 2)``
            [pixels] (x, y): the images gain exactly the variance that
            :func:`~diffaccel.dynamics.images.gaussian_blur` with this rms adds
            to a measured image
            (:func:`~diffaccel.dynamics.images.blur_variance`), for images of
            exactly ``K`` settings at a time (the image term of training, see
            :func:`~diffaccel.reconstruction.training.smoothed_for_loss`).

    Shapes:
        ``images(particles (N, 6), settings (K, P))`` -> ``(K, H, W)``.

    Raises:
        ValueError: if the beamline has no or several screens, the screen has no
            geometry, a name is not a parameter of the beamline, or ``p0c <= 0``.
    """

    def __init__(
        self,
        beamline: Beamline,
        names: Sequence[str],
        p0c: float,
        *,
        species: str = "electron",
        blur_pixels: float = 1.0,
        image_smoothing: Tensor | None = None,
    ) -> None:
        screens = [e for e in beamline if isinstance(e, Screen)]
        if len(screens) != 1:
            raise ValueError(
                f"the beamline must hold exactly one Screen; found {len(screens)}."
            )
        self.screen: Screen = screens[0]
        if self.screen.shape is None or self.screen.pixel_size is None:
            raise ValueError(f"Screen {self.screen.name!r} has no geometry.")
        if not (isinstance(p0c, int | float) and math.isfinite(p0c) and p0c > 0):
            raise ValueError(f"p0c must be a finite number > 0 eV; got {p0c!r}.")
        self._species = Species.from_name(species)  # raises ValueError if unknown
        if not 0 <= blur_pixels <= MAX_BLUR_PIXELS:
            raise ValueError(
                f"blur_pixels must be in [0, {MAX_BLUR_PIXELS:g}] pixels; got "
                f"{blur_pixels}."
            )
        self.names = list(names)
        for n in self.names:
            beamline._split_name(n)  # raises ValueError naming the problem
        self.beamline = beamline
        self.p0c = float(p0c)
        self.species = species
        self.blur_pixels = float(blur_pixels)
        if image_smoothing is not None:
            image_smoothing = torch.as_tensor(image_smoothing, dtype=torch.float64)
            if image_smoothing.dim() != 2 or image_smoothing.shape[1] != 2:
                raise ValueError(
                    "image_smoothing must be (K, 2) pixels; got shape "
                    f"{tuple(image_smoothing.shape)}."
                )
            if not bool(torch.isfinite(image_smoothing).all()) or bool(
                (image_smoothing < 0).any()
            ):
                raise ValueError("image_smoothing must be finite and >= 0 pixels.")
        self.image_smoothing = image_smoothing
        self.device = torch.device("cpu")

    # ----------------------------------------------------------------- spec I/O
    @classmethod
    def from_dataset(
        cls, dataset: Any, *, blur_pixels: float = 1.0
    ) -> ScreenForwardModel:
        """Forward model of a ``QuadScanDataset`` (its beamline, screen, names)."""
        return cls(
            dataset.beamline(),
            dataset.setting_names,
            dataset.p0c,
            species=dataset.species,
            blur_pixels=blur_pixels,
        )

    def to_spec(self) -> dict[str, Any]:
        """JSON-serialisable description (inverse of :meth:`from_spec`)."""
        return {
            "beamline": self.beamline.to_spec(),
            "names": self.names,
            "p0c": self.p0c,
            "species": self.species,
            "blur_pixels": self.blur_pixels,
        }

    @classmethod
    def from_spec(cls, spec: dict[str, Any]) -> ScreenForwardModel:
        """Rebuild from :meth:`to_spec` output."""
        return cls(
            Beamline.from_spec(spec["beamline"]),
            spec["names"],
            spec["p0c"],
            species=spec["species"],
            blur_pixels=spec["blur_pixels"],
        )

    def to(self, device: str | torch.device) -> ScreenForwardModel:
        """This model with tensors on ``device`` (returns self)."""
        self.device = torch.device(device)
        self.beamline = self.beamline.to(self.device)
        return self

    # ----------------------------------------------------------------- physics
    def check_settings(self, settings: Tensor) -> Tensor:
        """Validate settings ``(K, P)`` and return them as float64.

        Raises:
            ValueError: for a wrong shape, non-finite values or values beyond
                :data:`~diffaccel.data.quad_scan.PARAMETER_LIMITS`.
        """
        s = as_real_tensor(settings, "settings", dtype=torch.float64)
        if s.ndim == 1 and len(self.names) == 1:
            s = s[:, None]
        if s.ndim != 2 or s.shape[1] != len(self.names):
            raise ValueError(
                f"settings must have shape (K, {len(self.names)}) for names "
                f"{self.names}; got {tuple(s.shape)}."
            )
        if not torch.isfinite(s).all():
            raise ValueError("settings contain NaN or infinite values.")
        check_setting_limits(self.names, s)
        return s

    def track_to_screen(self, particles: Tensor, settings: Tensor) -> Tensor:
        """Particles at the screen, ``(N, 6), (K, P) -> (K, N, 6)``."""
        settings = settings.to(device=particles.device)
        return self.beamline.track_screens(
            particles,
            self.p0c,
            settings=settings,
            names=self.names,
            species=self._species,
        )[self.screen.name]

    def images(self, particles: Tensor, settings: Tensor) -> Tensor:
        """Blurred cloud-in-cell screen images (sum = fraction on screen).

        Args:
            particles: Initial Bmad coordinates.
            settings: Scan settings.

        Shapes:
            ``(N, 6), (K, P) -> (K, H, W)`` in the dtype of ``particles``.
        """
        at_screen = self.track_to_screen(particles, settings)
        return self.screen.image(at_screen, method="cic", blur_sigma=self._blur())

    def images_linear(self, particles: Tensor, maps: Tensor) -> Tensor:
        """Images of particles tracked with precomputed affine maps.

        With the maps of :meth:`linear_maps` (which exist only where they are
        exact for the beam) this equals :meth:`images` up to the paraxial terms
        of the exact drift (relative ``px^2 / 2``), offsets of misaligned
        elements included, at the cost of one batched matrix product.

        Shapes:
            ``particles (N, 6)``, ``maps (K, 7, 7)`` -> ``(K, H, W)``.
        """
        maps = maps.to(dtype=particles.dtype, device=particles.device)
        rows = maps[:, 0:3:2, :6]  # (K, 2, 6)
        xy = torch.einsum("kij,nj->kin", rows, particles)  # (K, 2, N)
        xy = xy + maps[:, 0:3:2, 6:]
        scr = self.screen
        return cic_image(
            xy[:, 0],
            xy[:, 1],
            scr.shape,
            scr.pixel_size,
            scr.center,
            None,
            self._blur(),
        )

    def _blur(self) -> tuple[float, float] | Tensor | None:
        """Rms of the Gaussian applied after CIC ``(x, y)`` [m], or None; one
        pair per image ``(K, 2)`` with ``image_smoothing``."""
        return self._blur_sizes

    @cached_property
    def _blur_sizes(self) -> tuple[float, float] | Tensor | None:
        """:meth:`_blur`'s value, made once (no tensor per step).

        Sized by the variance of the kernel that
        :func:`~diffaccel.dynamics.images.gaussian_blur` applies
        (:func:`~diffaccel.dynamics.images.blur_variance`), not by its nominal
        rms: the images' total point-spread variance is ``blur_pixels^2``
        exactly (cloud-in-cell's 1/6 pixel^2 included), plus exactly the
        variance that the same smoothing adds to the measured images. With
        nominal rms a sub-pixel smoothing adds less to the measured side than
        to the simulated one (0.32 against 0.33 pixel^2 at 0.58 pixel), and
        the fit narrows the beam where its spot is smallest.
        """
        extra = self.blur_pixels**2 - 1.0 / 6.0
        psx, psy = self.screen.pixel_size
        if self.image_smoothing is not None:
            total = blur_rms_for_variance(extra + blur_variance(self.image_smoothing))
            return total * torch.tensor([psx, psy], dtype=torch.float64)
        if extra <= 1e-6:
            return None
        rms = float(blur_rms_for_variance(extra))
        return (rms * psx, rms * psy)

    def _max_blur_pixels(self) -> float:
        """Largest total point-spread rms of the images [pixels]."""
        if self.image_smoothing is None:
            return self.blur_pixels
        return math.sqrt(self.blur_pixels**2 + float(self.image_smoothing.max()) ** 2)

    def pixel_kernel_sum_sq(self, samples: int = 64) -> float:
        """Sum over pixels of the squared deposit weights of one particle.

        ``kappa = mean_u sum_p w_p(u)^2`` over sub-pixel positions ``u`` of the
        particle, for the cloud-in-cell deposit and Gaussian blur of
        :meth:`images` (1 for a histogram, 4/9 for bare cloud-in-cell, about
        ``1 / (4 pi blur_pixels^2)`` for a wide blur). A pixel of an image of
        ``N`` particles with expected value ``s`` then has variance
        ``kappa s / N``: the sampling noise of the simulated images.

        Example:
            >>> from diffaccel.dynamics.elements.screen import Screen
            >>> from diffaccel.dynamics.beamline import Beamline
            >>> scr = Screen(name="S", shape=(8, 8), pixel_size=1e-4)
            >>> f = ScreenForwardModel(Beamline([scr]), [], 1e7, blur_pixels=0.1)
            >>> round(f.pixel_kernel_sum_sq(), 4)  # bare cloud-in-cell: (2/3)^2
            0.4444
        """
        blur = self._blur()
        if isinstance(blur, Tensor):  # per image: the median image's spread
            blur = tuple(float(v) for v in blur.median(0).values)
        kappa = 1.0
        for axis in range(2):
            n = 2 * math.ceil(6.0 * self._max_blur_pixels()) + 3
            u = (torch.arange(samples, dtype=torch.float64) + 0.5) / samples
            w = torch.zeros(samples, n, dtype=torch.float64)
            w[:, n // 2] = 1.0 - u
            w[:, n // 2 + 1] = u
            if blur is not None:  # along the last axis: rms blur[axis] [m]
                ps = self.screen.pixel_size[axis]
                w = gaussian_blur(w[None], (blur[axis], 0.0), (ps, ps))[0]
            kappa *= float(w.square().sum(-1).mean())
        return kappa

    def blur_sigma(self) -> tuple[float, float]:
        """Total point-spread rms ``(x, y)`` [m] (CIC plus Gaussian blur)."""
        psx, psy = self.screen.pixel_size
        return (self.blur_pixels * psx, self.blur_pixels * psy)

    def extent_mm(self) -> tuple[float, float, float, float]:
        """Screen extent ``(x_min, x_max, y_min, y_max)`` [mm] for ``imshow``."""
        xs, ys = self.screen.pixel_centers(dtype=torch.float64)
        psx, psy = self.screen.pixel_size
        return (
            1e3 * (float(xs[0]) - psx / 2),
            1e3 * (float(xs[-1]) + psx / 2),
            1e3 * (float(ys[0]) - psy / 2),
            1e3 * (float(ys[-1]) + psy / 2),
        )

    def transfer_maps(self, settings: Tensor) -> Tensor:
        """Affine first-order maps to the screen, composed analytically.

        The product of the elements' :meth:`~diffaccel.dynamics.Element.transfer_map`
        with each row of settings applied: ``A[k, :6, :6]`` the Jacobian about the
        reference orbit, ``A[k, :6, 6]`` the orbit offset (misaligned elements).
        Exact for images only where :meth:`linear_maps` returns them.

        Shapes:
            ``settings (K, P)`` -> ``(K, 7, 7)`` float64 (CPU).
        """
        return self._scanned(settings).transfer_map(self.p0c, self._species)

    def linear_maps(
        self,
        settings: Tensor,
        *,
        monochromatic: bool,
        maps: Tensor | None = None,
    ) -> Tensor | None:
        """:meth:`transfer_maps` if they reproduce the tracking, else None.

        Args:
            settings: Scan settings ``(K, P)``.
            monochromatic: True if every particle has ``pz = 0`` (a 4D beam).
            maps: ``transfer_maps(settings)`` when the caller already has them
                (returned as they are rather than computed again).

        Returns:
            ``(K, 7, 7)`` float64 (CPU) when every element of the scanned
            beamline is exactly affine for such a beam
            (:meth:`~diffaccel.dynamics.Beamline.linear_map_is_exact`); None
            otherwise (a cavity switched on, a bend, energy spread): then track.
        """
        line = self._scanned(settings)
        if not line.linear_map_is_exact(monochromatic):
            return None
        return line.transfer_map(self.p0c, self._species) if maps is None else maps

    def _scanned(self, settings: Tensor) -> Beamline:
        """A float64 CPU copy of the beamline with the settings applied."""
        s = self.check_settings(settings).cpu()
        line = Beamline.from_spec(self.beamline.to_spec())
        return line.with_params({n: s[:, p] for p, n in enumerate(self.names)})

    def drift_length(self) -> float:
        """Total beamline length [m] (a scale for divergence guesses)."""
        return max(float(self.beamline.length.sum()), 1e-3)

    def beta_gamma(self) -> float:
        """Relativistic ``beta * gamma = p0c / (m c^2)`` of the reference particle."""
        return self.p0c / self._species.mass_ev


# ATen's bilinear grid-sampler backward deposits cloud-in-cell images (its input
# gradient) and differentiates them (its grid gradient), as in
# diffaccel.dynamics.images.cic_image; arguments: bilinear, zero padding,
# align_corners=False
_grid_sampler_backward = torch.ops.aten.grid_sampler_2d_backward
_SAMPLER = (0, 0, False)


class LinearScreenImages:
    """Screen images through fixed linear maps for a fixed number of particles.

    The training fast path of :meth:`ScreenForwardModel.images_linear` (same
    images: cloud-in-cell deposition, then the Gaussian blur, sum = fraction on
    the screen): everything that does not change between steps (the maps in
    normalised screen coordinates, the blur matrices, the deposit weights) is
    prepared once, and one call is a handful of kernels with fixed shapes and no
    host synchronisation: one batched product gives every image's sampler
    coordinates, ATen's grid-sampler backward deposits all images at once, two
    products blur them; the hand-written backward runs the same kernels in
    reverse.

    Args:
        forward: The scan's forward model (screen geometry and blur).
        maps: Linear maps to the screen ``(K, 6, 6)``, or affine ``(K, 7, 7)``
            (last column: offsets [m]).
        n: Number of particles of every call.
        dims: Coordinates the particles carry (4: ``z = pz = 0``; 6: all).
        dtype: Floating dtype of particles and images.
        device: Device of particles and images.
        total: Number of particles of the whole beam when each process images
            its share of ``n`` (the images of all shares then sum to the beam's);
            default ``n``.

    Shapes:
        ``__call__(particles (n, dims))`` -> ``(K, H, W)``.
    """

    def __init__(
        self,
        forward: ScreenForwardModel,
        maps: Tensor,
        n: int,
        dims: int,
        *,
        dtype: torch.dtype = torch.float32,
        device: str | torch.device | None = None,
        total: int | None = None,
    ) -> None:
        scr = forward.screen
        h, w = scr.shape
        psx, psy = scr.pixel_size
        cx, cy = scr.center
        maps = maps.to(dtype=torch.float64, device="cpu")
        k = maps.shape[0]
        rows = maps[:, [0, 2], :dims]  # (K, 2, D)
        if maps.shape[-1] == 7:
            shift = maps[:, [0, 2], 6]
        else:
            shift = torch.zeros(k, 2, dtype=torch.float64)
        # sampler coordinates (align_corners=False): the screen spans [-1, 1]
        s = torch.tensor([2.0 / (psx * w), 2.0 / (psy * h)], dtype=torch.float64)
        centre = torch.tensor([cx, cy], dtype=torch.float64)
        kw = {"dtype": dtype, "device": device}
        self.g = (rows * s[:, None]).transpose(1, 2).contiguous().to(**kw)
        self.g_t = self.g.transpose(1, 2).contiguous()
        self.offset = ((shift - centre) * s).unsqueeze(1).to(**kw)  # (K, 1, 2)
        # 1.5 pixels beyond the edges all four corners are off the screen:
        # such particles deposit nothing and get no gradient (as in cic_image)
        self.lo = torch.tensor([-1.0 - 3.0 / w, -1.0 - 3.0 / h], **kw)
        self.hi = torch.tensor([1.0 + 3.0 / w, 1.0 + 3.0 / h], **kw)
        weight = 1.0 / (n if total is None else total)
        # per-step tensors in the shapes the kernels take, made once (the step budget
        # counts every ATen op of a step, views and implicit copies included):
        # the deposit weights contiguous (the sampler would copy an expanded
        # tensor), the offsets expanded to all particles, the blur matrices
        # expanded to all images
        self.per_particle = torch.full((k, 1, 1, n), weight, **kw)
        self.template = torch.empty((), **kw).expand(k, 1, h, w)
        self.offset_n = self.offset.expand(k, n, 2)
        self.shape = (k, h, w)
        self.n = n
        blur = forward._blur()
        self.by = self.bx_t = None
        if isinstance(blur, Tensor):  # one blur per image: (K, H, H), (K, W, W)
            zero = torch.zeros_like(blur[:, 0])
            eye_h = torch.eye(h, dtype=torch.float64).expand(k, h, h)
            eye_w = torch.eye(w, dtype=torch.float64).expand(k, w, w)
            sy = torch.stack([zero, blur[:, 1]], -1)
            sx = torch.stack([blur[:, 0], zero], -1)
            self.by = gaussian_blur(eye_h, sy, (psx, psy)).to(**kw)
            self.bx_t = gaussian_blur(eye_w, sx, (psx, psy)).to(**kw)
            self.by_k = self.by.contiguous()
            self.bx_t_k = self.bx_t.contiguous()
            self.by_t_k = self.by.transpose(1, 2).contiguous()
            self.bx_k = self.bx_t.transpose(1, 2).contiguous()
        elif blur is not None:
            # the blur of dynamics.images.gaussian_blur as two matrices: blurring
            # the identity in one direction gives that direction's matrix
            eye_h = torch.eye(h, dtype=torch.float64)[None]
            eye_w = torch.eye(w, dtype=torch.float64)[None]
            self.by = gaussian_blur(eye_h, (0.0, blur[1]), (psx, psy))[0].to(**kw)
            self.bx_t = gaussian_blur(eye_w, (blur[0], 0.0), (psx, psy))[0].to(**kw)
            self.by_k = self.by.expand(k, h, h)
            self.bx_t_k = self.bx_t.expand(k, w, w)
            self.by_t_k = self.by.t().expand(k, h, h)
            self.bx_k = self.bx_t.t().expand(k, w, w)

    def __call__(self, particles: Tensor) -> Tensor:
        return _LinearCIC.apply(particles, self)


class _LinearCIC(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: Tensor, spec: LinearScreenImages) -> Tensor:  # type: ignore[override]
        k, h, w = spec.shape
        grid = torch.baddbmm(spec.offset_n, x.expand(k, *x.shape), spec.g)
        grid = torch.clamp_(grid, spec.lo, spec.hi).view(k, 1, spec.n, 2)
        image = _grid_sampler_backward(
            spec.per_particle, spec.template, grid, *_SAMPLER, [True, False]
        )[0].view(k, h, w)
        if spec.by is not None:
            image = torch.bmm(torch.bmm(spec.by_k, image), spec.bx_t_k)
        ctx.save_for_backward(grid)
        ctx.spec = spec
        return image

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None]:  # type: ignore[override]
        (grid,) = ctx.saved_tensors
        spec = ctx.spec
        k, h, w = spec.shape
        if spec.by is not None:  # adjoint of by @ image @ bx_t
            grad = torch.bmm(torch.bmm(spec.by_t_k, grad), spec.bx_k)
        g = _grid_sampler_backward(
            spec.per_particle,
            grad.view(k, 1, h, w),
            grid,
            *_SAMPLER,
            [False, True],
        )[1]
        return torch.bmm(g.view(k, spec.n, 2), spec.g_t).sum(0), None


def _select_rows(coords: Coords, rows: Tensor) -> Coords:
    """The rows ``rows`` of every batched ``(U, N)`` column (``(N,)`` ones as is)."""
    return tuple(  # type: ignore[return-value]
        c if c is None or c.dim() < 2 else c.index_select(0, rows) for c in coords
    )


def _stages(
    spec: list[dict[str, Any]],
    names: list[str],
    distinct: Tensor,
    device: str | torch.device,
) -> list[tuple[Tensor | None, Beamline]]:
    """The shared elements ``spec`` in parts, each at its distinct settings rows.

    ``names`` are the scanned parameters of these elements, ``distinct`` their
    distinct rows ``(U, P)`` (sorted, as ``torch.unique`` gives them). A part
    begins at the first element and at each element with a scanned parameter;
    its rows are the distinct rows of the parameters up to its end. See
    :class:`SharedUpstream`.
    """
    elements = [e["name"] for e in spec]
    acts_at = [elements.index(n.rsplit(".", 1)[0]) for n in names]
    starts = sorted({0, *acts_at})
    stages: list[tuple[Tensor | None, Beamline]] = []
    previous: Tensor | None = None  # each of the U rows' row in the previous part
    for a, b in zip(starts, [*starts[1:], len(spec)], strict=True):
        cols = [p for p, at in enumerate(acts_at) if at < b]
        part = Beamline.from_spec(spec[a:b])
        index = None
        if cols:
            uniq, inverse = torch.unique(distinct[:, cols], dim=0, return_inverse=True)
            part = part.with_params(
                {names[p]: uniq[:, j] for j, p in enumerate(cols) if acts_at[p] >= a}
            )
            if previous is not None:
                # one of the U rows of each of this part's rows, and its row
                # in the previous part
                one = torch.empty(len(uniq), dtype=torch.long)
                one.scatter_(0, inverse, torch.arange(len(inverse)))
                index = previous[one]
                if len(index) == int(previous.max()) + 1 and bool(
                    (index == torch.arange(len(index))).all()
                ):
                    index = None
            previous = inverse
        stages.append((None if index is None else index.to(device), part.to(device)))
    return stages


class SharedUpstream:
    """Screen images of several scans that begin with the same elements.

    Scans of one beam often share their first elements and settings: in the AWA
    6D layout both scans pass the same scanned quadrupole, drift and deflecting
    cavity before one goes straight to a screen and the other through a
    spectrometer dipole. Those leading elements are tracked once per call, for
    the distinct rows of their settings over all scans, and each scan then
    tracks only its own remaining elements from there (same arithmetic as
    :meth:`ScreenForwardModel.images`, so the same images).

    Build it with :meth:`build`, which returns None when nothing is shared.
    The beam is tracked as coordinate columns (never stacked into particles
    between the parts), ``z`` only as far as an element needs it, and the
    generated particles are checked once, at the entrance. The shared part
    runs in stages: each element sees only the distinct rows of the settings
    up to it (the quadrupole of the AWA layout its 5 values, not the 10 rows of
    quadrupole x cavity), and the rows are copied out where a later scanned
    element needs more.

    Args:
        stages: The shared leading elements in consecutive parts, each with the
            distinct rows of the settings up to its end applied (``(U_j,)``
            parameters), and the index of each of its rows among the previous
            part's rows (None where the previous part's are already them, or
            where nothing before it is scanned). The last part's rows are the
            ``U`` distinct rows of every shared setting.
        rows: For each scan, the index of each of its settings among the ``U``
            distinct rows; None where they are exactly ``0 .. U - 1``.
        downstream: For each scan, its remaining elements (ending at the
            screen) with that scan's settings applied (``(K_s,)`` parameters).
        forwards: The scans' forward models (screen, blur, ``p0c``, species).

    Shapes:
        ``__call__(particles (N, 6))`` -> one ``(K_s, H_s, W_s)`` image stack per
        scan.
    """

    def __init__(
        self,
        stages: list[tuple[Tensor | None, Beamline]],
        rows: list[Tensor | None],
        downstream: list[Beamline],
        forwards: list[ScreenForwardModel],
    ) -> None:
        self.stages = stages
        self.rows = rows
        self.downstream = downstream
        self.forwards = forwards
        # z leaves a part only if an element after it reads z
        later = any(e.reads_z for line in downstream for e in line.elements)
        self.need_z: list[bool] = []
        for _, part in reversed(stages):
            self.need_z.insert(0, later)
            later = later or any(e.reads_z for e in part.elements)

    @classmethod
    def build(
        cls,
        forwards: Sequence[ScreenForwardModel],
        settings: Sequence[Tensor],
        device: str | torch.device = "cpu",
    ) -> SharedUpstream | None:
        """The shared upstream of ``forwards`` with ``settings``, or None.

        The shared part is the longest run of leading elements (no screen) with
        the same specification in every scan, the same reference momentum and
        species. None when it is empty or when its distinct settings rows are
        as many as all scans' rows together (nothing to save).

        Shapes:
            ``settings[s] (K_s, P_s)``.
        """
        forwards = list(forwards)
        if len(forwards) < 2:
            return None
        first = forwards[0]
        if any(f.p0c != first.p0c or f.species != first.species for f in forwards[1:]):
            return None
        specs = [f.beamline.to_spec() for f in forwards]
        n_shared = 0
        for i in range(min(len(s) for s in specs)):
            spec = specs[0][i]
            if spec["type"] == "Screen" or any(s[i] != spec for s in specs[1:]):
                break
            n_shared = i + 1
        if n_shared == 0:
            return None
        shared = {e["name"] for e in specs[0][:n_shared]}

        def upstream_name(name: str) -> bool:
            return name.rsplit(".", 1)[0] in shared

        up_names = [n for n in first.names if upstream_name(n)]
        if any(
            sorted(n for n in f.names if upstream_name(n)) != sorted(up_names)
            for f in forwards
        ):
            return None
        checked = [
            f.check_settings(s).cpu() for f, s in zip(forwards, settings, strict=True)
        ]
        up_values = [
            s[:, [f.names.index(n) for n in up_names]]
            for f, s in zip(forwards, checked, strict=True)
        ]
        stacked = torch.cat(up_values)
        if up_names:
            distinct, inverse = torch.unique(stacked, dim=0, return_inverse=True)
        else:
            distinct, inverse = stacked[:1], torch.zeros(len(stacked), dtype=torch.long)
        if len(distinct) >= len(stacked) and up_names:
            return None
        stages = _stages(specs[0][:n_shared], up_names, distinct, device)
        rows, downstream = [], []
        start = 0
        for f, spec, s in zip(forwards, specs, checked, strict=True):
            k = s.shape[0]
            idx = inverse[start : start + k]
            start += k
            identity = k == len(distinct) and bool((idx == torch.arange(k)).all())
            rows.append(None if identity else idx.to(device))
            own = Beamline.from_spec(spec[n_shared:])
            own_names = [n for n in f.names if not upstream_name(n)]
            own = own.with_params({n: s[:, f.names.index(n)] for n in own_names})
            downstream.append(own.to(device))
        return cls(stages, rows, downstream, forwards)

    def __call__(self, particles: Tensor) -> list[Tensor]:
        check_particles(particles)
        p0c = as_p0c(self.forwards[0].p0c, particles)
        species = self.forwards[0]._species
        at: Coords = tuple(particles.unbind(-1))  # type: ignore[assignment]
        for (index, part), need_z in zip(self.stages, self.need_z, strict=True):
            if index is not None:
                at = _select_rows(at, index)
            at = part.track_columns(at, p0c, species, need_z=need_z)
        images = []  # at: columns (U, N) or (N,)
        scans = zip(self.rows, self.downstream, self.forwards, strict=True)
        for rows, line, fwd in scans:
            start = at if rows is None else _select_rows(at, rows)
            screens = line.images_of_columns(
                start, p0c, species, method="cic", blur_sigma=fwd._blur()
            )
            images.append(screens[fwd.screen.name])
        return images


def _six_columns(x: Tensor) -> Tensor:
    """Particles ``(N, D)`` with ``z = pz = 0`` appended up to ``(N, 6)``."""
    return torch.nn.functional.pad(x, (0, 6 - x.shape[1]))


class ScanImages:
    """Every scan's simulated images of one training sample.

    With ``dims = 4`` (``pz = 0`` exactly) a scan whose affine maps are exact
    (see :meth:`ScreenForwardModel.linear_maps`: no cavity on, no bend) images
    through them (:class:`LinearScreenImages`); the other scans, and every
    scan with ``dims = 6``, track exactly (chromatic quadrupoles, RF curvature
    of a deflecting cavity, bends), the leading elements that they share (AWA
    6D layout: quadrupole, drift, cavity, drift) once per call, each element
    for the distinct settings up to it, and ``z`` only as far as an element
    reads it (:class:`SharedUpstream`; the same images as tracking each scan).

    Args:
        forwards: Forward model of each scan.
        settings: Settings of each scan ``(K_s, P_s)``.
        maps: Each scan's :meth:`ScreenForwardModel.transfer_maps` of its
            settings where the caller has computed them (not computed again),
            or None.
        dims: Coordinates the particles carry (4: ``z = pz = 0``; 6: all).
        n: Particles of every call.
        device: Device of particles and images.
        total: Particles of the whole beam when each process images its share
            of ``n`` (every image is then weighted by ``n / total``, so that
            the shares' images sum to the beam's); None for the whole beam.

    Shapes:
        ``__call__(particles (n, dims))`` -> scan ``s``: ``(K_s, H_s, W_s)``.
    """

    def __init__(
        self,
        forwards: Sequence[ScreenForwardModel],
        settings: Sequence[Tensor],
        maps: Sequence[Tensor | None] | None,
        dims: int,
        n: int,
        device: torch.device,
        total: int | None = None,
    ) -> None:
        imagers: list[Any] = []
        map_list = [None] * len(forwards) if maps is None else list(maps)
        for f, s, r in zip(forwards, settings, map_list, strict=True):
            lin = f.linear_maps(s, monochromatic=True, maps=r) if dims == 4 else None
            if lin is not None:
                imagers.append(
                    LinearScreenImages(f, lin, n, dims, device=device, total=total)
                )
            else:
                imagers.append(None)
        self.tracked = [i for i, im in enumerate(imagers) if im is None]
        self.shared = SharedUpstream.build(
            [forwards[i] for i in self.tracked],
            [settings[i] for i in self.tracked],
            device,
        )
        if self.shared is None:
            for i in self.tracked:
                f, s = forwards[i], settings[i]
                imagers[i] = lambda x, f=f, s=s: f.images(_six_columns(x), s)
        self.imagers = imagers
        self.weight = None if total is None else n / total

    def __call__(self, x: Tensor) -> list[Tensor]:
        """Every scan's simulated images of the particles ``x``."""
        out = [None if im is None else im(x) for im in self.imagers]
        if self.shared is not None:
            for i, image in zip(
                self.tracked, self.shared(_six_columns(x)), strict=True
            ):
                out[i] = image
        if self.weight is not None:
            w, tracked = self.weight, self.tracked
            out = [o if i not in tracked else o * w for i, o in enumerate(out)]
        return out  # type: ignore[return-value]
