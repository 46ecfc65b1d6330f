"""Preprocessing of raw screen images of a quad scan.

Every function takes a :class:`~diffaccel.data.QuadScanDataset` and returns a new
one (the input is never modified) with the step and its parameters appended to
``metadata["preprocessing"]``. A typical chain for raw camera frames::

    ds = subtract_background(ds, dark=dark_frame)     # or the edge estimate
    ds = median_filter(ds, size=3)
    ds = threshold(ds, method="triangle")
    ds = crop_to_beam(ds, n_rms=4.0)
    ds = pool(ds, factor=2)
    ds = normalize(ds)

Pixel intensities are in arbitrary camera units until :func:`normalize`.

Background-subtracted images keep their negative pixels (the zero-mean noise
around the true level): :func:`subtract_background`, :func:`median_filter`,
:func:`center_centroids`, :func:`crop_to_beam` and :func:`pool` are linear or
noise-symmetric and leave that noise signed, so image moments and the
reconstruction's image term (which accept signed pixels) stay unbiased.
Clipping the noise at zero instead leaves a positive floor under the whole
image that widens the second moments (``subtract_background(clip=True)``
does it on request). :func:`threshold` zeroes pixels by design: it removes
the noise and also the halo below the threshold, which narrows the beam.
"""

from __future__ import annotations

import math
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from diffaccel.data.quad_scan import QuadScanDataset

__all__ = [
    "average_shots",
    "center_centroids",
    "crop_to_beam",
    "image_centroids",
    "median_filter",
    "normalize",
    "pool",
    "subtract_background",
    "threshold",
    "triangle_threshold",
]


def _check(ds: QuadScanDataset) -> None:
    if not isinstance(ds, QuadScanDataset):
        raise TypeError(f"expected a QuadScanDataset; got {type(ds).__name__}")


def _positive_images(images: Tensor, step: str, clip: bool = True) -> Tensor:
    """Clamp at zero if ``clip``; raise if a whole image vanished or its sum is
    not positive (nothing left to fit)."""
    if clip:
        images = images.clamp_min(0.0)
    empty = (images <= 0).flatten(2).all(dim=-1)
    if bool(empty.any()):
        k, s = (int(v) for v in torch.nonzero(empty)[0])
        raise ValueError(
            f"{step}: image of setting {k} (shot {s}) is all zero afterwards; "
            "use a weaker setting"
        )
    sums = images.sum(dim=(-2, -1), dtype=torch.float64)
    if bool((sums <= 0).any()):
        k, s = (int(v) for v in torch.nonzero(sums <= 0)[0])
        raise ValueError(
            f"{step}: image of setting {k} (shot {s}) sums to "
            f"{float(sums[k, s]):g} afterwards (no beam above the background?)"
        )
    return images


# ---------------------------------------------------------------- background
def subtract_background(
    ds: QuadScanDataset,
    dark: Tensor | None = None,
    edge_pixels: int = 4,
    clip: bool = False,
) -> QuadScanDataset:
    """Remove the camera background; the noise stays signed unless ``clip``.

    Without clipping the result is unbiased: where there is no beam, pixels
    scatter around 0 (negative and positive) and their contribution to image
    moments and to the reconstruction's image term averages out. Clipping at 0
    keeps only the positive half of that noise, a floor under the whole image
    that inflates rms sizes (and emittances) by tens of percent on a camera
    frame where the beam fills a small part of the image.

    Args:
        ds: Dataset with raw images.
        dark: Dark frame [camera units] broadcastable to (K, S, H, W), e.g. (H, W)
            or (K, S, H, W). When ``None``, the background of each image is the
            median of a border band ``edge_pixels`` wide (the beam must not
            touch the border).
        edge_pixels: Width of the border band used by the edge estimate [pixels].
        clip: Clamp negative pixels to 0 afterwards (biased; see above).

    Returns:
        New dataset; the step records the method, ``clip`` and the mean level
        removed.

    Raises:
        ValueError: if ``dark`` does not broadcast, contains NaN/inf, the band
            is wider than half the image, or an image is all zero or sums to
            <= 0 afterwards.
    """
    _check(ds)
    images = ds.images
    h, w = ds.screen_shape
    if dark is not None:
        dark = torch.as_tensor(dark, dtype=images.dtype, device=images.device)
        try:
            level = torch.broadcast_to(dark, images.shape)
        except RuntimeError as err:
            raise ValueError(
                f"dark: shape {tuple(dark.shape)} does not broadcast to images "
                f"{tuple(images.shape)}"
            ) from err
        if not bool(torch.isfinite(dark).all()):
            raise ValueError("dark: expected finite values; found NaN/inf")
        step = {"step": "subtract_background", "method": "dark"}
    else:
        if not 1 <= edge_pixels <= min(h, w) // 2:
            raise ValueError(
                f"edge_pixels: expected 1 ... {min(h, w) // 2} for {h}x{w} images; "
                f"got {edge_pixels}"
            )
        e = edge_pixels
        band = torch.cat(
            [
                images[..., :e, :].flatten(-2),
                images[..., -e:, :].flatten(-2),
                images[..., e:-e, :e].flatten(-2),
                images[..., e:-e, -e:].flatten(-2),
            ],
            dim=-1,
        )
        level = band.median(dim=-1).values[..., None, None]
        step = {"step": "subtract_background", "method": "edge", "edge_pixels": e}
    step["clip"] = bool(clip)
    step["mean_level"] = float(level.mean())
    out = _positive_images(images - level, "subtract_background", clip=clip)
    return ds.with_step(step, images=out)


# ---------------------------------------------------------------- threshold
def triangle_threshold(image: Tensor, bins: int = 256) -> Tensor:
    """Triangle-method threshold of each image (Zack, Rogers & Latt 1977).

    The histogram of pixel values is joined by a line from its peak to its far
    end; the threshold is the bin edge farthest below that line.

    Args:
        image: Images, shape (*B, H, W).
        bins: Number of histogram bins.

    Returns:
        Thresholds of shape (*B,) in the units of ``image``.
    """
    flat = image.flatten(-2).reshape(-1, image.shape[-2] * image.shape[-1])
    out = flat.new_empty(flat.shape[0])
    for b, values in enumerate(flat):
        lo, hi = float(values.min()), float(values.max())
        if hi <= lo:
            out[b] = hi
            continue
        hist = torch.histc(values.float(), bins=bins, min=lo, max=hi).double()
        peak = int(hist.argmax())
        # the far end is the side of the peak with the longer tail
        end = bins - 1 if (bins - 1 - peak) >= peak else 0
        idx = torch.arange(bins, dtype=torch.float64)
        x0, y0, x1, y1 = float(peak), float(hist[peak]), float(end), float(hist[end])
        # distance of each histogram point below the peak-end line
        dist = ((y1 - y0) * idx - (x1 - x0) * hist + x1 * y0 - y1 * x0).abs()
        lo_i, hi_i = sorted((peak, end))
        sel = dist[lo_i : hi_i + 1]
        level = lo_i + int(sel.argmax())
        # threshold at the upper edge of the chosen bin (on the tail side)
        edge = level + (1 if end > peak else 0)
        out[b] = lo + (hi - lo) * edge / bins
    return out.reshape(image.shape[:-2])


def threshold(
    ds: QuadScanDataset,
    method: Literal["triangle", "fraction", "absolute"] = "triangle",
    value: float | None = None,
    subtract: bool = False,
    bins: int = 256,
) -> QuadScanDataset:
    """Zero every pixel at or below a threshold.

    Args:
        ds: Dataset.
        method: ``"triangle"`` (per image, from the histogram; ``value``
            multiplies it, default 1), ``"fraction"`` (``value`` times each
            image's maximum) or ``"absolute"`` (``value`` in image units).
        value: See ``method``.
        subtract: Also subtract the threshold from the pixels above it.
        bins: Histogram bins of the triangle method.

    Returns:
        New dataset; the step records the method and the mean threshold.

    Raises:
        ValueError: for an unknown method, a missing or negative ``value``, or
            an image left all zero.
    """
    _check(ds)
    images = ds.images
    if method == "triangle":
        factor = 1.0 if value is None else float(value)
        level = triangle_threshold(images, bins=bins) * factor
    elif method == "fraction":
        if value is None or not 0 <= value < 1:
            raise ValueError(f"threshold: fraction must be in [0, 1); got {value}")
        level = images.flatten(-2).amax(dim=-1) * float(value)
    elif method == "absolute":
        if value is None or not math.isfinite(value):
            raise ValueError(f"threshold: absolute value required; got {value}")
        level = torch.full(images.shape[:2], float(value), dtype=images.dtype)
    else:
        raise ValueError(
            f"threshold: method must be 'triangle', 'fraction' or 'absolute'; "
            f"got {method!r}"
        )
    level = level.to(images)[..., None, None]
    out = torch.where(images > level, images - level if subtract else images, 0.0)
    out = _positive_images(out, "threshold")
    step = {
        "step": "threshold",
        "method": method,
        "value": value,
        "subtract": subtract,
        "mean_threshold": float(level.mean()),
    }
    return ds.with_step(step, images=out)


# ---------------------------------------------------------------- median filter
def median_filter(ds: QuadScanDataset, size: int = 3) -> QuadScanDataset:
    """Replace each pixel by the median of its ``size x size`` neighbourhood.

    Removes isolated hot pixels; borders are reflected. Signed (background-
    subtracted) pixels stay signed: the median of zero-mean noise is ~0.

    Args:
        ds: Dataset.
        size: Odd window width [pixels], >= 3 and smaller than the image.

    Returns:
        New dataset.
    """
    _check(ds)
    h, w = ds.screen_shape
    if size < 3 or size % 2 == 0 or size > min(h, w):
        raise ValueError(
            f"median_filter: size must be odd, >= 3 and <= {min(h, w)}; got {size}"
        )
    k, s = ds.images.shape[:2]
    r = size // 2
    x = F.pad(ds.images.reshape(k * s, 1, h, w), (r, r, r, r), mode="reflect")
    windows = F.unfold(x, kernel_size=size)  # (K*S, size*size, H*W)
    out = windows.median(dim=1).values.reshape(k, s, h, w)
    out = _positive_images(out, "median_filter", clip=False)
    return ds.with_step({"step": "median_filter", "size": size}, images=out)


# ---------------------------------------------------------------- centroids
def image_centroids(images: Tensor) -> Tensor:
    """Intensity-weighted centroids of images in pixel units.

    Args:
        images: Non-negative images, shape (*B, H, W).

    Returns:
        (*B, 2) tensor of (row, column) centroids [pixels], row 0 = first row.
    """
    h, w = images.shape[-2:]
    rows = torch.arange(h, dtype=images.dtype, device=images.device)
    cols = torch.arange(w, dtype=images.dtype, device=images.device)
    total = images.sum(dim=(-2, -1))
    ci = (images.sum(dim=-1) * rows).sum(dim=-1) / total
    cj = (images.sum(dim=-2) * cols).sum(dim=-1) / total
    return torch.stack([ci, cj], dim=-1)


def _shift(images: Tensor, shifts: Tensor) -> Tensor:
    """Shift images by (rows, cols) sub-pixel amounts, bilinear, zero fill.

    images (B, H, W), shifts (B, 2); content moves to higher indices for
    positive shifts.
    """
    b, h, w = images.shape
    theta = images.new_zeros(b, 2, 3)
    theta[:, 0, 0] = 1.0
    theta[:, 1, 1] = 1.0
    # affine_grid works in normalised [-1, 1] coordinates (align_corners=True)
    theta[:, 0, 2] = -2.0 * shifts[:, 1] / max(w - 1, 1)
    theta[:, 1, 2] = -2.0 * shifts[:, 0] / max(h - 1, 1)
    grid = F.affine_grid(theta, [b, 1, h, w], align_corners=True)
    out = F.grid_sample(
        images[:, None], grid, mode="bilinear", padding_mode="zeros", align_corners=True
    )
    return out[:, 0]


_CENTERING_ITERATIONS = 5
_CENTERING_TOLERANCE_PX = 1e-4


def center_centroids(
    ds: QuadScanDataset, mode: Literal["each", "common"] = "each"
) -> QuadScanDataset:
    """Move image centroids to the image centre (sub-pixel, bilinear).

    Args:
        ds: Dataset with background-free images.
        mode: ``"each"`` centres every image on its own centroid (removes the
            centroid motion over the scan, which a centred beam model then
            does not have to explain); ``"common"`` applies one shift, the
            mean centroid of all images, so the motion is kept.

    The shift is refined up to five times so that centroids land on the centre
    even when part of an image is pushed off the border (that part is lost).

    Returns:
        New dataset; the step records the applied shifts [pixels].
    """
    _check(ds)
    if mode not in ("each", "common"):
        raise ValueError(
            f"center_centroids: mode must be 'each' or 'common'; got {mode!r}"
        )
    k, s, h, w = ds.shape
    flat = ds.images.reshape(k * s, h, w).double()
    target = torch.tensor([(h - 1) / 2, (w - 1) / 2], dtype=torch.float64)
    shifts = torch.zeros(k * s, 2, dtype=torch.float64)
    shifted = flat
    # intensity pushed off the border moves the centroid of what remains, so
    # refine the shift of the original image a few times (Newton-like steps)
    for _ in range(_CENTERING_ITERATIONS):
        error = target - image_centroids(shifted)
        if mode == "common":
            error = error.mean(dim=0, keepdim=True).expand_as(error)
        if float(error.abs().max()) < _CENTERING_TOLERANCE_PX:
            break
        shifts = shifts + error
        shifted = _shift(flat, shifts)
    out = shifted.to(ds.images.dtype).reshape(k, s, h, w)
    out = _positive_images(out, "center_centroids", clip=False)
    step = {
        "step": "center_centroids",
        "mode": mode,
        "shifts_pixels": [[round(float(v), 4) for v in row] for row in shifts],
    }
    return ds.with_step(step, images=out)


# ---------------------------------------------------------------- cropping
def crop_to_beam(
    ds: QuadScanDataset,
    n_rms: float = 4.0,
    shape: tuple[int, int] | None = None,
) -> QuadScanDataset:
    """Crop all images to one window around the beam.

    The window is centred on the mean centroid of all images; by default its
    half-widths are ``n_rms`` times the largest rms extent over images, per
    plane. The same window is used for every image (one screen geometry), and
    ``center`` is updated so pixel coordinates stay physical.

    Args:
        ds: Dataset with background-free images.
        n_rms: Half-width of the window in rms extents.
        shape: Explicit window (H', W') [pixels] instead of ``n_rms``.

    Returns:
        New dataset of images (K, S, H', W').
    """
    _check(ds)
    h, w = ds.screen_shape
    # the window (not the kept pixel values) from the images clipped at 0:
    # signed noise far from the beam could make an rms extent imaginary
    imgs = ds.images.double().clamp_min(0.0)
    cent = image_centroids(imgs)  # (K, S, 2)
    rows = torch.arange(h, dtype=torch.float64)
    cols = torch.arange(w, dtype=torch.float64)
    total = imgs.sum(dim=(-2, -1))
    var_i = (imgs.sum(-1) * (rows - cent[..., :1]) ** 2).sum(-1) / total
    var_j = (imgs.sum(-2) * (cols - cent[..., 1:]) ** 2).sum(-1) / total
    ci, cj = (float(v) for v in cent.reshape(-1, 2).mean(dim=0))
    if shape is None:
        if not n_rms > 0:
            raise ValueError(f"crop_to_beam: n_rms must be > 0; got {n_rms}")
        half_i = n_rms * float(var_i.max().sqrt())
        half_j = n_rms * float(var_j.max().sqrt())
        hh = min(h, 2 * math.ceil(half_i) + 1)
        ww = min(w, 2 * math.ceil(half_j) + 1)
    else:
        hh, ww = (int(v) for v in shape)
        if not (1 <= hh <= h and 1 <= ww <= w):
            raise ValueError(
                f"crop_to_beam: shape must be within 1..({h}, {w}); got {shape}"
            )
    i0 = min(max(round(ci - (hh - 1) / 2), 0), h - hh)
    j0 = min(max(round(cj - (ww - 1) / 2), 0), w - ww)
    out = ds.images[..., i0 : i0 + hh, j0 : j0 + ww]
    out = _positive_images(out, "crop_to_beam", clip=False)
    px, py = ds.pixel_size
    center = (
        ds.center[0] + (j0 + (ww - 1) / 2 - (w - 1) / 2) * px,
        ds.center[1] + (i0 + (hh - 1) / 2 - (h - 1) / 2) * py,
    )
    step = {
        "step": "crop_to_beam",
        "n_rms": None if shape is not None else n_rms,
        "window": [i0, i0 + hh, j0, j0 + ww],
        "kept_fraction": float(out.sum() / ds.images.sum()),
    }
    return ds.with_step(step, images=out.contiguous(), center=center)


# ---------------------------------------------------------------- pooling
def pool(ds: QuadScanDataset, factor: int | tuple[int, int] = 2) -> QuadScanDataset:
    """Downsample by summing blocks of pixels; the pixel size grows by ``factor``.

    Images are zero-padded at the high-index end to a multiple of the factor,
    so the total intensity is conserved exactly; ``center`` is updated.

    Args:
        ds: Dataset.
        factor: Block size [pixels], one int or (rows, cols).

    Returns:
        New dataset with images (K, S, ceil(H/fy), ceil(W/fx)) and pixel size
        (fx * px, fy * py); a recorded ``resolution_pixels`` r becomes
        ``sqrt(r^2 + (f^2 - 1) / 12) / f`` in the new pixels (summing f pixels
        adds a box of f pixels in place of one; f the mean of fx and fy).
    """
    _check(ds)
    fy, fx = (factor, factor) if isinstance(factor, int) else factor
    if fy < 1 or fx < 1:
        raise ValueError(f"pool: factor must be >= 1; got {factor}")
    k, s, h, w = ds.shape
    hp, wp = math.ceil(h / fy) * fy, math.ceil(w / fx) * fx
    x = F.pad(ds.images, (0, wp - w, 0, hp - h))
    out = x.reshape(k, s, hp // fy, fy, wp // fx, fx).sum(dim=(3, 5))
    px, py = ds.pixel_size
    center = (
        ds.center[0] + ((wp - 1) / 2 - (w - 1) / 2) * px,
        ds.center[1] + ((hp - 1) / 2 - (h - 1) / 2) * py,
    )
    step = {"step": "pool", "factor": [fy, fx]}
    res = ds.resolution_pixels
    if res is not None:
        f = 0.5 * (fx + fy)
        res = math.sqrt(res**2 + (f**2 - 1.0) / 12.0) / f
    return ds.with_step(
        step,
        images=out,
        pixel_size=(px * fx, py * fy),
        center=center,
        resolution_pixels=res,
    )


# ---------------------------------------------------------------- normalisation
def normalize(ds: QuadScanDataset) -> QuadScanDataset:
    """Scale every image (each shot) to unit sum.

    Returns:
        New dataset with ``images.sum((-2, -1)) == 1``.
    """
    _check(ds)
    total = ds.images.sum(dim=(-2, -1), keepdim=True)
    if bool((total <= 0).any()):
        raise ValueError("normalize: an image has a non-positive sum")
    return ds.with_step({"step": "normalize"}, images=ds.images / total)


def average_shots(ds: QuadScanDataset) -> QuadScanDataset:
    """Average the shots of each setting into one image.

    Returns:
        New dataset with images (K, 1, H, W).
    """
    _check(ds)
    step = {"step": "average_shots", "n_shots": ds.n_shots}
    return ds.with_step(step, images=ds.images.mean(dim=1, keepdim=True))
