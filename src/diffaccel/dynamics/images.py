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
from collections.abc import Sequence

import torch
from torch import Tensor

__all__ = ["cic_image", "gaussian_blur", "kde_image", "pixel_centers"]

# exp(-80) = 1.8e-35 is still a normal float32: clamping the exponent there keeps
# CPU float32 arithmetic out of (very slow) denormals at a negligible error.
_MIN_EXPONENT = -80.0


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
    if not bool(torch.isfinite(x).all() & torch.isfinite(y).all()):
        raise ValueError("x and y contain NaN or infinite positions.")
    batch = x.shape[:-1]
    n = x.shape[-1]
    x = x.reshape(-1, n)
    y = y.reshape(-1, n)
    if weights is not None:
        weights = weights.reshape(-1, n)
    return x, y, weights, batch


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
    bilinear weights; parts falling outside the screen are dropped. A beam that
    misses the screen entirely gives an all-zero image (never NaN).

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
    # Continuous pixel coordinates; clamped well outside the screen so that huge
    # positions cannot overflow the integer cast (their weight is zero anyway).
    fx = ((x - cx) / psx + (w - 1) / 2).clamp(-2.0, w + 1.0)
    fy = ((y - cy) / psy + (h - 1) / 2).clamp(-2.0, h + 1.0)
    j0 = fx.detach().floor()
    i0 = fy.detach().floor()
    tx = fx - j0
    ty = fy - i0
    j0 = j0.long()
    i0 = i0.long()
    base = (torch.arange(b, device=x.device) * (h * w)).unsqueeze(-1)
    idx = []
    val = []
    for di, dj, wt in (
        (0, 0, (1 - ty) * (1 - tx)),
        (0, 1, (1 - ty) * tx),
        (1, 0, ty * (1 - tx)),
        (1, 1, ty * tx),
    ):
        i = i0 + di
        j = j0 + dj
        inside = (i >= 0) & (i < h) & (j >= 0) & (j < w)
        idx.append(base + i.clamp(0, h - 1) * w + j.clamp(0, w - 1))
        val.append(wt * inside)
    values = torch.stack(val)
    if weights is not None:
        values = values * weights
        total = weights.sum(-1)
    else:
        total = torch.full((b,), float(n), dtype=x.dtype, device=x.device)
    flat = x.new_zeros(b * h * w).index_add(
        0, torch.stack(idx).reshape(-1), values.reshape(-1)
    )
    image = flat.reshape(b, h, w) / total.reshape(b, 1, 1)
    if blur_sigma is not None:
        image = gaussian_blur(image, blur_sigma, (psx, psy))
    return image.reshape(*batch, h, w)


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
    no ``N x H x W`` tensor is formed. For a beam much wider than the bandwidth
    and well inside the screen the image sum is close to 1.

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
    kx = _kernel(x, xs, hx, psx)  # (B, N, W)
    ky = _kernel(y, ys, hy, psy)  # (B, N, H)
    if weights is not None:
        kx = kx * weights.unsqueeze(-1)
        total = weights.sum(-1)
    else:
        total = torch.full((b,), float(n), dtype=x.dtype, device=x.device)
    image = torch.bmm(ky.transpose(1, 2), kx) / total.reshape(b, 1, 1)
    return image.reshape(*batch, h, w)


def _kernel(u: Tensor, centers: Tensor, bw: float, pixel: float) -> Tensor:
    """``pixel * N(c - u; bw)`` for positions ``(B, N)`` and centres ``(P,)``."""
    arg = (u.unsqueeze(-1) - centers) * (1.0 / bw)
    arg = (-0.5 * arg.square()).clamp(min=_MIN_EXPONENT)
    return arg.exp() * (pixel / (math.sqrt(2 * math.pi) * bw))
