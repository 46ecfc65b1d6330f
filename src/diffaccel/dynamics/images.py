"""Differentiable screen images: cloud-in-cell deposition and Gaussian KDE.

Pixel convention (the quad-scan dataset's): ``image[..., i, j]`` is centred at
``y = center_y + (i - (H - 1) / 2) * pixel_size_y`` and
``x = center_x + (j - (W - 1) / 2) * pixel_size_x`` (row = y ascending,
column = x ascending). A pixel holds the summed particle weight it receives
divided by the total weight (``N`` for unit weights), so the image sum is the
fraction of the beam that lands on the screen; images are never renormalised.
"""

from __future__ import annotations

import math
import os
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor, wait
from typing import TypeVar

import torch
from torch import Tensor

from diffaccel.dynamics._validate import broadcast_shapes, finite_checks_enabled

__all__ = [
    "blur_rms_for_variance",
    "blur_variance",
    "cic_image",
    "gaussian_blur",
    "kde_image",
    "pixel_centers",
]

# exp(-80) = 1.8e-35 is still a normal float32: clamping the exponent there keeps
# CPU float32 arithmetic out of (very slow) denormals at a negligible error.
_MIN_EXPONENT = -80.0
# Kernels are evaluated as exp2(e * log2(e)): torch's vectorised exp2 is about
# four times faster than exp on AVX-512 CPUs and as accurate (1 ulp).
_LOG2_E = 1.0 / math.log(2.0)
# Kernel truncation radius of the KDE, in bandwidths (float64; float32).
_KDE_CUT = 9.0
_KDE_CUT_FLOAT32 = 6.0
_T = TypeVar("_T")


def _pair(value: Sequence[float] | float | Tensor, what: str) -> tuple[float, float]:
    if isinstance(value, Tensor):
        value = value.detach().cpu().reshape(-1).tolist()
    if isinstance(value, int | float):
        value = (float(value), float(value))
    if len(value) != 2:
        raise ValueError(f"{what} must be a pair (x, y); got {value!r}.")
    a, b = float(value[0]), float(value[1])
    if not (math.isfinite(a) and math.isfinite(b)):
        raise ValueError(f"{what} must be finite; got {(a, b)}.")
    return a, b


def _geometry(
    shape: Sequence[int], pixel_size: Sequence[float] | float, center: Sequence[float]
) -> tuple[int, int, float, float, float, float]:
    if len(shape) != 2 or any(int(s) != s or s < 1 for s in shape):
        raise ValueError(f"shape must be (H, W) with positive ints; got {shape!r}.")
    psx, psy = _pair(pixel_size, "pixel_size [m]")
    if psx <= 0 or psy <= 0:
        raise ValueError(f"pixel_size must be > 0 m; got {(psx, psy)}.")
    cx, cy = _pair(center, "center [m]")
    return int(shape[0]), int(shape[1]), psx, psy, cx, cy


def _prepare(
    x: Tensor, y: Tensor, weights: Tensor | None
) -> tuple[Tensor, Tensor, Tensor | None, torch.Size]:
    if not isinstance(x, Tensor) or not isinstance(y, Tensor):
        raise TypeError("x and y must be torch.Tensors shaped (*K, N).")
    if x.dim() < 1 or y.dim() < 1:
        raise ValueError(
            f"x and y must be shaped (*K, N); got {tuple(x.shape)}, {tuple(y.shape)}."
        )
    shapes = [x.shape, y.shape] + ([] if weights is None else [weights.shape])
    try:
        full = broadcast_shapes(*shapes)
    except RuntimeError as err:
        raise ValueError(
            "x, y and weights must broadcast to one shape (*K, N); got shapes "
            f"{', '.join(str(tuple(s)) for s in shapes)}."
        ) from err
    if full[-1] == 0:
        raise ValueError(
            f"x and y hold no particles (N = 0; shape {tuple(full)}); an image "
            "needs at least one particle."
        )
    if weights is not None:
        x, y, weights = torch.broadcast_tensors(x, y, weights.to(x))
    else:
        x, y = torch.broadcast_tensors(x, y)
    _check_finite(x, y)
    batch = x.shape[:-1]
    n = x.shape[-1]
    x = x.reshape(-1, n)
    y = y.reshape(-1, n)
    if weights is not None:
        weights = weights.reshape(-1, n)
    return x, y, weights, batch


def _check_finite(x: Tensor, y: Tensor) -> None:
    """Raise if ``x`` or ``y`` holds a NaN or an infinity (one host sync).

    A sum is one cheap reduction and is non-finite whenever an entry is; only
    then (or if huge finite positions overflow it) is each entry checked.
    """
    if not finite_checks_enabled():  # training on a GPU (see finite_checks)
        return
    with torch.no_grad():
        if bool(torch.isfinite(x.sum() + y.sum())):
            return
        if bool(torch.isfinite(x).all() & torch.isfinite(y).all()):
            return
    raise ValueError(
        "x and y contain NaN or infinite positions (after tracking: particles "
        "lost, e.g. a setting or element too strong for the beam's momentum)."
    )


def pixel_centers(
    shape: Sequence[int],
    pixel_size: Sequence[float] | float,
    center: Sequence[float] = (0.0, 0.0),
    *,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> tuple[Tensor, Tensor]:
    """Pixel-centre coordinates ``(xs, ys)`` [m] of a screen, shapes ``(W,)``, ``(H,)``.

    Example:
        >>> xs, ys = pixel_centers((3, 2), (1.0, 1.0))
        >>> xs.tolist(), ys.tolist()
        ([-0.5, 0.5], [-1.0, 0.0, 1.0])
    """
    h, w, psx, psy, cx, cy = _geometry(shape, pixel_size, center)
    kw = {"dtype": dtype, "device": device}
    xs = cx + (torch.arange(w, **kw) - (w - 1) / 2) * psx
    ys = cy + (torch.arange(h, **kw) - (h - 1) / 2) * psy
    return xs, ys


def _gaussian_matrix(n: int, sigma_px: float | Tensor, like: Tensor) -> Tensor:
    """``(n, n)`` blur matrix, or ``(K, n, n)`` for ``K`` rms values ``(K,)``;
    columns sum to 1 before truncation by the edges."""
    idx = torch.arange(n, dtype=like.dtype, device=like.device)
    d = idx[:, None] - idx[None, :]
    if isinstance(sigma_px, Tensor):
        s = sigma_px.to(dtype=like.dtype, device=like.device).clamp_min(1e-6)
        g = torch.exp(-0.5 * (d / s[:, None, None]).square())
        # the normalising sum over +-(2 n + 800) pixels: 8 rms of any blur up
        # to 100 pixels beyond the screen, without reading sigma back
        r = 2 * n + 800
        full = torch.arange(-r, r + 1, dtype=like.dtype, device=like.device)
        norm = torch.exp(-0.5 * (full / s[:, None]).square()).sum(-1)
        return g / norm[:, None, None]
    g = torch.exp(-0.5 * (d / sigma_px).square())
    r = math.ceil(8 * sigma_px) + n
    full = torch.arange(-r, r + 1, dtype=like.dtype, device=like.device)
    return g / torch.exp(-0.5 * (full / sigma_px).square()).sum()


def blur_variance(sigma_px: Tensor | float) -> Tensor:
    """Variance [pixels^2] of the kernel :func:`gaussian_blur` applies for rms
    ``sigma_px`` [pixels], away from the edges.

    The kernel is the Gaussian sampled at whole pixels and normalised to sum 1,
    so its variance is below ``sigma_px^2`` for rms below about one pixel
    (0.32 instead of 0.33 at 0.58 pixel, 0.002 instead of 0.07 at 0.27 pixel)
    and equal to it beyond. Two blurs meant to differ by a known variance
    (the two sides of an image comparison) must be sized by this, not by
    ``sigma_px^2``: see :func:`blur_rms_for_variance`.

    Shapes: ``sigma_px`` any shape -> the same shape, float64.

    Example:
        >>> round(float(blur_variance(1.0)), 6), round(float(blur_variance(0.27)), 4)
        (1.0, 0.0021)
    """
    s = torch.as_tensor(sigma_px, dtype=torch.float64).clamp_min(1e-6)
    r = math.ceil(8.0 * float(s.max())) + 2 if s.numel() else 2
    k = torch.arange(-r, r + 1, dtype=torch.float64)
    g = torch.exp(-0.5 * (k / s[..., None]).square())
    return (g * k.square()).sum(-1) / g.sum(-1)


def blur_rms_for_variance(variance_px2: Tensor | float) -> Tensor:
    """The rms [pixels] whose :func:`gaussian_blur` kernel has variance
    ``variance_px2`` [pixels^2] (the inverse of :func:`blur_variance`); 0
    where the variance is <= 0.

    Shapes: any shape -> the same shape, float64.

    Example:
        >>> round(float(blur_rms_for_variance(blur_variance(0.3))), 9)
        0.3
    """
    v = torch.as_tensor(variance_px2, dtype=torch.float64)
    lo = torch.zeros_like(v)
    hi = v.clamp_min(0.0).sqrt() + 1.0  # blur_variance(s) <= s^2: a bracket
    for _ in range(60):  # bisection: the variance grows with the rms
        mid = 0.5 * (lo + hi)
        low = blur_variance(mid) < v
        lo, hi = torch.where(low, mid, lo), torch.where(low, hi, mid)
    return torch.where(v > 0, 0.5 * (lo + hi), torch.zeros_like(v))


def gaussian_blur(
    image: Tensor, sigma: Sequence[float] | float, pixel_size: Sequence[float] | float
) -> Tensor:
    """Gaussian blur of images ``(*K, H, W)`` with rms ``sigma`` [m] (x, y).

    ``sigma`` is one pair for all images, or a tensor ``(K, 2)`` of one pair
    per image (images ``(K, H, W)``). Mass blurred past the edge is lost (the
    screen does not see it). Computed as two matrix products, so it is exact
    and differentiable.
    """
    if not isinstance(image, Tensor) or image.dim() < 2:
        got = tuple(image.shape) if isinstance(image, Tensor) else type(image).__name__
        raise ValueError(f"image must be a tensor shaped (*K, H, W); got {got}.")
    if isinstance(sigma, Tensor) and sigma.dim() == 2:
        return _blur_per_image(image, sigma, pixel_size)
    sx, sy = _pair(sigma, "blur_sigma [m]")
    psx, psy = _pair(pixel_size, "pixel_size [m]")
    if sx < 0 or sy < 0:
        raise ValueError(f"blur_sigma must be >= 0 m; got {(sx, sy)}.")
    h, w = image.shape[-2:]
    if sy > 0:
        image = _gaussian_matrix(h, sy / psy, image) @ image
    if sx > 0:
        image = image @ _gaussian_matrix(w, sx / psx, image).transpose(0, 1)
    return image


def _blur_per_image(
    image: Tensor, sigma: Tensor, pixel_size: Sequence[float] | float
) -> Tensor:
    """:func:`gaussian_blur` with one rms pair [m] per image, ``sigma (K, 2)``.

    The values are not read back (this runs in training steps on any device):
    the caller passes finite rms >= 0, as ``ScreenForwardModel`` checks once.
    """
    if image.dim() != 3 or sigma.shape != (image.shape[0], 2):
        raise ValueError(
            f"per-image blur needs images (K, H, W) and sigma (K, 2); got "
            f"{tuple(image.shape)} and {tuple(sigma.shape)}."
        )
    psx, psy = _pair(pixel_size, "pixel_size [m]")
    h, w = image.shape[-2:]
    sig = sigma.detach()
    image = _gaussian_matrix(h, sig[:, 1] / psy, image) @ image
    return image @ _gaussian_matrix(w, sig[:, 0] / psx, image).transpose(-1, -2)


def cic_image(
    x: Tensor,
    y: Tensor,
    shape: Sequence[int],
    pixel_size: Sequence[float] | float,
    center: Sequence[float] = (0.0, 0.0),
    weights: Tensor | None = None,
    blur_sigma: Sequence[float] | float | None = None,
) -> Tensor:
    """Cloud-in-cell (bilinear) screen image of particle positions.

    Each particle spreads its weight over the four nearest pixel centres with
    bilinear weights; parts falling outside the screen are dropped (a particle
    within one pixel outside the edge still gives the edge pixel its share, so the
    image is continuous in the positions). A beam that misses the screen
    entirely gives an all-zero image (never NaN).

    Args:
        x: Horizontal positions [m], shape ``(*K, N)``.
        y: Vertical positions [m], shape ``(*K, N)``.
        shape: ``(H, W)`` pixels.
        pixel_size: ``(pixel_size_x, pixel_size_y)`` [m] or one number.
        center: ``(center_x, center_y)`` of the screen [m].
        weights: Optional particle weights, shape broadcastable to ``(*K, N)``;
            images are divided by the total weight. Default: all ones.
        blur_sigma: Optional rms of a Gaussian blur [m], one number or ``(x, y)``,
            applied after deposition (see :func:`gaussian_blur`).

    Returns:
        Images shaped ``(*K, H, W)`` whose sum is the fraction of the weight on
        the screen.

    Shapes:
        ``x, y``: ``(*K, N)`` -> ``(*K, H, W)``.

    Example:
        >>> x = torch.tensor([0.0, 0.25])
        >>> cic_image(x, torch.zeros(2), (1, 3), 1.0)
        tensor([[0.0000, 0.8750, 0.1250]])
    """
    h, w, psx, psy, cx, cy = _geometry(shape, pixel_size, center)
    x, y, weights, batch = _prepare(x, y, weights)
    b, n = x.shape
    geometry = (
        h,
        w,
        1.0 / psx,
        (w - 1) / 2 - cx / psx,
        1.0 / psy,
        (h - 1) / 2 - cy / psy,
    )
    if weights is None:
        image = _CloudInCell.apply(x, y, geometry)
        total = torch.full((b, 1, 1), float(n), dtype=x.dtype, device=x.device)
    else:
        image = _CloudInCell.apply(x, y, geometry, weights)
        total = weights.sum(-1).reshape(b, 1, 1)
    image = image / total
    if blur_sigma is not None:
        image = gaussian_blur(image, blur_sigma, (psx, psy))
    return image.reshape(*batch, h, w)


# ATen's bilinear grid-sampler backward: its input gradient is exactly a
# cloud-in-cell deposit (the adjoint of bilinear interpolation) and its grid
# gradient is our position gradient. Vectorised, parallel over images, and
# available on every device.
_grid_sampler_backward = torch.ops.aten.grid_sampler_2d_backward
_BILINEAR, _ZEROS_PADDING, _ALIGN_CORNERS = 0, 0, False


class _CloudInCell(torch.autograd.Function):
    """Bilinear deposition of ``(B, N)`` positions on ``(B, H, W)`` pixel centres.

    Cloud-in-cell deposition is the adjoint of bilinear interpolation, so both
    passes are ATen's grid-sampler kernels with zero padding: the forward is the
    input gradient of ``grid_sample`` (each particle's weight scattered to its
    four nearest pixel centres, corners off the screen dropped), the backward is
    its grid gradient (the image gradient interpolated, differentiated along x and
    y). Positions are clamped two pixels beyond the edges: such a particle has all
    four corners off the screen, deposits nothing and gets zero gradient, and the
    sampler never sees huge coordinates.
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx,
        x: Tensor,
        y: Tensor,
        geometry: tuple[int, int, float, float, float, float],
        weights: Tensor | None = None,
    ) -> Tensor:
        h, w, ax, bx, ay, by = geometry
        b, n = x.shape
        # normalised sampler coordinates (align_corners=False): pixel index f
        # maps to (2 f + 1) / W - 1
        scale = (2.0 * ax / w, 2.0 * ay / h)
        grid = x.new_empty(b, 1, n, 2)
        # the offsets filled on the device (new_tensor would copy from the host)
        kw = {"dtype": x.dtype, "device": x.device}
        torch.add(
            torch.full((), (2.0 * bx + 1.0) / w - 1.0, **kw),
            x,
            alpha=scale[0],
            out=grid[:, 0, :, 0],
        )
        torch.add(
            torch.full((), (2.0 * by + 1.0) / h - 1.0, **kw),
            y,
            alpha=scale[1],
            out=grid[:, 0, :, 1],
        )
        torch.clamp_(grid[..., 0], -1.0 - 3.0 / w, 1.0 + 3.0 / w)
        torch.clamp_(grid[..., 1], -1.0 - 3.0 / h, 1.0 + 3.0 / h)
        if weights is None:
            per_particle = x.new_ones(()).expand(b, 1, 1, n)
        else:
            per_particle = weights.reshape(b, 1, 1, n)
        template = x.new_empty(()).expand(b, 1, h, w)
        image = _grid_sampler_backward(
            per_particle,
            template,
            grid,
            _BILINEAR,
            _ZEROS_PADDING,
            _ALIGN_CORNERS,
            [True, False],
        )[0]
        ctx.scale = scale
        ctx.save_for_backward(grid, weights)
        return image.reshape(b, h, w)

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        grid, weights = ctx.saved_tensors
        b, _, n, _ = grid.shape
        h, w = grad.shape[-2:]
        grad = grad.reshape(b, 1, h, w).contiguous()
        gx = gy = gw = None
        if ctx.needs_input_grad[0] or ctx.needs_input_grad[1]:
            if weights is None:
                per_particle = grid.new_ones(()).expand(b, 1, 1, n)
            else:
                per_particle = weights.reshape(b, 1, 1, n)
            g = _grid_sampler_backward(
                per_particle,
                grad,
                grid,
                _BILINEAR,
                _ZEROS_PADDING,
                _ALIGN_CORNERS,
                [False, True],
            )[1]
            if ctx.needs_input_grad[0]:
                gx = g[:, 0, :, 0] * ctx.scale[0]
            if ctx.needs_input_grad[1]:
                gy = g[:, 0, :, 1] * ctx.scale[1]
        if weights is not None and ctx.needs_input_grad[3]:
            gw = torch.grid_sampler_2d(
                grad, grid, _BILINEAR, _ZEROS_PADDING, _ALIGN_CORNERS
            ).reshape(b, n)
        return gx, gy, None, gw


def kde_image(
    x: Tensor,
    y: Tensor,
    shape: Sequence[int],
    pixel_size: Sequence[float] | float,
    center: Sequence[float] = (0.0, 0.0),
    bandwidth: Sequence[float] | float | None = None,
    weights: Tensor | None = None,
) -> Tensor:
    """Gaussian kernel-density screen image, computed separably.

    The pixel value is the Gaussian KDE at the pixel centre times the pixel area,
    ``sum_n w_n N(x_j - x_n; h_x) N(y_i - y_n; h_y) dx dy / sum_n w_n``, evaluated
    as ``Ky^T @ (w * Kx)`` with kernel matrices ``Kx (N, W)``, ``Ky (N, H)``:
    no ``N x H x W`` tensor is formed. Kernel values below ``exp(-cut^2 / 2)``
    of a kernel's peak are dropped (cut 9 bandwidths in float64 -> 2.6e-18, 6 in
    float32 -> 1.5e-8, below its round-off). On the CPU, per image, the shorter
    side of the window of pixels within the cut of some particle gets a kernel
    matrix; along the longer side each particle has a tile of ``2 r + 1`` pixels
    around its nearest one (``r = floor(cut h / pixel + 1/2)``, two
    exponentials per particle), particles are sorted by that pixel and each
    such band of particles adds one product to ``2 r + 1`` rows: the same exact
    values, for a fraction of the work on a wide beam. The gradient is analytic
    (with respect to positions and weights). For a beam much wider than the
    bandwidth and well inside the screen the image sum is close to 1.

    Off the CPU (CUDA) all images are computed at once on the whole screen with
    fixed shapes (particles in chunks of fixed size): no per-image Python loop
    and no host synchronisation from data-dependent windows; same values (the
    window only drops kernel values below the cut). On the CPU the kernels are
    evaluated and used in chunks of particles of about 1 MB (they stay in cache
    between their passes), in a reused workspace (fresh memory costs a page
    fault per 4 KiB on first touch), and the backward recomputes them.

    CPU worker threads: with ``torch.get_num_threads() >= 2``, at least 2 images
    and at least 2^15 particles per image, the images (forward and backward) are
    spread over a reused pool of worker threads, each running torch with one
    intra-op thread, instead of using torch's intra-op threads: the many small
    ops of an image wake the OpenMP team on every call, which costs more than it
    gains (2-core AMD EPYC KVM guest: aten::sub 5x and aten::mm 2.4x slower per
    call at 2 threads than at 1). Each image is computed by the same code with one
    intra-op thread, so results do not depend on the number of workers (they
    equal a 1-thread run bit for bit). The environment variable
    ``DIFFACCEL_KDE_THREADS`` sets it: ``auto`` (default: up to
    ``torch.get_num_threads()`` workers), ``0`` or ``1`` (none: the calling
    thread, with its intra-op threads), or a number of workers. Never used
    under the autograd profiler, while compiling, or for tensor subclasses.

    Args:
        x: Horizontal positions [m], shape ``(*K, N)``.
        y: Vertical positions [m], shape ``(*K, N)``.
        shape: ``(H, W)`` pixels.
        pixel_size: ``(pixel_size_x, pixel_size_y)`` [m] or one number.
        center: ``(center_x, center_y)`` of the screen [m].
        bandwidth: Kernel rms ``h`` [m], one number or ``(h_x, h_y)``;
            default one pixel.
        weights: Optional particle weights broadcastable to ``(*K, N)``.

    Returns:
        Images shaped ``(*K, H, W)``.

    Shapes:
        ``x, y``: ``(*K, N)`` -> ``(*K, H, W)``.

    Example:
        >>> img = kde_image(torch.zeros(1), torch.zeros(1), (5, 5), 1e-3)
        >>> round(img.sum().item(), 3)
        0.982
    """
    h, w, psx, psy, cx, cy = _geometry(shape, pixel_size, center)
    hx, hy = _pair((psx, psy) if bandwidth is None else bandwidth, "bandwidth [m]")
    if hx <= 0 or hy <= 0:
        raise ValueError(f"bandwidth must be > 0 m; got {(hx, hy)}.")
    x, y, weights, batch = _prepare(x, y, weights)
    b, n = x.shape
    xs, ys = pixel_centers((h, w), (psx, psy), (cx, cy), dtype=x.dtype, device=x.device)
    if weights is not None:
        total = weights.sum(-1)
    else:
        total = torch.full((b,), float(n), dtype=x.dtype, device=x.device)
    # Pixels farther than the cut from every particle receive less than
    # exp(-cut^2 / 2) of a particle's peak (float32: 6 -> 1.5e-8, below its
    # round-off; float64: 9 -> 2.6e-18): each image is computed only on the window
    # of rows and columns its particles can reach.
    norm = (psx / (math.sqrt(2 * math.pi) * hx)) * (psy / (math.sqrt(2 * math.pi) * hy))
    if _full_screen_path(x):
        image = _kde_full_screen(x, y, xs, ys, (hx, hy), weights)
        return (image * (norm / total.reshape(b, 1, 1))).reshape(*batch, h, w)
    cut = _KDE_CUT if x.dtype == torch.float64 else _KDE_CUT_FLOAT32
    lo_x, hi_x = _reach(x, hx * cut, psx, cx, w)
    lo_y, hi_y = _reach(y, hy * cut, psy, cy, h)
    x0, y0 = cx - (w - 1) / 2 * psx, cy - (h - 1) / 2 * psy  # first pixel centres
    plans = []
    for i in range(b):
        rows, cols = hi_y[i] - lo_y[i], hi_x[i] - lo_x[i]
        if rows <= 0 or cols <= 0:
            continue
        # tiles along the longer side of the window, the kernel matrix along the
        # shorter one (it costs one kernel value per window pixel and particle)
        if cols < rows:
            plans.append((i, True, lo_x[i], hi_x[i], (y0, psy, h, hy, hx, cut)))
        else:
            plans.append((i, False, lo_y[i], hi_y[i], (x0, psx, w, hx, hy, cut)))
    # widest windows first: the most work, so worker threads finish together
    plans.sort(key=lambda plan: plan[3] - plan[2], reverse=True)
    workers = _image_workers(x, len(plans))
    image = _TileKDE.apply(x, y, xs, ys, plans, weights, workers)
    image = image * (norm / total.reshape(b, 1, 1))
    return image.reshape(*batch, h, w)


# Particles per chunk of the full-screen KDE (fixed shapes: no host sync).
_FULL_CHUNK = 2**15


def _kde_full_screen(
    x: Tensor,
    y: Tensor,
    xs: Tensor,
    ys: Tensor,
    bandwidth: tuple[float, float],
    weights: Tensor | None,
) -> Tensor:
    """Unnormalised KDE of all ``B`` images at once on the whole screen.

    ``image[b] = Ky[b]^T (w Kx[b])`` with kernels over every pixel: shapes depend
    only on ``(B, N, H, W)``, never on the data, so there is no host
    synchronisation and no per-image loop (the GPU path). Particles are taken in
    chunks of a fixed size; the backward recomputes each chunk's kernels.

    Shapes:
        ``x, y, weights (B, N)``, ``xs (W,)``, ``ys (H,)`` -> ``(B, H, W)``.
    """
    return _FullScreenKDE.apply(x, y, xs, ys, bandwidth, weights)


def _full_screen_path(x: Tensor) -> bool:
    """Whether images of ``x`` take the fixed-shape full-screen path (not CPU).

    On the CPU the windowed, banded path is faster (it computes only the pixels
    a beam reaches); on accelerators data-dependent windows would cost a host
    synchronisation per image.
    """
    return x.device.type != "cpu"


def _chunks(n: int) -> list[tuple[int, int]]:
    return [(s, min(s + _FULL_CHUNK, n)) for s in range(0, n, _FULL_CHUNK)]


def _batched_kernel(u: Tensor, centers: Tensor, bw: float) -> Tensor:
    """``exp(-(c - u)^2 / (2 bw^2))`` shaped ``(B, P, n)`` for ``u (B, n)``."""
    k = centers.unsqueeze(-1) - u.unsqueeze(-2)
    k = k.square_().mul_(-0.5 * _LOG2_E / bw**2)
    return k.clamp_(min=_MIN_EXPONENT * _LOG2_E).exp2_()


class _FullScreenKDE(torch.autograd.Function):
    """See :func:`_kde_full_screen`; analytic backward (as :class:`_TileKDE`)."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx,
        x: Tensor,
        y: Tensor,
        xs: Tensor,
        ys: Tensor,
        bandwidth: tuple[float, float],
        weights: Tensor | None,
    ) -> Tensor:
        hx, hy = bandwidth
        b, n = x.shape
        image = x.new_zeros(b, ys.shape[0], xs.shape[0])
        for s, e in _chunks(n):
            kx = _batched_kernel(x[:, s:e], xs, hx)  # (B, W, n)
            if weights is not None:
                kx = kx.mul_(weights[:, None, s:e])
            ky = _batched_kernel(y[:, s:e], ys, hy)  # (B, H, n)
            image.baddbmm_(ky, kx.transpose(1, 2))
        ctx.bandwidth = bandwidth
        ctx.save_for_backward(x, y, xs, ys, weights)
        return image

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        x, y, xs, ys, weights = ctx.saved_tensors
        hx, hy = ctx.bandwidth
        need_x, need_y = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        need_w = weights is not None and ctx.needs_input_grad[5]
        gx = torch.zeros_like(x) if need_x else None
        gy = torch.zeros_like(y) if need_y else None
        gw = torch.zeros_like(weights) if need_w else None
        grad = grad.contiguous()
        for s, e in _chunks(x.shape[1]):
            kx = _batched_kernel(x[:, s:e], xs, hx)  # (B, W, n)
            ky = _batched_kernel(y[:, s:e], ys, hy)  # (B, H, n)
            w = None if weights is None else weights[:, None, s:e]
            if need_y:
                kxw = kx if w is None else kx * w
                bky = torch.bmm(grad, kxw).mul_(ky)  # (B, H, n)
                b_sum = bky.sum(1)
                gy[:, s:e] = (ys @ bky - y[:, s:e] * b_sum) / hy**2
            if need_x or need_w:
                akx = torch.bmm(grad.transpose(1, 2), ky).mul_(kx)  # (B, W, n)
                row_sum = akx.sum(1)
                if need_w:
                    gw[:, s:e] = row_sum
                if need_x:
                    g = (xs @ akx - x[:, s:e] * row_sum) / hx**2
                    gx[:, s:e] = g if w is None else g * w[:, 0]
        return gx, gy, None, None, None, gw


# (t0, pt, nt, ht, hd, cut) of _tile_forward; (image, tall, lo, hi, geometry)
_TileGeometry = tuple[float, float, int, float, float, float]
_TilePlan = tuple[int, bool, int, int, _TileGeometry]


class _TileKDE(torch.autograd.Function):
    """All ``B`` windowed images of the CPU path (see :func:`_tile_forward`).

    One autograd node for the batch: the forward computes each image's window
    by :func:`_tile_forward` and writes it into the ``(B, H, W)`` image; the
    backward gives each image's gradients by :func:`_tile_backward`. Images are
    independent, so they may be computed by worker threads (see
    :func:`_map_images`); each image is computed by the same code whatever the
    number of workers.

    ``plans`` holds, per non-empty image, ``(i, tall, lo, hi, geometry)``:
    image ``i``, whose window is the pixels ``[lo, hi)`` along x (``tall``: the
    tiles run along y, the whole screen height) or along y (tiles along x), and
    the ``geometry`` of :func:`_tile_forward`.

    Shapes:
        ``x, y, weights (B, N)``, ``xs (W,)``, ``ys (H,)`` -> ``(B, H, W)``.
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx,
        x: Tensor,
        y: Tensor,
        xs: Tensor,
        ys: Tensor,
        plans: list[_TilePlan],
        weights: Tensor | None,
        workers: int,
    ) -> Tensor:
        b, n = x.shape
        image = x.new_zeros(b, ys.shape[0], xs.shape[0])

        def one(k: int) -> tuple:
            i, tall, lo, hi, geometry = plans[k]
            wi = None if weights is None else weights[i]
            if tall:
                window = _tile_forward(y[i], x[i], xs[lo:hi], geometry, wi)
                image[i, :, lo:hi].copy_(window[0])
            else:
                window = _tile_forward(x[i], y[i], ys[lo:hi], geometry, wi)
                image[i, lo:hi, :].copy_(window[0].t())
            return window[1:]

        states = _map_images(one, [plan[0] for plan in plans], workers)
        ctx.plans, ctx.workers, ctx.n = plans, workers, n
        ctx.states = [(geometry, bands) for _, geometry, bands in states]
        ctx.save_for_backward(*(t for tensors, _, _ in states for t in tensors))
        return image

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        saved = ctx.saved_tensors
        need_w = ctx.needs_input_grad[5]
        b, n = grad.shape[0], ctx.n
        gx = grad.new_zeros(b, n)
        gy = grad.new_zeros(b, n)
        gw = grad.new_zeros(b, n) if need_w else None

        def one(k: int) -> None:
            i, tall, lo, hi, _ = ctx.plans[k]
            geometry, bands = ctx.states[k]
            tensors = saved[5 * k : 5 * k + 5]
            wi = None if gw is None else gw[i]
            if tall:
                g = grad[i, :, lo:hi]
                _tile_backward(g, tensors, geometry, bands, gy[i], gx[i], wi)
            else:
                g = grad[i, lo:hi, :].t()
                _tile_backward(g, tensors, geometry, bands, gx[i], gy[i], wi)

        workers = ctx.workers if not torch.is_grad_enabled() else 1
        _map_images(one, [plan[0] for plan in ctx.plans], workers)
        gx = gx if ctx.needs_input_grad[0] else None
        gy = gy if ctx.needs_input_grad[1] else None
        return gx, gy, None, None, None, gw, None


def _tile_forward(
    t: Tensor,
    d: Tensor,
    centers: Tensor,
    geometry: _TileGeometry,
    weights: Tensor | None,
) -> tuple[Tensor, tuple[Tensor | None, ...], tuple, list[tuple[int, int, int]]]:
    """One image ``sum_n w_n g_t(t_i - t_n) g_d(d_j - d_n)`` (unnormalised Gaussians).

    ``t`` is the tiled axis (the whole screen side of ``nt`` pixels), ``d`` the
    axis of the window ``centers`` (``nd`` pixels). Each particle's kernel along
    ``t`` is a tile of ``2 r + 1`` exact values at the pixels ``i_n - r .. i_n + r``
    around its nearest pixel ``i_n``, with ``r = floor(cut s + 1/2)`` (``s`` the
    bandwidth in pixels): every pixel within ``cut`` bandwidths of the particle is
    in its tile, so only kernel values below ``exp(-cut^2 / 2)`` of the peak are
    dropped, as on the window's edges. Along ``d`` the kernel is a matrix over the
    window. Particles are sorted by ``i_n`` (a band per row): a band adds
    ``tiles (2r+1, m) @ kernels^T (m, nd)`` to the ``2 r + 1`` rows around its
    row. Particles whose tile misses the screen are dropped. Kernels are
    evaluated and used in chunks of particles (see :func:`_chunk_particles`) in a
    reused buffer (see :func:`_workspace`); the backward recomputes them.

    ``geometry`` is ``(t0, pt, nt, ht, hd, cut)``: first pixel centre and pixel
    size along ``t`` [m], pixels along ``t``, bandwidths along ``t`` and ``d``
    [m], cut in bandwidths. Inputs are not differentiated through (detached).

    Returns:
        The window ``(nt, nd)``, then what :func:`_tile_backward` needs: the
        saved tensors ``(f, d_rel, c_rel, w, order)``, the geometry
        ``(r, n_bands, pt, ht, hd)`` and the bands.

    Shapes:
        ``t, d, weights (N,)``, ``centers (nd,)`` -> ``(nt, nd)``.
    """
    t0, pt, nt, ht, hd, cut = geometry
    r = math.floor(cut * ht / pt + 0.5)
    nk, n_bands = 2 * r + 1, nt + 2 * r
    n = t.shape[0]
    # pixel coordinate along t; band (row + r) of the nearest pixel
    v = (t.detach() - t0) / pt
    band = torch.round(v)
    f = v - band  # offset from the nearest pixel centre, [-1/2, 1/2] pixel
    # off the screen (band < 0 or >= n_bands) -> n_bands
    band = band.add_(r).clamp_(-1, n_bands).remainder_(n_bands + 1)
    # small integer keys: radix sort (int16 is 5x faster than int32, uint8
    # another 1.4x faster than int16)
    itype = _key_dtype(n_bands)
    band = band.to(itype)
    order = torch.argsort(band)
    counts = torch.bincount(band, minlength=n_bands + 1).tolist()
    nv = n - counts[-1]  # particles whose tile reaches the screen
    order = order[:nv]
    bands = _band_ranges(counts[:-1])
    f = f.index_select(0, order)
    # d relative to the first window pixel: smaller numbers, less cancellation
    d_rel = d.detach().index_select(0, order).sub_(centers[0])
    c_rel = centers - centers[0]
    w = None if weights is None else weights.detach().index_select(0, order)
    nd = centers.shape[0]
    chunk = _chunk_particles(nv, nd)
    buf = _workspace(nk * nv + max(nd * chunk, 2 * nv), t)
    spare = buf[nk * nv :]
    tiles = buf[: nk * nv].view(nk, nv)
    _tile_kernel(f, ht / pt, r, tiles, w, spare[: 2 * nv].view(2, nv))
    out = t.new_zeros(n_bands + 2 * r, nd)
    for s0, e0 in _particle_chunks(nv, chunk):
        m = e0 - s0
        kd = _window_kernel(d_rel[s0:e0], c_rel, hd, spare[: nd * m].view(nd, m))
        for s, e, row in _bands_in(bands, s0, e0):
            out[row : row + nk].addmm_(tiles[:, s0 + s : s0 + e], kd[:, s:e].t())
    saved = (f, d_rel, c_rel, w, order)
    return out[2 * r : 2 * r + nt], saved, (r, n_bands, pt, ht, hd), bands


def _tile_backward(
    grad: Tensor,
    saved: Sequence[Tensor | None],
    geometry: tuple,
    bands: list[tuple[int, int, int]],
    out_t: Tensor,
    out_d: Tensor,
    out_w: Tensor | None,
) -> None:
    """Gradients of one :func:`_tile_forward` image, written into ``out_*``.

    Analytic: with ``T = G_band Kd`` and ``X = (G_band diag(d_j)) Kd`` (one
    product per band), ``dL/dt_n = w_n sum_k tile_nk T_nk (k - r - f_n) p / h_t^2``
    and ``dL/dd_n = w_n sum_k tile_nk (X_nk - d_n T_nk) / h_d^2`` (``f_n`` the
    offset from the nearest pixel in pixels, ``p`` the pixel size); the weight
    gradient is ``sum_k tile_nk T_nk``. Particles dropped by the forward keep
    their zero gradient: ``out_t``, ``out_d`` and ``out_w`` (optional) must be
    zero on entry.

    Shapes:
        ``grad (nt, nd)``; ``out_t, out_d, out_w (N,)``.
    """
    f, d_rel, c_rel, w, order = saved
    r, n_bands, pt, ht, hd = geometry
    nk, nv, nd = 2 * r + 1, f.shape[0], c_rel.shape[0]
    # rows (i, {G, G d_j}) of the padded gradient image: one product per band
    # gives both sum_j G_ij Kd_nj and sum_j G_ij d_j Kd_nj
    gg = grad.new_zeros(n_bands + 2 * r, 2, nd)
    gg[2 * r : 2 * r + grad.shape[0], 0] = grad
    torch.mul(gg[:, 0], c_rel, out=gg[:, 1])
    gg = gg.view(n_bands + 2 * r, 2 * nd)
    # reducer (3, 2 nk): S0 = sum_k tile T, St = sum_k (k - r) tile T and
    # Sd = sum_k tile X
    red = grad.new_zeros(3, nk, 2)
    red[0, :, 0] = 1.0
    red[1, :, 0] = torch.arange(-r, r + 1, dtype=grad.dtype, device=grad.device)
    red[2, :, 1] = 1.0
    red = red.view(3, 2 * nk)
    chunk = _chunk_particles(nv, nd)
    # workspace: tiles (nk, nv), sums (3, nv), then per chunk the kernels
    # and their products (the tile kernel's scratch before that)
    buf = _workspace((nk + 3) * nv + max((nd + 2 * nk) * chunk, 2 * nv), grad)
    tiles = buf[: nk * nv].view(nk, nv)
    sums = buf[nk * nv : (nk + 3) * nv].view(3, nv)
    spare = buf[(nk + 3) * nv :]
    _tile_kernel(f, ht / pt, r, tiles, None, spare[: 2 * nv].view(2, nv))
    for s0, e0 in _particle_chunks(nv, chunk):
        m = e0 - s0
        kd = _window_kernel(d_rel[s0:e0], c_rel, hd, spare[: nd * m].view(nd, m))
        tx = spare[nd * m : (nd + 2 * nk) * m].view(2 * nk, m)
        for s, e, row in _bands_in(bands, s0, e0):
            torch.mm(gg[row : row + nk].view(2 * nk, nd), kd[:, s:e], out=tx[:, s:e])
        tx.view(nk, 2, m).mul_(tiles[:, None, s0:e0])
        torch.mm(red, tx, out=sums[:, s0:e0])
    s_0, s_t, s_d = sums.unbind(0)
    g = sums.new_empty(3 if out_w is not None else 2, nv)
    gt = torch.addcmul(s_t, f, s_0, value=-1.0, out=g[0]).mul_(pt / ht**2)
    gd = torch.addcmul(s_d, d_rel, s_0, value=-1.0, out=g[1]).mul_(1 / hd**2)
    if w is not None:
        gt.mul_(w)
        gd.mul_(w)
    # back to the caller's particle order; dropped particles keep zero
    out_t.scatter_(0, order, gt)
    out_d.scatter_(0, order, gd)
    if out_w is not None:
        out_w.scatter_(0, order, s_0)


def _tile_kernel(
    f: Tensor,
    s: float,
    r: int,
    out: Tensor,
    scale: Tensor | None = None,
    scratch: Tensor | None = None,
) -> Tensor:
    """``out[k, n] = scale_n exp(-(k - r - f_n)^2 / (2 s^2))``, ``k = 0 .. 2r``.

    Two exponentials per particle instead of ``2 r + 1``: with
    ``g0 = exp(-f^2 / 2 s^2)`` and ``a = exp(f / s^2)``, the value at offset
    ``k - r = j > 0`` is the one at ``j - 1`` times ``a exp(-(2 j - 1) / 2 s^2)``
    (``1 / a`` for ``j < 0``): one pass per row, a relative error of about
    ``|j|`` ulp; the ``exp(-j^2 / 2 s^2)`` factors come with the recurrence, so
    no intermediate exceeds a kernel value by more than ``a <= exp(1 / 2 s^2)``
    (the old ``g0 a^j`` reached ``exp(72)`` at ``s = 1 / (2 cut)``, the smallest
    bandwidth with ``r >= 1``). ``scale`` (default 1, e.g. particle weights)
    multiplies ``g0``; ``scratch`` (``(2, N)``, optional) holds ``a`` and ``1 / a``.
    """
    c = _LOG2_E / (2.0 * s * s)  # exp(-u / 2 s^2) = exp2(-c u)
    zero = f.new_zeros(())
    torch.addcmul(zero, f, f, value=-c, out=out[r]).exp2_()
    if scale is not None:
        out[r].mul_(scale)
    if r > 0:
        if scratch is None:
            scratch = f.new_empty(2, f.shape[0])
        up = torch.mul(f, 2.0 * c, out=scratch[0]).exp2_()  # exp(f / s^2)
        down = torch.reciprocal(up, out=scratch[1])
        for j in range(1, r + 1):
            # out[r +- j] / out[r +- (j - 1)] = exp(-(2 j - 1) / 2 s^2) exp(+-f / s^2)
            q = 2.0 ** (-c * (2 * j - 1))
            torch.addcmul(zero, out[r + j - 1], up, value=q, out=out[r + j])
            torch.addcmul(zero, out[r - j + 1], down, value=q, out=out[r - j])
    return out


def _key_dtype(n_bands: int) -> torch.dtype:
    """Smallest integer dtype for band keys ``0 .. n_bands`` (sorting is radix)."""
    if n_bands <= 255:
        return torch.uint8
    return torch.int16 if n_bands < 2**15 else torch.int32


def _window_kernel(d: Tensor, centers: Tensor, h: float, out: Tensor) -> Tensor:
    """``out[j, n] = exp(-(centers_j - d_n)^2 / (2 h^2))`` (``(nd, m)``), in place."""
    torch.sub(centers.unsqueeze(-1), d, out=out)
    torch.addcmul(out.new_zeros(()), out, out, value=-0.5 * _LOG2_E / h**2, out=out)
    return out.clamp_(min=_MIN_EXPONENT * _LOG2_E).exp2_()


def _band_ranges(counts: list[int]) -> list[tuple[int, int, int]]:
    """``(first particle, end particle, band)`` of each non-empty band."""
    out, start = [], 0
    for band, count in enumerate(counts):
        if count:
            out.append((start, start + count, band))
            start += count
    return out


def _bands_in(
    bands: list[tuple[int, int, int]], lo: int, hi: int
) -> Iterator[tuple[int, int, int]]:
    """The parts of ``bands`` within particles ``[lo, hi)``, numbered from ``lo``."""
    for s, e, band in bands:
        if e <= lo:
            continue
        if s >= hi:
            return
        yield max(s, lo) - lo, min(e, hi) - lo, band


# Window-kernel values per chunk of particles: evaluating and using the kernels
# chunk by chunk keeps them in cache between their passes (the subtraction, the
# square, the exp and the products). 2^18 (1 MB float32): about 10 % faster
# than 2^20 on an AVX2 EPYC (forward+backward, 100k particles x 20 images, 1
# thread, interleaved A/B under load); smaller chunks pay more per-call overhead.
_CHUNK_ELEMENTS = 2**18
_CHUNK_MIN_PARTICLES = 1024


def _chunk_particles(n: int, rows: int) -> int:
    """Particles per chunk for window kernels of ``rows`` pixels."""
    return max(1, min(n, max(_CHUNK_MIN_PARTICLES, _CHUNK_ELEMENTS // max(rows, 1))))


def _particle_chunks(n: int, chunk: int) -> list[tuple[int, int]]:
    return [(s, min(s + chunk, n)) for s in range(0, n, chunk)]


# Above this many elements a workspace is not kept between calls (256 MB float32).
_WORKSPACE_KEEP = 2**26
_WORKSPACES = threading.local()


def _workspace(numel: int, like: Tensor) -> Tensor:
    """A flat scratch buffer of ``numel`` elements, reused between calls (per thread).

    Freshly allocated CPU memory is slow to touch the first time (a page fault
    per 4 KiB page, 1-20 us each depending on the host): the KDE kernels are
    large, so they live in one buffer that is kept (up to 256 MB float32) and
    reused by every image and every call. Contents are arbitrary.
    """
    if numel > _WORKSPACE_KEEP:
        return like.new_empty(numel)
    cache = _WORKSPACES.__dict__.setdefault("buffers", {})
    key = (like.dtype, like.device)
    buf = cache.get(key)
    if buf is None or buf.numel() < numel:
        buf = like.new_empty(numel)
        cache[key] = buf
    return buf[:numel]


# Worker threads for the CPU tile path: images are independent, so B images are
# spread over worker threads, each running torch with one intra-op thread. Many
# small ops per image (window kernels and band products in cache-sized chunks)
# parallelise badly with torch's intra-op (OpenMP) threads: on a 2-core AMD
# EPYC KVM guest, waking the OpenMP team on every op made aten::sub 5x and
# aten::mm 2.4x slower per call at 2 threads than at 1. Below this many
# particles per image the images are computed in the calling thread (small
# training steps keep their op-for-op behaviour).
_THREAD_MIN_PARTICLES = 2**15
_THREADS_ENV = "DIFFACCEL_KDE_THREADS"
_POOLS: dict[int, ThreadPoolExecutor] = {}
_POOLS_LOCK = threading.Lock()


def _forget_pools() -> None:
    """After ``fork`` the child has none of the parent's threads: start afresh."""
    global _POOLS_LOCK
    _POOLS.clear()
    _POOLS_LOCK = threading.Lock()


os.register_at_fork(after_in_child=_forget_pools)


def _image_workers(x: Tensor, images: int) -> int:
    """Worker threads for ``images`` CPU tile images of ``x (B, N)`` (1: none).

    ``DIFFACCEL_KDE_THREADS``: unset or ``auto`` -> ``torch.get_num_threads()``,
    ``0`` or ``1`` -> no worker threads, ``n`` -> at most ``n``. Threads are used
    only for at least 2 images of at least :data:`_THREAD_MIN_PARTICLES`
    particles, and never while the autograd profiler records (it would not see
    the workers' ops), while compiling, or for tensor subclasses and modes (their
    thread-local state does not reach the workers).
    """
    setting = os.environ.get(_THREADS_ENV, "auto").strip().lower()
    if setting in ("", "auto"):
        workers = torch.get_num_threads()
    else:
        workers = int(setting) if setting.isdigit() else -1
        if workers < 0:
            raise ValueError(
                f"{_THREADS_ENV} must be 'auto' or a number of worker threads "
                f"(0 or 1: none); got {setting!r}."
            )
    if workers < 2 or images < 2 or x.shape[-1] < _THREAD_MIN_PARTICLES:
        return 1
    if (
        type(x) is not Tensor
        or torch.autograd._profiler_enabled()
        or torch.compiler.is_compiling()
        or torch._C._is_torch_function_mode_enabled()
        or torch._C._len_torch_dispatch_stack() > 0
    ):
        return 1
    return min(workers, images)


def _pool(workers: int) -> ThreadPoolExecutor:
    """A reused pool of ``workers`` threads, each with one torch intra-op thread.

    ``torch.set_num_threads(1)`` in a worker sets that thread's OpenMP and MKL
    thread counts (thread-local), but also torch's process-wide default that
    threads started later initialise from. So each worker first initialises
    its own count (``torch.get_num_threads()``), then sets 1; the pool is
    started whole (a barrier holds every worker until all have done so), then
    the calling thread restores the default with its own unchanged count.
    Threads started meanwhile by other code would inherit 1 thread.
    """
    with _POOLS_LOCK:
        pool = _POOLS.get(workers)
        if pool is not None:
            return pool
        pool = ThreadPoolExecutor(workers, thread_name_prefix="diffaccel-kde")
        caller_threads = torch.get_num_threads()
        started = threading.Barrier(workers)

        def one_intra_op_thread() -> None:
            torch.get_num_threads()
            torch.set_num_threads(1)
            started.wait(timeout=60.0)

        try:
            for future in [pool.submit(one_intra_op_thread) for _ in range(workers)]:
                future.result()
        finally:
            torch.set_num_threads(caller_threads)
        _POOLS[workers] = pool
        return pool


def _map_images(
    fn: Callable[[int], _T], images: Sequence[int], workers: int
) -> list[_T]:
    """``[fn(k) for k in range(len(images))]``, on ``workers`` threads if ``> 1``.

    ``images`` names the image of each item (for errors). Every call returns (or
    fails) before this does; the first failure is raised as a ``RuntimeError``
    naming the image, chained to the worker's exception.
    Workers run without gradient recording and in the caller's inference mode.
    """
    count = len(images)
    if workers < 2 or count < 2:
        return [fn(k) for k in range(count)]
    inference = torch.is_inference_mode_enabled()

    def run(k: int) -> _T:
        with torch.inference_mode(inference), torch.no_grad():
            return fn(k)

    pool = _pool(workers)
    futures = [pool.submit(run, k) for k in range(count)]
    wait(futures)
    for k, future in enumerate(futures):
        error = future.exception()
        if error is not None:
            raise RuntimeError(
                f"kde_image: image {images[k]} failed in a worker thread: "
                f"{type(error).__name__}: {error} (set {_THREADS_ENV}=1 to compute "
                "the images in the calling thread)"
            ) from error
    return [future.result() for future in futures]


def _reach(
    u: Tensor, radius: float, pixel: float, center: float, n_pix: int
) -> tuple[list[int], list[int]]:
    """Per batch row, the pixel range ``[lo, hi)`` within ``radius`` [m] of ``u``."""
    offset = (n_pix - 1) / 2 - center / pixel
    u = u.detach()
    u_min, u_max = u.amin(-1), u.amax(-1)  # (faster than aminmax on CPU)
    lo = ((u_min - radius) / pixel + offset).ceil()
    hi = ((u_max + radius) / pixel + offset).floor() + 1
    lo = lo.clamp(0, n_pix).long().tolist()
    hi = hi.clamp(0, n_pix).long().tolist()
    return lo, hi
