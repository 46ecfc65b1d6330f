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
import threading
from collections.abc import Iterator, Sequence

import torch
from torch import Tensor

__all__ = ["cic_image", "gaussian_blur", "kde_image", "pixel_centers"]

# exp(-80) = 1.8e-35 is still a normal float32: clamping the exponent there keeps
# CPU float32 arithmetic out of (very slow) denormals at a negligible error.
_MIN_EXPONENT = -80.0
# Kernels are evaluated as exp2(e * log2(e)): torch's vectorised exp2 is about
# four times faster than exp on AVX-512 CPUs and as accurate (1 ulp).
_LOG2_E = 1.0 / math.log(2.0)
# Kernel truncation radius of the KDE, in bandwidths (float64; float32).
_KDE_CUT = 9.0
_KDE_CUT_FLOAT32 = 6.0


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


def _gaussian_matrix(n: int, sigma_px: float, like: Tensor) -> Tensor:
    """``(n, n)`` blur matrix; columns sum to 1 before truncation by the edges."""
    idx = torch.arange(n, dtype=like.dtype, device=like.device)
    d = idx[:, None] - idx[None, :]
    g = torch.exp(-0.5 * (d / sigma_px).square())
    r = math.ceil(8 * sigma_px) + n
    full = torch.arange(-r, r + 1, dtype=like.dtype, device=like.device)
    return g / torch.exp(-0.5 * (full / sigma_px).square()).sum()


def gaussian_blur(
    image: Tensor, sigma: Sequence[float] | float, pixel_size: Sequence[float] | float
) -> Tensor:
    """Gaussian blur of images ``(*K, H, W)`` with rms ``sigma`` [m] (x, y).

    Mass blurred past the edge is lost (the screen does not see it). Computed as
    two matrix products, so it is exact and differentiable.
    """
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
        torch.add(
            x.new_tensor((2.0 * bx + 1.0) / w - 1.0),
            x,
            alpha=scale[0],
            out=grid[:, 0, :, 0],
        )
        torch.add(
            y.new_tensor((2.0 * by + 1.0) / h - 1.0),
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
    no ``N x H x W`` tensor is formed. Per image, only the rows and columns within
    9 bandwidths (float32: 6) of some particle are computed (the rest is below
    3e-18 (1.5e-8) of a kernel's peak), which keeps compact beams on large
    screens cheap. When that window is much longer than a kernel along one side
    (a beam wide compared with the bandwidth), the particles are sorted into
    bands of a few pixels along that side and each band gets a kernel matrix over
    only the pixels it reaches, with one product per band: the same exact values,
    about half the work on this benchmark's quad scan. The gradient is analytic
    (with respect to positions and weights). For a beam much wider than the
    bandwidth and well inside the screen the image sum is close to 1.

    Off the CPU (CUDA) all images are computed at once on the whole screen with
    fixed shapes (particles in chunks of fixed size): no per-image Python loop
    and no host synchronisation from data-dependent windows; same values (the
    window only drops kernel values below the cut). On the CPU the kernels are
    evaluated and used in chunks of particles of a few MB (they stay in cache
    between their passes), in a reused workspace (fresh memory costs a page
    fault per 4 KiB on first touch), and the backward recomputes them.

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
    image = x.new_zeros(b, h, w)
    # unbind once: indexing x[i] in the loop would give each image a backward
    # that zero-fills a full (B, N) gradient
    x_rows, y_rows = x.unbind(0), y.unbind(0)
    w_rows = (None,) * b if weights is None else weights.unbind(0)
    # a window much taller than a kernel is rendered in bands of rows (particles
    # grouped by row): split the longer side of each window
    reach_x, reach_y = math.ceil(cut * hx / psx), math.ceil(cut * hy / psy)
    for i in range(b):
        rows, cols = hi_y[i] - lo_y[i], hi_x[i] - lo_x[i]
        if rows <= 0 or cols <= 0:
            continue
        win_x, win_y = xs[lo_x[i] : hi_x[i]], ys[lo_y[i] : hi_y[i]]
        band_y, band_x = _band_rows(rows, reach_y, n), _band_rows(cols, reach_x, n)
        if band_x is not None and (band_y is None or cols > rows):
            # split the columns: render the transposed window
            image[i, lo_y[i] : hi_y[i], lo_x[i] : hi_x[i]] = _SeparableKDE.apply(
                y_rows[i],
                x_rows[i],
                win_y,
                win_x,
                (hy, hx),
                w_rows[i],
                (psx, reach_x, band_x),
            ).transpose(0, 1)
        else:
            image[i, lo_y[i] : hi_y[i], lo_x[i] : hi_x[i]] = _SeparableKDE.apply(
                x_rows[i],
                y_rows[i],
                win_x,
                win_y,
                (hx, hy),
                w_rows[i],
                (psy, reach_y, band_y),
            )
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
    """See :func:`_kde_full_screen`; analytic backward as :class:`_SeparableKDE`."""

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


# Band rendering pays off from this many particles per image (below, the
# sorting and per-band products cost more than the rows they save).
_BAND_MIN_PARTICLES = 4096


def _band_rows(rows: int, reach: int, n: int) -> int | None:
    """Particle rows per band for a window of ``rows``, or None to render it whole.

    A band of ``c`` particle rows needs ``c + 2 reach`` image rows; ``c`` is
    about half the kernel reach, and banding is used only when that is at most
    three quarters of the window.
    """
    c = reach // 2 + 1
    if n < _BAND_MIN_PARTICLES or 4 * (c + 2 * reach) > 3 * rows:
        return None
    return c


class _SeparableKDE(torch.autograd.Function):
    """``sum_n w_n gy(y_i - y_n) gx(x_j - x_n)`` with unnormalised Gaussians ``g``.

    Kernels are stored transposed, ``(pixels, N)``. Columns: one kernel matrix
    ``Kx (N, w')`` over the window. Rows: either one
    kernel matrix ``Ky (N, h')`` and one product ``Ky^T (w Kx)``, or, when
    ``band`` gives a number of rows ``c``, particles are grouped (sorted) by the
    band of ``c`` rows they sit in and each group gets a kernel over only its
    ``c + 2 reach`` rows (every row a particle reaches within the cut): one
    ``(N, c + 2 reach)`` matrix and one product per band, added into the window.
    Either way every kept kernel value is exact.

    Backward (analytic): with ``A = Ky G`` and ``B = (w Kx) G^T`` (per band),
    ``dL/dx_n = sum_j A_nj w_n Kx_nj (x_j - x_n) / hx^2``, and
    ``dL/dy_n = sum_i B_ni Ky_ni (y_i - y_n) / hy^2``, evaluated with matrix-vector
    products over all particles at once.
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx,
        x: Tensor,
        y: Tensor,
        xs: Tensor,
        ys: Tensor,
        bandwidth: tuple[float, float],
        weights: Tensor | None,
        banding: tuple[float, int, int | None],
    ) -> Tensor:
        pixel_y, reach, c = banding
        h = ys.shape[0]
        order = None
        if c is None:
            # one band: the whole window, rows relative to its first row
            c, reach, n_bands, counts = h, 0, 1, [x.shape[0]]
        else:
            n_bands = h // c + 1
            f = (y.detach() - ys[0]) / pixel_y  # row coordinate in the window
            # small integer keys: radix sort (int16 is 5x faster than int32)
            itype = torch.int16 if n_bands < 2**15 else torch.int32
            key = (f / c).floor_().clamp_(0, n_bands - 1).to(itype)
            order = torch.argsort(key)
            counts = torch.bincount(key, minlength=n_bands).tolist()
            # index_select / scatter_: 3-6x faster than x[order] / index_put_
            x, y = x.index_select(0, order), y.index_select(0, order)
            if weights is not None:
                weights = weights.index_select(0, order)
        starts = [0]
        for k in counts:
            starts.append(starts[-1] + k)
        width = c + 2 * reach
        # first image row of each particle's band (window rows; may be < 0)
        if n_bands == 1:
            first = ys[:1]
        else:
            band_of = torch.repeat_interleave(
                torch.arange(n_bands, device=x.device),
                torch.tensor(counts).to(x.device),
            )
            first = ys[0] + (band_of * c - reach).to(ys.dtype) * pixel_y
        rel = torch.arange(width, dtype=ys.dtype, device=ys.device) * pixel_y
        # kernels are stored transposed, (pixels, N): the broadcast subtraction
        # and the column sums of the backward then run along the long particle
        # axis (3x faster than (N, pixels) on AVX2 CPUs). They are evaluated and
        # used in chunks of particles (see _chunk_particles) in a reused buffer
        # (see _workspace); the backward recomputes them
        n, nx = x.shape[0], xs.shape[0]
        y_rel = y - first
        chunk = _chunk_particles(n, nx + width)
        buf = _workspace((nx + width) * chunk, x)
        out = x.new_zeros(n_bands * c + 2 * reach, xs.shape[0])
        for s0, e0 in _particle_chunks(n, chunk):
            kx, ky = _kernel_pair(
                x[s0:e0],
                y_rel[s0:e0],
                xs,
                rel,
                bandwidth,
                buf[: (nx + width) * (e0 - s0)],
            )
            kxw = kx if weights is None else kx.mul_(weights[s0:e0])
            for s, e, r in _nonempty_bands(starts, c, s0, e0):
                out[r : r + width].addmm_(ky[:, s:e], kxw[:, s:e].transpose(0, 1))
        ctx.bandwidth = bandwidth
        ctx.bands = (c, reach, n_bands, starts)
        ctx.save_for_backward(x, y, xs, rel, first, weights, order)
        return out[reach : reach + h]

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        x, y, xs, rel, first, weights, order = ctx.saved_tensors
        hx, hy = ctx.bandwidth
        c, reach, n_bands, starts = ctx.bands
        width = rel.shape[0]
        n, nx = x.shape[0], xs.shape[0]
        y_rel = y - first
        chunk = _chunk_particles(n, nx + width)
        buf = _workspace((3 * nx + 2 * width) * chunk, x)
        padded = grad.new_zeros(n_bands * c + 2 * reach, grad.shape[1])
        padded[reach : reach + grad.shape[0]] = grad
        need_y = ctx.needs_input_grad[1]
        need_x = ctx.needs_input_grad[0]
        need_w = weights is not None and ctx.needs_input_grad[5]
        gy = x.new_empty(n) if need_y else None
        gx = x.new_empty(n) if need_x else None
        gw = x.new_empty(n) if need_w else None
        for s0, e0 in _particle_chunks(n, chunk):
            m = e0 - s0
            kx, ky = _kernel_pair(
                x[s0:e0], y_rel[s0:e0], xs, rel, ctx.bandwidth, buf[: (nx + width) * m]
            )
            spare = buf[(nx + width) * m :]
            w = None if weights is None else weights[s0:e0]
            bands = list(_nonempty_bands(starts, c, s0, e0))
            row_sum = None  # sum_ij G_ij Ky_ni Kx_nj
            if need_y:
                kxw = (
                    kx
                    if w is None
                    else torch.mul(kx, w, out=spare[: nx * m].view(nx, m))
                )
                # (width, m): sum_j w Kx_nj G_ij, per band
                bm = spare[nx * m : (nx + width) * m].view(width, m)
                for s, e, r in bands:
                    torch.mm(padded[r : r + width], kxw[:, s:e], out=bm[:, s:e])
                bky = bm.mul_(ky)
                b_sum = bky.sum(0)
                g = torch.addcmul(rel @ bky, y_rel[s0:e0], b_sum, value=-1.0)
                torch.mul(g, 1.0 / hy**2, out=gy[s0:e0])
                if w is None:
                    row_sum = b_sum  # saves a pass over the (w', m) product below
            if need_x or need_w:
                # (w', m): sum_i Ky_ni G_ij, per band
                a = spare[(nx + width) * m : (2 * nx + width) * m].view(nx, m)
                for s, e, r in bands:
                    band_t = padded[r : r + width].transpose(0, 1)
                    torch.mm(band_t, ky[:, s:e], out=a[:, s:e])
                akx = a.mul_(kx)
                if row_sum is None:
                    row_sum = akx.sum(0)
                if need_w:
                    gw[s0:e0] = row_sum
                if need_x:
                    g = torch.addcmul(xs @ akx, x[s0:e0], row_sum, value=-1.0)
                    if w is None:
                        torch.mul(g, 1.0 / hx**2, out=gx[s0:e0])
                    else:
                        torch.mul(g, w / hx**2, out=gx[s0:e0])
        if order is not None:
            gx, gy, gw = (
                None if g is None else _unsort(g, order) for g in (gx, gy, gw)
            )
        return gx, gy, None, None, None, gw, None


def _nonempty_bands(
    starts: list[int], c: int, lo: int = 0, hi: int | None = None
) -> Iterator[tuple[int, int, int]]:
    """``(first particle, end particle, first padded row)`` of each non-empty band.

    Only the particles in ``[lo, hi)`` are taken, numbered from ``lo``.
    """
    hi = starts[-1] if hi is None else hi
    for k in range(len(starts) - 1):
        s, e = max(starts[k], lo), min(starts[k + 1], hi)
        if e > s:
            yield s - lo, e - lo, k * c


# Kernel values (both matrices) per chunk of particles: evaluating and using
# the kernels chunk by chunk keeps them in cache between their passes (the
# subtraction, the square, the exp and the products): 1.3-1.5x faster per image
# than whole-window matrices on an AVX2 EPYC (4 MB chunks; from 1 MB the
# per-call overhead dominates).
_CHUNK_ELEMENTS = 2**20
_CHUNK_MIN_PARTICLES = 1024


def _chunk_particles(n: int, rows: int) -> int:
    """Particles per chunk for kernels of ``rows`` pixels in all."""
    return min(n, max(_CHUNK_MIN_PARTICLES, _CHUNK_ELEMENTS // max(rows, 1)))


def _particle_chunks(n: int, chunk: int) -> list[tuple[int, int]]:
    return [(s, min(s + chunk, n)) for s in range(0, n, chunk)]


def _unsort(values: Tensor, order: Tensor) -> Tensor:
    """Inverse of ``values = original[order]``."""
    return values.new_empty(values.shape).scatter_(0, order, values)


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


def _kernel_pair(
    x: Tensor,
    y: Tensor,
    xs: Tensor,
    ys: Tensor,
    bandwidth: tuple[float, float],
    buf: Tensor,
) -> tuple[Tensor, Tensor]:
    """Kernels ``Kx (W', N)`` and ``Ky (H', N)`` written into the front of ``buf``.

    The two matrices are adjacent in ``buf``: the element-wise passes after the
    subtraction run once over both (fewer, longer calls).
    """
    n, nx, ny = x.shape[0], xs.shape[0], ys.shape[0]
    both = buf[: (nx + ny) * n]
    kx = torch.sub(xs.unsqueeze(-1), x, out=both[: nx * n].view(nx, n))
    ky = torch.sub(ys.unsqueeze(-1), y, out=both[nx * n :].view(ny, n))
    zero = buf.new_zeros(())
    hx, hy = bandwidth
    if hx == hy:
        torch.addcmul(zero, both, both, value=-0.5 * _LOG2_E / hx**2, out=both)
    else:
        torch.addcmul(zero, kx, kx, value=-0.5 * _LOG2_E / hx**2, out=kx)
        torch.addcmul(zero, ky, ky, value=-0.5 * _LOG2_E / hy**2, out=ky)
    both.clamp_(min=_MIN_EXPONENT * _LOG2_E).exp2_()
    return kx, ky


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
