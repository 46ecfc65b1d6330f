"""Fit-quality alarms: what a finished reconstruction already tells about its inputs.

A reconstruction that cannot reproduce its data still returns moments. The
signals below are computed from what the fit already has (the measured
training images, the reconstruction's images at the same settings and the
scans' first-order transfer maps); each alarm names the likely causes in the
order of likelihood for *its* signal.

Signals (:func:`fit_signals`):

- ``image_l1``: relative L1 of each training image (``sum|m - p| / sum m``);
  per scan its mean.
- ``moment_residual``: rms over the training images of the relative misses of
  the second moments, measured minus predicted: ``d<xx>/<xx>``,
  ``d<yy>/<yy>``, ``d<xy>/sqrt(<xx><yy>)`` (both images in a box of 4
  predicted rms around the predicted centroid, as the uncertainty analysis
  does, the forward model's point spread beyond the data's removed first).
- ``moment_residual_one_beam``: what is left of those misses after the best
  linear change of one beam's covariance (every scan together; the moment
  design of :mod:`~diffaccel.reconstruction.uncertainty`), and
  ``moment_residual_per_scan``: after a change of its own for every scan.
  Small after the change: a beam that fits the moments exists and the
  training did not reach it; large: no beam does (something the beamline
  model lacks). One beam far worse than one change per scan: the scans
  disagree with each other.
- ``edge_level``: per image, the brightest point of the measured image along
  its outermost two rows or columns (a 5-pixel running mean along the edge)
  over its peak; with ``edge_flatness`` (least over largest along that edge:
  near 1 for a uniform background, near 0 for a beam cut by the edge).
- ``floor_share``: per image, the share of its intensity on a floor, the
  level of its dimmest edge (the median along the edge of its outermost rows
  or columns, signed) times its pixels over its sum: a pedestal, an
  unsubtracted background or noise clipped at zero.
- 4D through z or pz: the scans' first-order maps to the screen's x and y
  have a z or pz column (``ensemble.unconstrained_coordinates`` does not list
  it), while a 4D reconstruction sets z = pz = 0.

Thresholds, measured with ``benchmarks/alarms.py``: 20 good 4D fits of
synthetic scans (presets gaussian, correlated, nonlinear; KDE, cloud-in-cell
and histogram images; Poisson noise up to 3 % at the peak; one, two and three
scans; 2000 particles, 300 steps), bad fits of each pattern, and the shared
benchmark files fitted with the defaults (4D: ``gpsr_4d_synthetic.h5``,
``awa_quad_scan_train.h5``; 6D: ``sixd_synthetic_train.h5``):

- :data:`MOMENT_MISS_RAW` (misses as they are): good synthetic fits 0.4-1.9 %
  rms, the shared 6D file 0.24 %, the GPSR 4D file 0.37 %, the AWA
  measurement 6.2 % (its images are thresholded: their tails are cut, the
  fit's are not); a mislabelled setting 36 %, settings shuffled against
  their images 91 %, a 4D fit through a cavity 34 %.
- :data:`MOMENT_MISS` (left after the best linear change of the beam): good
  fits at most 1.6 %, the shared files at most 4.6 % (AWA); the bad fits of
  one scan 31-77 %.
- :data:`INCONSISTENT_RATIO` and :data:`INCONSISTENT_LEVEL`: one beam over one
  beam per scan on the two- and three-scan good fits 0.86-1.14 (the shared 6D
  file 0.97), with at most 1.1 % left; a scan's quadrupole length doubled,
  a copy of another scan's images, one of three scans with a 40 % wrong pixel
  size, a 4D fit of a cavity and dipole layout: 30-180x, 8.8-27 % left. On
  the shared 6D file (120 steps, 4096 particles): the dipole-on scan's
  quadrupole doubled 14x (40 % left), its images a copy of the dipole-off
  scan's 2.4x (17 % left).
- :data:`OUTLIER_RATIO` and :data:`OUTLIER_L1`: the worst training image of a
  good fit is at most 2.8x the median (relative L1 at most 0.27; the shared
  files 1.7x (6D), 2.0x (AWA), 2.8x (GPSR 4D)); an image recorded at another
  setting only 2.4x (L1 0.76): the image and moment terms bend the beam
  toward it. Its second moments stand out: the miss left at that image after
  the best linear change of the beam (``moment_left``) is 82 %, 8.9x the
  median image's, where good fits leave at most 2.5 % at any image (ratios
  up to 14x at such small misses; the shared files at most 7.5 %, AWA, 2.9x
  its median) and shuffled settings miss every image alike (2.4x). A
  training image is listed when its L1 stands out (:data:`OUTLIER_RATIO` x
  the median and :data:`OUTLIER_L1`) or its ``moment_left`` does
  (:data:`OUTLIER_RATIO` x the median and :data:`MOMENT_MISS`); the images
  of a scan that disagrees with the others are listed too.
- :data:`EDGE_LEVEL`: good synthetic fits below 0.001, the GPSR 4D and 6D
  files at most 0.015; a 4-row band of the screen through the beam 0.71. The
  AWA measurement's strongest setting reaches 0.28 (its beam runs past the
  first rows), one image of 11: hence :data:`EDGE_SHARE`.

- :data:`FLOOR_SHARE`: 0 on the good synthetic fits, the shared files,
  noise-free camera frames and background-subtracted frames with read noise
  (``benchmarks/background_bias.py``'s, signed: the noise is not a floor); the
  same frames with negative pixels clipped at 0 (screen rms +100-180 %)
  4.7-5.3 %; a pedestal of 0.1 % of the peak 18 % (128 x 128 pixels), of 1 %
  69 %, of 10 % 96 %. A fit reproduces a pedestal with a halo, so no fit
  signal sees it (10 % of the peak: moments 11 %, 1.5 % after the best change
  of the beam, edge 0.09).

Known limit (in the benchmark too): a single scan in the wrong units (fitted
by another beam; no fit signal sees it) stays quiet.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from diffaccel.data.quad_scan import QuadScanDataset
from diffaccel.data.scans import MultiScanDataset
from diffaccel.reconstruction.ensemble import Reconstruction, unconstrained_coordinates
from diffaccel.reconstruction.forward import ScreenForwardModel
from diffaccel.reconstruction.pipeline import as_scans, psf_excess
from diffaccel.reconstruction.screen_moments import covariance_design, pair_indices
from diffaccel.reconstruction.uncertainty import (
    image_moments,
    linear_posterior,
    moment_window,
)

__all__ = [
    "EDGE_LEVEL",
    "FLOOR_SHARE",
    "INCONSISTENT_LEVEL",
    "INCONSISTENT_RATIO",
    "MOMENT_MISS",
    "MOMENT_MISS_RAW",
    "OUTLIER_L1",
    "OUTLIER_RATIO",
    "FitAlarm",
    "ScanFit",
    "dataset_maps",
    "fit_alarms",
    "fit_signals",
    "floor_share",
    "longitudinal_alarm",
    "poor_fit_causes",
    "prediction_alarms",
    "scan_fits",
    "scan_floor_share",
]

#: Rms relative miss of the training images' second moments left after the
#: best linear change of the beam above which the fit is reported as not
#: reproducing them (no beam does).
MOMENT_MISS = 0.08
#: The same for the misses as they are (before any change of the beam).
MOMENT_MISS_RAW = 0.2
#: One beam's moment residual over one change per scan's, above which (with
#: :data:`INCONSISTENT_LEVEL`) the scans are reported as disagreeing.
INCONSISTENT_RATIO = 2.0
#: One beam's moment residual (rms, relative) needed for that report.
INCONSISTENT_LEVEL = 0.06
#: A training image's relative L1 over the median of the others above which
#: (with :data:`OUTLIER_L1`) it is reported as standing out; per scan the same
#: ratio of its mean over the median of the other scans' means.
OUTLIER_RATIO = 4.0
#: Relative L1 an outlying image (or scan) must also exceed.
OUTLIER_L1 = 0.2
#: Brightness along a screen edge over the image's peak above which the beam
#: is reported as touching that edge.
EDGE_LEVEL = 0.15
#: Share of a scan's images that must be bright at an edge for the warning:
#: one cut image among many leaves the beam to the other settings (the shared
#: AWA measurement's strongest setting of 11 reaches 0.28: its beam runs past
#: the first rows).
EDGE_SHARE = 0.25
#: Least over largest brightness along the edge above which the brightness is
#: read as a uniform background rather than a beam cut by the edge.
FLAT_EDGE = 0.5
#: Share of a measured image's intensity on a floor (:func:`floor_share`,
#: median over a scan's images) above which the images are reported as
#: sitting on a pedestal or background.
FLOOR_SHARE = 0.02
#: Measured intensity outside the moment box beyond the predicted (a fraction
#: of the image) above which a background is named first among the causes.
HALO_EXCESS = 0.05
#: Box of the moments, in predicted rms around the predicted centroid.
WINDOW_SIGMA = 4.0
#: A z or pz column of the maps to screen x/y above this fraction of the x or
#: px column makes the screen see that coordinate (as
#: :func:`~diffaccel.reconstruction.ensemble.unconstrained_coordinates`).
LONGITUDINAL_TOLERANCE = 1e-3
#: Element types whose maps can make the screen see z or pz.
LONGITUDINAL_TYPES = ("TransverseDeflectingCavity", "Dipole", "LinearMap")

#: Most settings or scans named in one warning.
_MAX_LISTED = 6

_UNDERFIT = (
    "training too short or with too few particles (more steps or particles)",
    "a prior that holds the beam back (longitudinal_scale, unseen_weight)",
    "a generator too small for the beam (width, depth)",
)
_NO_BEAM = (
    "background or a pedestal left in the images (subtract it)",
    "the beam clipped by the screen or its region of interest",
    "a camera point spread unlike the model's (blur_pixels)",
    "a beamline, screen calibration or beam energy (p0c) that is not the measurement's",
)
_INCONSISTENT = (
    "one scan's beamline or settings not those of its file (an element length, "
    "a setting's units or scale, the drift to its screen)",
    "one scan's images belonging to another scan or measurement (copied, "
    "swapped or from another file)",
    "screen calibrations (pixel size, centre) other than recorded",
    "scans taken of different beams (energy, charge, machine state)",
)
_OUTLIER_SCAN = (
    "that scan's beamline or settings not those of its file (an element "
    "length, a setting's units or scale)",
    "its screen calibration (pixel size, centre)",
    "its images of another beam or machine state (a cavity or dipole not as recorded)",
    "background or a pedestal in its images only",
)
_OUTLIER_SETTING = (
    "the image recorded at another setting than the one listed (a mislabelled "
    "or lagging magnet)",
    "a bad shot (beam trip, saturation, a camera glitch)",
    "background or a pedestal in that image only",
    "the beam partly off the screen at that setting",
)
_EDGE_BEAM = (
    "a screen region of interest too small or cropped too tightly",
    "settings that make the beam larger than the screen (weak focusing)",
    "a screen centre (center_x, center_y) off the beam",
)
_FLOOR = (
    "background or a pedestal not subtracted (subtract background frames or "
    "the camera's black level)",
    "a beam larger than the screen in every direction (weaker focusing, a "
    "larger screen)",
)
_EDGE_FLAT = (
    "background or a pedestal not subtracted (the edge is uniformly bright)",
    "a screen region of interest cropped into the beam",
)
_POOR_FIT_DEFAULT = (
    "settings in the wrong units or scale (e.g. k1 in 1/m^2 vs T/m or a current)",
    "a beamline that is not the measurement's (element lengths, order, drift "
    "to the screen)",
    "a wrong screen calibration (pixel size, centre)",
    "a wrong beam energy (p0c)",
)


@dataclass(frozen=True)
class FitAlarm:
    """One fit-quality warning.

    Attributes:
        kind: ``"moment_miss"``, ``"inconsistent_scans"``, ``"outlier_scan"``,
            ``"outlier_setting"``, ``"screen_edge"``, ``"background"`` or
            ``"longitudinal_4d"``.
        message: What was measured, one sentence without the causes.
        causes: Likely causes, the most likely first.
        value: The signal (dimensionless).
        threshold: The level it was warned above.
        scans: The scans concerned.
    """

    kind: str
    message: str
    causes: tuple[str, ...]
    value: float
    threshold: float
    scans: tuple[str, ...] = ()

    def text(self) -> str:
        """The warning as one line: the message, then the causes in order."""
        return (
            f"{self.message}; likely causes, most likely first: "
            + "; ".join(f"({i}) {c}" for i, c in enumerate(self.causes, 1))
            + "."
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {
            "kind": self.kind,
            "message": self.message,
            "causes": list(self.causes),
            "value": self.value,
            "threshold": self.threshold,
            "scans": list(self.scans),
        }


@dataclass
class ScanFit:
    """What one scan's fit knows: its images, predictions and maps.

    Attributes:
        name: Scan name.
        measured: Measured training images, unit sum ``(K, H, W)``.
        predicted: The reconstruction's images at the same settings ``(K, H, W)``.
        maps: First-order maps of those settings ``(K, 7, 7)`` (float64).
        xs: Pixel-centre x [m] ``(W,)``; ``ys``: y [m] ``(H,)``.
        train_indices: The settings' indices in the scan ``(K,)``.
        all_measured: Every measured image of the scan (training and held
            out) ``(K_all, H, W)`` for the edge check; default ``measured``.
        psf_excess: Variance ``(x, y)`` [m^2] the model's point spread adds
            beyond the data's (``pipeline.psf_excess``).
    """

    name: str
    measured: Tensor
    predicted: Tensor
    maps: Tensor
    xs: Tensor
    ys: Tensor
    train_indices: Sequence[int] = ()
    all_measured: Tensor | None = None
    psf_excess: tuple[float, float] = (0.0, 0.0)


def _relative_moment_misses(fit: ScanFit) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``(misses (K, 3), residual (3K,), scale (3K,), halo (K,))``: relative
    misses of ``<xx>, <xy>, <yy>`` per image, the raw residuals with their
    scales (the rows of
    :func:`~diffaccel.reconstruction.screen_moments.covariance_design`), and the
    measured intensity outside the moment box less the predicted (a background
    the beam does not explain shows there). Scales are the predicted variances
    plus one pixel^2 (a beam smaller than a pixel has no resolved size)."""
    pred = fit.predicted.detach().to("cpu", torch.float64)
    meas = fit.measured.detach().to("cpu", torch.float64)
    win = moment_window(pred, fit.xs, fit.ys, WINDOW_SIGMA)
    mm = image_moments(meas, fit.xs, fit.ys, win)
    pm = image_moments(pred, fit.xs, fit.ys, win)
    pm[:, 2] -= fit.psf_excess[0]
    pm[:, 4] -= fit.psf_excess[1]
    px2 = float(fit.xs[1] - fit.xs[0]) ** 2 if fit.xs.numel() > 1 else 0.0
    py2 = float(fit.ys[1] - fit.ys[0]) ** 2 if fit.ys.numel() > 1 else 0.0
    sxx = pm[:, 2].clamp_min(0) + px2
    syy = pm[:, 4].clamp_min(0) + py2
    sxy = (sxx * syy).clamp_min(1e-300).sqrt()
    res = mm[:, 2:] - pm[:, 2:]  # <xx>, <xy>, <yy>
    scale = torch.stack([sxx, sxy, syy], -1).clamp_min(1e-300)

    def outside(img: Tensor) -> Tensor:
        pos = img.clamp_min(0)
        total = pos.sum((-2, -1)).clamp_min(1e-300)
        return 1.0 - (pos * win).sum((-2, -1)) / total

    halo = outside(meas) - outside(pred)
    return res / scale, res.reshape(-1), scale.reshape(-1), halo


def _fit_residual(
    designs: Sequence[Tensor],
    residuals: Sequence[Tensor],
    scales: Sequence[Tensor],
    cov: Tensor,
    dims: int,
) -> tuple[list[float], Tensor]:
    """``(r, left)``: rms relative residual per group after the best linear
    covariance change common to all groups (degrees of freedom counted as in
    :func:`~diffaccel.reconstruction.uncertainty.linear_posterior`), and the
    relative misses left per image after that change, rms over its ``<xx>,
    <xy>, <yy>`` rows ``(K_total,)``."""
    sd = cov.diagonal()[:dims].clamp_min(1e-300).sqrt()
    prior = torch.tensor(
        [
            float(sd[i] ** 2) if i == j else 0.5 * float(sd[i] * sd[j])
            for i, j in pair_indices(dims)
        ],
        dtype=torch.float64,
    )
    groups = torch.cat([torch.full((r.numel(),), g) for g, r in enumerate(residuals)])
    design, residual, scale = (torch.cat(list(t)) for t in (designs, residuals, scales))
    _, shift, r, _ = linear_posterior(design, residual, scale, prior, groups)
    left = ((residual - design @ shift) / scale).reshape(-1, 3)
    return [float(v) for v in r], left.square().mean(1).sqrt()


def _edge_profiles(img: Tensor, dy: int, dx: int) -> tuple[Tensor, ...]:
    """Mean of the outermost ``dy`` rows (first, last) and ``dx`` columns
    (first, last) of images ``(K, H, W)``: four profiles ``(K, W)`` or ``(K, H)``,
    in the order of :data:`_SIDES`."""
    h, w = img.shape[-2:]
    return (
        img[:, :dy, :].mean(1),
        img[:, h - dy :, :].mean(1),
        img[:, :, :dx].mean(2),
        img[:, :, w - dx :].mean(2),
    )


def _edge_levels(images: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Per image: ``(level, flatness, side)`` of its brightest edge.

    ``level``: largest running mean (5 pixels) along the outermost two rows or
    columns of an edge, over the image's peak; ``flatness``: least over largest
    of that running mean along the same edge; ``side``: 0 bottom (first row),
    1 top (last row), 2 left (first column), 3 right (last column).
    """
    img = images.detach().to("cpu", torch.float64).clamp_min(0)
    _, h, w = img.shape
    peak = img.amax((-2, -1)).clamp_min(1e-300)
    profiles = _edge_profiles(img, 2 if h >= 8 else 1, 2 if w >= 8 else 1)
    levels, flats = [], []
    for prof in profiles:
        n = prof.shape[-1]
        span = min(5, n)
        smooth = torch.nn.functional.avg_pool1d(prof[:, None], span, stride=1)[:, 0]
        top = smooth.amax(-1)
        levels.append(top / peak)
        flats.append(smooth.amin(-1) / top.clamp_min(1e-300))
    level = torch.stack(levels, -1)  # (K, 4)
    flat = torch.stack(flats, -1)
    best, side = level.max(-1)
    return best, flat.gather(-1, side[:, None])[:, 0], side


def floor_share(images: Tensor) -> Tensor:
    """Per image ``(K,)``: the share of its intensity that its floor carries.

    The floor is the level of the image's dimmest edge: each edge's level is
    the median, along the edge, of the signed mean of its outermost rows or
    columns (an eighth of the screen, 1 to 4 of them). Zero-mean noise (a
    background-subtracted camera frame) averages out, a beam cut by an edge
    raises that edge only, and a pedestal, an unsubtracted background or noise
    clipped at zero raises all four. A level within two standard errors of
    zero (the edge's spread) counts as 0. The share is that level times the
    number of pixels over the image's sum: the intensity a uniform floor
    spreads over the frame, which the second moments weight by the squared
    distance from the beam.

    Example:
        >>> im = torch.zeros(1, 16, 16); im[0, 6:10, 6:10] = 1.0
        >>> floor_share(im + 0.01)  # 0.01 * 256 of 16 + 2.56
        tensor([0.1379], dtype=torch.float64)
    """
    img = images.detach().to("cpu", torch.float64)
    _, h, w = img.shape
    edges = _edge_profiles(img, max(1, min(4, h // 8)), max(1, min(4, w // 8)))
    levels = torch.stack([e.median(-1).values for e in edges], -1)  # (K, 4)
    # standard error of each median (1.25 std / sqrt(n) for Gaussian noise)
    errors = torch.stack(
        [1.2533 * e.std(-1) / math.sqrt(e.shape[-1]) for e in edges], -1
    )
    level, side = levels.min(-1)
    # a floor within 2 standard errors of 0 is noise, not a floor (all four
    # edges above 2 errors by chance: ~3e-7 per image)
    level = torch.where(level > 2 * errors.gather(-1, side[:, None])[:, 0], level, 0.0)
    return level * (h * w) / img.sum((-2, -1)).clamp_min(1e-300)


_SIDES = (
    "bottom (first row)",
    "top (last row)",
    "left (first column)",
    "right (last column)",
)


def fit_signals(fits: Sequence[ScanFit], cov: Tensor, dims: int) -> dict[str, Any]:
    """The fit-quality signals of the module docstring.

    Args:
        fits: One :class:`ScanFit` per scan with training images.
        cov: The reconstruction's covariance ``(6, 6)`` [Bmad units] (scales
            the linear moment fit).
        dims: Reconstructed coordinates (4 or 6).

    Returns:
        JSON-ready dict: ``moment_residual``, ``moment_residual_one_beam``,
        ``moment_residual_per_scan`` (pooled rms, relative),
        ``moment_left_worst`` and ``moment_left_worst_ratio`` (the training
        image missed most after the one-beam change, and over the median
        image), ``image_l1_worst`` and ``image_l1_worst_ratio``, and per scan
        ``scans[name]``: ``image_l1`` (per training image), ``moment_residual``,
        ``moment_residual_one_beam``, ``moment_residual_own_beam``,
        ``moment_left`` (per training image, rms relative miss left after the
        one-beam change), ``edge_level``, ``edge_flatness``, ``edge_side``
        and ``floor_share`` (per image of ``all_measured``).
    """
    cov = cov.to(torch.float64)
    out: dict[str, Any] = {"scans": {}}
    designs, residuals, scales, misses = [], [], [], []
    for fit in fits:
        m = fit.measured.detach().to("cpu", torch.float64)
        p = fit.predicted.detach().to("cpu", torch.float64)
        l1 = (m - p).abs().sum((-2, -1)) / m.sum((-2, -1)).clamp_min(1e-300)
        miss, res, scale, halo = _relative_moment_misses(fit)
        design = covariance_design(fit.maps.to(torch.float64)[:, :6, :6], dims)
        designs.append(design)
        residuals.append(res)
        scales.append(scale)
        misses.append(miss)
        every = fit.measured if fit.all_measured is None else fit.all_measured
        level, flat, side = _edge_levels(every)
        out["scans"][fit.name] = {
            "image_l1": l1.tolist(),
            "train_indices": [int(i) for i in fit.train_indices]
            or list(range(m.shape[0])),
            "moment_residual": float(miss.square().mean().sqrt()),
            "halo_excess": float(halo.mean()),
            "edge_level": level.tolist(),
            "edge_flatness": flat.tolist(),
            "edge_side": side.tolist(),
            "floor_share": floor_share(every).tolist(),
        }
    if not fits:
        return out
    allm = torch.cat(misses)
    out["moment_residual"] = float(allm.square().mean().sqrt())
    out["halo_excess"] = max(s["halo_excess"] for s in out["scans"].values())
    l1 = [v for s in out["scans"].values() for v in s["image_l1"]]
    med = float(torch.tensor(l1).median())
    out["image_l1_worst"] = max(l1)
    out["image_l1_worst_ratio"] = max(l1) / max(med, 1e-12)
    one, left = _fit_residual(designs, residuals, scales, cov, dims)
    own = [
        _fit_residual([d], [r], [s], cov, dims)[0][0]
        for d, r, s in zip(designs, residuals, scales, strict=True)
    ]
    n = torch.tensor([float(r.numel()) for r in residuals], dtype=torch.float64)
    pool = lambda v: float(  # noqa: E731
        (torch.tensor(v, dtype=torch.float64).square() * n).sum().div(n.sum()).sqrt()
    )
    out["moment_residual_one_beam"] = pool(one)
    out["moment_residual_per_scan"] = pool(own)
    out["moment_left_worst"] = float(left.max())
    out["moment_left_worst_ratio"] = float(left.max() / left.median().clamp_min(1e-12))
    lefts = left.split([r.numel() // 3 for r in residuals])
    for fit, a, b, c in zip(fits, one, own, lefts, strict=True):
        out["scans"][fit.name]["moment_residual_one_beam"] = a
        out["scans"][fit.name]["moment_residual_own_beam"] = b
        out["scans"][fit.name]["moment_left"] = c.tolist()
    return out


def _median_of_others(values: Sequence[float], i: int) -> float:
    others = [v for j, v in enumerate(values) if j != i]
    return float(torch.tensor(others).median()) if others else math.nan


def fit_alarms(
    signals: Mapping[str, Any], *, longitudinal: FitAlarm | None = None
) -> list[FitAlarm]:
    """The alarms the signals of :func:`fit_signals` raise (empty: a good fit).

    Raises one alarm per pattern at most: scans that disagree
    (:data:`INCONSISTENT_RATIO`, :data:`INCONSISTENT_LEVEL`; two or more
    scans) or else the moments missed (:data:`MOMENT_MISS`), a scan or a
    training image whose image error stands out (:data:`OUTLIER_RATIO`,
    :data:`OUTLIER_L1`), measured images bright at a screen edge
    (:data:`EDGE_LEVEL`), measured images on a floor (:data:`FLOOR_SHARE`).
    The causes of the moment alarms are ordered by the
    other signals: a cut beam (edge), a background (measured intensity
    outside the beam's box beyond the prediction's by more than
    :data:`HALO_EXCESS`), a beam the training did not reach (the linear
    change fits them), or none that fits. ``longitudinal``: the
    :func:`longitudinal_alarm` of the training scans, if any; its remedy then
    comes first in every cause list.
    """
    scans = signals.get("scans", {})
    alarms: list[FitAlarm] = []
    names = list(scans)
    one = signals.get("moment_residual_one_beam")
    own = signals.get("moment_residual_per_scan")
    total = signals.get("moment_residual")
    edge = _edge_alarm(scans)
    first: tuple[str, ...] = ()
    if longitudinal is not None:
        first += (longitudinal.causes[0],)
    if edge is not None:
        first += (edge.causes[0],)
    if (signals.get("halo_excess") or 0.0) > HALO_EXCESS:
        first += (_NO_BEAM[0],)
    inconsistent = (
        len(names) >= 2
        and one is not None
        and one > INCONSISTENT_LEVEL
        and one > INCONSISTENT_RATIO * max(own, 1e-12)
    )
    if inconsistent:
        per = ", ".join(
            f"{n!r} {100 * scans[n]['moment_residual_one_beam']:.1f} % "
            f"({100 * scans[n]['moment_residual_own_beam']:.1f} % alone)"
            for n in names
        )
        alarms.append(
            FitAlarm(
                "inconsistent_scans",
                "the scans disagree with each other: the best single beam "
                f"misses their image second moments by {100 * one:.1f} % rms, "
                f"a beam of its own per scan by {100 * own:.1f} % (per scan: "
                f"{per}; warned above {INCONSISTENT_RATIO:g}x and "
                f"{100 * INCONSISTENT_LEVEL:.0f} %), so no one beam fits them "
                "all and the moments are not a measurement",
                _ordered(first, _INCONSISTENT),
                one / max(own, 1e-12),
                INCONSISTENT_RATIO,
                tuple(names),
            )
        )
    elif total is not None and (
        total > MOMENT_MISS_RAW or (one is not None and one > MOMENT_MISS)
    ):
        reachable = one is not None and one < 0.5 * total
        detail = (
            f"the best linear change of the beam would leave {100 * one:.1f} %"
            if reachable
            else f"no change of the beam fits them much better "
            f"({100 * (one or total):.1f} % left)"
        )
        per = ", ".join(
            f"{n!r} {100 * scans[n]['moment_residual']:.1f} %" for n in names
        )
        if len(names) >= 2 and one is not None and one > 1.5 * max(own, 1e-12):
            first += _INCONSISTENT[:2]  # one beam fits the scans worse than each
        rest = _UNDERFIT + _NO_BEAM if reachable and not first else _NO_BEAM + _UNDERFIT
        alarms.append(
            FitAlarm(
                "moment_miss",
                "the training images' second moments are missed by "
                f"{100 * total:.1f} % rms (per scan: {per}; warned above "
                f"{100 * MOMENT_MISS_RAW:.0f} %, or above "
                f"{100 * MOMENT_MISS:.0f} % left after the best change of the "
                f"beam: good fits leave under ~1 %); {detail}",
                _ordered(first, rest),
                total,
                MOMENT_MISS,
                tuple(names),
            )
        )
    alarms += _outlier_alarms(scans)
    if edge is not None:
        alarms.append(edge)
    floor = _floor_alarm(scans)
    if floor is not None:
        alarms.append(floor)
    return alarms


def scan_floor_share(scan: Mapping[str, Any]) -> float | None:
    """Median over a scan's images of their :func:`floor_share` (``scan``: one
    scan's entry of :func:`fit_signals`); None without images."""
    shares = scan.get("floor_share")
    return float(torch.tensor(shares).median()) if shares else None


def _floor_alarm(scans: Mapping[str, Any]) -> FitAlarm | None:
    """Scans whose measured images sit on a floor: :func:`scan_floor_share`
    above :data:`FLOOR_SHARE`."""
    shares = {n: scan_floor_share(s) for n, s in scans.items()}
    hits = {n: v for n, v in shares.items() if v is not None and v > FLOOR_SHARE}
    if not hits:
        return None
    per = ", ".join(f"{n!r} {100 * v:.1f} %" for n, v in hits.items())
    return FitAlarm(
        "background",
        "the measured images sit on a floor: all four screen edges stay bright, "
        "and the floor carries a share of each image's intensity (median over "
        f"the scan: {per}; warned above {100 * FLOOR_SHARE:g} %); the fit "
        "takes the floor for beam (a wide halo), which biases the sizes and "
        "emittances",
        _FLOOR,
        max(hits.values()),
        FLOOR_SHARE,
        tuple(hits),
    )


def _ordered(first: Sequence[str], rest: Sequence[str]) -> tuple[str, ...]:
    """``first`` then ``rest``, each cause once."""
    return tuple(dict.fromkeys((*first, *rest)))


def _outlier_alarms(scans: Mapping[str, Any]) -> list[FitAlarm]:
    names = list(scans)
    out: list[FitAlarm] = []
    means = [float(torch.tensor(scans[n]["image_l1"]).mean()) for n in names]
    if len(names) >= 3:
        bad = [
            i
            for i, v in enumerate(means)
            if v > OUTLIER_L1 and v > OUTLIER_RATIO * _median_of_others(means, i)
        ]
        if bad:
            i = max(bad, key=lambda j: means[j])
            ref = _median_of_others(means, i)
            out.append(
                FitAlarm(
                    "outlier_scan",
                    f"scan {names[i]!r}'s training images stand out: relative "
                    f"L1 {means[i]:.3g} against a median {ref:.3g} of the other "
                    f"scans (warned above {OUTLIER_RATIO:g}x and {OUTLIER_L1:g})",
                    _OUTLIER_SCAN,
                    means[i] / max(ref, 1e-12),
                    OUTLIER_RATIO,
                    (names[i],),
                )
            )
    pooled = [float(v) for n in names for v in scans[n]["image_l1"]]
    pooled_left = [float(v) for n in names for v in scans[n].get("moment_left", [])]
    if len(pooled) < 4:
        return out
    med = float(torch.tensor(pooled).median())
    med_left = float(torch.tensor(pooled_left).median()) if pooled_left else math.inf
    listed = []
    worst = 0.0
    for n in names:
        idx = scans[n]["train_indices"]
        left = scans[n].get("moment_left", [0.0] * len(idx))
        for k, (v, w) in enumerate(zip(scans[n]["image_l1"], left, strict=True)):
            by_l1 = v > OUTLIER_L1 and v > OUTLIER_RATIO * med
            by_moments = w > MOMENT_MISS and w > OUTLIER_RATIO * med_left
            if by_l1 or by_moments:
                listed.append((n, idx[k], v, w))
                r_l1 = v / max(med, 1e-12) if by_l1 else 0.0
                r_moments = w / max(med_left, 1e-12) if by_moments else 0.0
                worst = max(worst, r_l1, r_moments)
    if listed:
        where = ", ".join(
            f"scan {n!r} setting {k} (L1 {v:.3g}, moments {100 * w:.0f} %)"
            for n, k, v, w in listed[:_MAX_LISTED]
        )
        if len(listed) > _MAX_LISTED:
            where += f" and {len(listed) - _MAX_LISTED} more"
        out.append(
            FitAlarm(
                "outlier_setting",
                f"{len(listed)} training image(s) stand out from the others: "
                f"{where}, against a median relative L1 of {med:.3g} and a "
                f"median second-moment miss of {100 * med_left:.1f} % left after "
                "the best change of the beam (warned above "
                f"{OUTLIER_RATIO:g}x the median and L1 {OUTLIER_L1:g}, or moments "
                f"{100 * MOMENT_MISS:.0f} %)",
                _OUTLIER_SETTING,
                worst,
                OUTLIER_RATIO,
                tuple(dict.fromkeys(n for n, *_ in listed)),
            )
        )
    return out


def _edge_alarm(scans: Mapping[str, Any]) -> FitAlarm | None:
    hits = []
    for n, s in scans.items():
        cut = [
            (n, k, lev, flat, side)
            for k, (lev, flat, side) in enumerate(
                zip(s["edge_level"], s["edge_flatness"], s["edge_side"], strict=True)
            )
            if lev > EDGE_LEVEL
        ]
        if len(cut) >= EDGE_SHARE * len(s["edge_level"]):
            hits += cut
    if not hits:
        return None
    worst = max(hits, key=lambda h: h[2])
    flat = sum(h[3] > FLAT_EDGE for h in hits) > len(hits) / 2
    where = ", ".join(
        f"scan {n!r} setting {k} {_SIDES[side].split(' ')[0]} {lev:.2f}"
        for n, k, lev, _, side in hits[:_MAX_LISTED]
    )
    if len(hits) > _MAX_LISTED:
        where += f" and {len(hits) - _MAX_LISTED} more"
    what = (
        "uniformly bright along the edge"
        if flat
        else "the beam is cut by the edge, so its size and emittance come out too small"
    )
    return FitAlarm(
        "screen_edge",
        f"measured images are bright at a screen edge in {len(hits)} image(s): "
        f"{where} (brightness along the edge over the image's peak; beams well "
        f"inside stay below ~0.06, warned above {EDGE_LEVEL:g}): {what}",
        _EDGE_FLAT + _EDGE_BEAM[:1] if flat else _EDGE_BEAM + _EDGE_FLAT[:1],
        worst[2],
        EDGE_LEVEL,
        tuple(dict.fromkeys(h[0] for h in hits)),
    )


def longitudinal_alarm(
    dims: int,
    maps: Mapping[str, Tensor],
    beamline_specs: Mapping[str, Sequence[dict]],
    *,
    what: str = "imaged",
) -> FitAlarm | None:
    """An alarm for a 4D beam (z = pz = 0) imaged where the screen sees z or pz.

    Args:
        dims: The reconstruction's coordinates (only 4 can raise it).
        maps: ``{scan: (K, 7, 7)}`` first-order maps of the settings imaged.
        beamline_specs: ``{scan: element list}`` (names the elements).
        what: Verb of the message (``"imaged"``, ``"trained"``...).

    Returns:
        The alarm, or None (6D, or no first-order z or pz column at any
        setting: a drift and quadrupole line).
    """
    if dims != 4 or not maps:
        return None
    seen: dict[str, list[str]] = {}
    for name, r in maps.items():
        blind = unconstrained_coordinates([r], 6, LONGITUDINAL_TOLERANCE)
        coords = [c for c in ("z", "pz") if c not in blind]
        if coords:
            seen[name] = coords
    if not seen:
        return None
    parts = []
    for name, coords in seen.items():
        elements = [
            f"{e.get('type')} {e.get('name')!r}"
            for e in beamline_specs.get(name, [])
            if e.get("type") in LONGITUDINAL_TYPES
        ]
        on = ", ".join(elements) if elements else "its elements"
        parts.append(f"scan {name!r} ({on}: screen x/y see {' and '.join(coords)})")
    return FitAlarm(
        "longitudinal_4d",
        f"a 4D reconstruction (z = pz = 0 for every particle) is {what} through "
        f"elements that read z or pz: {'; '.join(parts)}; its images leave out "
        "the streak or dispersion these elements give the real beam",
        (
            "the reconstruction is 4D: reconstruct in 6D (--dims 6) to image "
            "through these elements",
            "or predict with them switched off (cavity voltage 0, dipole angle 0)",
        ),
        1.0,
        LONGITUDINAL_TOLERANCE,
        tuple(seen),
    )


def poor_fit_causes(alarms: Sequence[FitAlarm]) -> tuple[str, ...]:
    """Likely causes of training images the fit does not reproduce (relative
    L1 above the poor-fit level), ordered by what the other signals say: a 4D
    beam through z or pz readers, a cut beam or a bright edge, scans that
    disagree, moments a beam could reach (under-training), then the usual
    input errors (units, beamline, calibration, p0c)."""
    kinds = {a.kind: a for a in alarms}
    first: list[str] = []
    if "longitudinal_4d" in kinds:
        first.append(
            "a cavity streak or dispersion that a 4D beam cannot show (--dims 6)"
        )
    if "screen_edge" in kinds:
        first.extend(kinds["screen_edge"].causes[:1])
    if "inconsistent_scans" in kinds:
        first.extend(_INCONSISTENT[:2])
    miss = kinds.get("moment_miss")
    if miss is not None:
        first.extend(miss.causes[:1])
    seen = set()
    ordered = []
    for c in (*first, *_POOR_FIT_DEFAULT, *_NO_BEAM[:1], *_UNDERFIT[:1]):
        if c not in seen:
            seen.add(c)
            ordered.append(c)
    return tuple(ordered)


def scan_fits(
    result: Reconstruction,
    dataset: QuadScanDataset | MultiScanDataset,
    predicted: Mapping[str, Tensor],
    train_indices: Mapping[str, Sequence[int]],
    maps: Mapping[str, Tensor] | None = None,
) -> list[ScanFit]:
    """:class:`ScanFit` of every scan of ``dataset`` with training settings.

    Args:
        result: The reconstruction (its blur per scan).
        dataset: The scans.
        predicted: ``{scan: (K_s, H_s, W_s)}`` images of every setting
            (``evaluation.predict_dataset``).
        train_indices: ``{scan: indices}`` of the training settings.
        maps: ``{scan: (K_s, 7, 7)}`` maps of every setting
            (:func:`dataset_maps`), computed here when None.
    """
    fits = []
    for name, scan in as_scans(dataset):
        train = [int(i) for i in train_indices.get(name, [])]
        if not train:
            continue
        fwd = ScreenForwardModel.from_dataset(
            scan, blur_pixels=result.config.blur_for(scan)
        )
        xs, ys = fwd.screen.pixel_centers(dtype=torch.float64)
        meas = scan.mean_images()
        fits.append(
            ScanFit(
                name=name,
                measured=meas[train],
                predicted=predicted[name][train],
                maps=(
                    fwd.transfer_maps(scan.settings[train])
                    if maps is None
                    else maps[name][train]
                ),
                xs=xs,
                ys=ys,
                train_indices=train,
                all_measured=meas,
                psf_excess=psf_excess(fwd),
            )
        )
    return fits


def dataset_maps(
    dataset: QuadScanDataset | MultiScanDataset,
) -> tuple[dict[str, Tensor], dict[str, list[dict]]]:
    """``({scan: (K_s, 7, 7)}, {scan: beamline spec})`` of every setting of
    every scan (the inputs of :func:`longitudinal_alarm`)."""
    maps, specs = {}, {}
    for name, scan in as_scans(dataset):
        fwd = ScreenForwardModel.from_dataset(scan)
        maps[name] = fwd.transfer_maps(scan.settings)
        specs[name] = list(scan.beamline_spec)
    return maps, specs


def prediction_alarms(
    result: Reconstruction,
    dataset: QuadScanDataset | MultiScanDataset | None = None,
    settings: Tensor | None = None,
) -> list[FitAlarm]:
    """Alarms of a prediction: a 4D result imaged through z or pz readers.

    Args:
        result: The reconstruction.
        dataset: The scans predicted (their beamlines and settings), or None.
        settings: With ``dataset`` None, settings ``(K, P)`` of the result's
            own (first) training beamline.

    Returns:
        The :func:`longitudinal_alarm` (``what="predicted"``) as a list, or [].
    """
    if dataset is not None:
        maps, specs = dataset_maps(dataset)
    else:
        fwd = result.forward
        name = result.scan_names[0]
        maps = {name: fwd.transfer_maps(fwd.check_settings(settings))}
        specs = {name: fwd.beamline.to_spec()}
    alarm = longitudinal_alarm(result.config.dims, maps, specs, what="predicted")
    return [] if alarm is None else [alarm]
