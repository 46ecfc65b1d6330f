"""Accuracy metrics: beam moments vs ground truth, sliced Wasserstein, image errors."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from diffaccel.dynamics import as_real_tensor

#: Bmad coordinate names in column order.
COORDINATES = ("x", "px", "y", "py", "z", "pz")


def beam_moments(particles: Tensor) -> dict[str, Tensor]:
    """Second-moment summary of a particle cloud (float64).

    Emittances are geometric rms emittances ``sqrt(det Sigma)`` of the 2x2 blocks
    (x-px, y-py, z-pz) and of the 4x4 transverse and full 6x6 covariance; Twiss
    ``beta = <x^2> / eps`` [m], ``alpha = -<x px> / eps``.

    Args:
        particles: Bmad coordinates ``(N, 6)``.

    Shapes:
        Returns ``centroid (6,)``, ``rms (6,)``, ``cov (6, 6)``, ``corr (6, 6)``
        and scalars ``emit_x``, ``emit_y``, ``emit_z`` [m], ``emit_4d`` [m^2],
        ``emit_6d`` [m^3], ``beta_x``, ``beta_y`` [m], ``alpha_x``, ``alpha_y``.

    Raises:
        ValueError: if ``particles`` is not ``(N, 6)`` with N >= 2 or not finite.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> m = beam_moments(torch.randn(20000, 6, generator=g) * 1e-3)
        >>> round(float(m["emit_x"]) * 1e6, 1)
        1.0
    """
    particles = as_real_tensor(particles, "particles")  # numpy arrays too
    if particles.ndim != 2 or particles.shape[1] != 6 or particles.shape[0] < 2:
        raise ValueError(
            f"particles must have shape (N >= 2, 6); got {tuple(particles.shape)}."
        )
    x = particles.detach().to(torch.float64)
    if not torch.isfinite(x).all():
        raise ValueError("particles contain NaN or inf.")
    mu = x.mean(0)
    xc = x - mu
    cov = xc.T @ xc / (x.shape[0] - 1)
    return covariance_moments(mu, cov)


def moment_errors(reconstructed: Tensor, truth: Tensor) -> dict[str, float]:
    """Relative errors of rms sizes and emittances, and correlation-matrix error.

    Args:
        reconstructed: Particles ``(N, 6)``.
        truth: Ground-truth particles ``(M, 6)``.

    Returns:
        ``rms_<coord>`` and ``emit_x/y/z/4d/6d``: ``(reco - truth) / truth``
        (NaN where the truth is 0, e.g. a 4D beam's z); ``corr_max_abs`` and
        ``corr_rms``: max and rms absolute difference of the transverse 4x4
        correlation matrices; ``corr_diff_<a>_<b>``: reconstructed minus true
        correlation coefficient of coordinates ``a``, ``b`` (all 15 pairs).
    """
    a, b = beam_moments(reconstructed), beam_moments(truth)
    out: dict[str, float] = {}

    def rel(u: Tensor, v: Tensor) -> float:
        v = float(v)
        return (float(u) - v) / v if v != 0 else math.nan

    for i, c in enumerate(COORDINATES):
        out[f"rms_{c}"] = rel(a["rms"][i], b["rms"][i])
    for k in ("emit_x", "emit_y", "emit_z", "emit_4d", "emit_6d"):
        out[k] = rel(a[k], b[k])
    d = (a["corr"][:4, :4] - b["corr"][:4, :4]).abs()
    out["corr_max_abs"] = float(d.max())
    out["corr_rms"] = float(d.square().mean().sqrt())
    for i in range(6):
        for j in range(i + 1, 6):
            name = f"corr_diff_{COORDINATES[i]}_{COORDINATES[j]}"
            diff = float(a["corr"][i, j] - b["corr"][i, j])
            # NaN where either beam has no spread in a coordinate (4D: z, pz)
            zero = float(a["rms"][i] * a["rms"][j] * b["rms"][i] * b["rms"][j]) == 0
            out[name] = math.nan if zero else diff
    return out


def sliced_wasserstein(
    a: Tensor,
    b: Tensor,
    n_projections: int = 256,
    generator: torch.Generator | None = None,
    scale: Tensor | None = None,
) -> Tensor:
    """Sliced 1-Wasserstein distance between two particle clouds.

    Both clouds are divided by ``scale`` (default: the rms sizes of ``b``, the
    reference; coordinates with zero spread in ``b`` are left out), projected on
    ``n_projections`` random unit directions, and the 1D Wasserstein-1 distances
    (from 1001 quantiles) are averaged. 0 for identical clouds; a shift of the
    whole cloud by ``t`` reference sigmas along one axis gives about
    ``t * E|u_axis|`` over random unit directions ``u``.

    Args:
        a: Particles ``(N, D)``.
        b: Reference particles ``(M, D)``.
        n_projections: Random directions.
        generator: RNG for the directions.
        scale: Per-coordinate normalisation ``(D,)``.

    Shapes:
        ``(N, D)``, ``(M, D)`` -> ``()`` float64 [units of ``scale``].

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> x = torch.randn(5000, 6, generator=g)
        >>> float(sliced_wasserstein(x, x, generator=g))
        0.0
    """
    if a.ndim != 2 or b.ndim != 2 or a.shape[1] != b.shape[1]:
        raise ValueError(
            f"need (N, D) and (M, D) clouds; got {tuple(a.shape)}, {tuple(b.shape)}."
        )
    a = a.detach().to(torch.float64)
    b = b.detach().to(a.device, torch.float64)
    s = b.std(0) if scale is None else torch.as_tensor(scale, dtype=torch.float64)
    keep = s > 0
    a, b, s = a[:, keep], b[:, keep], s[keep]
    a, b = a / s, b / s
    d = a.shape[1]
    dirs = torch.randn(d, n_projections, generator=generator, dtype=torch.float64)
    dirs = dirs / dirs.norm(dim=0, keepdim=True)
    # projections as rows (P, N): the product writes them contiguous, no
    # transposed copy before the sort
    pa = _sorted_rows(dirs.T.to(a.device) @ a.T)
    pb = _sorted_rows(dirs.T.to(b.device) @ b.T)
    q = torch.linspace(0.0, 1.0, 1001, dtype=torch.float64, device=a.device)
    return (_sorted_quantiles(pa.T, q) - _sorted_quantiles(pb.T, q)).abs().mean()


def _sorted_rows(values: Tensor) -> Tensor:
    """``values.sort(-1).values`` of a fresh contiguous ``(P, N)`` tensor, faster.

    Sorts in place, on the CPU with numpy (SIMD sort, ~5x torch's on this
    2-core AVX2 machine): the evaluation's share of a whole ``reconstruct``
    (it counts in the command's wall time). ``values`` is overwritten.
    """
    if values.device.type == "cpu" and values.is_contiguous():
        values.numpy().sort(axis=-1)
        return values
    return values.sort(-1).values


def _sorted_quantiles(values: Tensor, q: Tensor) -> Tensor:
    """``torch.quantile(values, q, dim=0)`` of columns already sorted ascending.

    The same linear interpolation between order statistics, without the second
    sort that ``torch.quantile`` does (which took as long as the first).

    Shapes:
        ``values (N, P)``, ``q (Q,)`` -> ``(Q, P)``.
    """
    pos = q * (values.shape[0] - 1)
    lo = pos.floor().long().clamp_max(values.shape[0] - 1)
    hi = (lo + 1).clamp_max(values.shape[0] - 1)
    frac = (pos - lo).unsqueeze(1)
    return torch.lerp(values[lo], values[hi], frac)


def image_errors(predicted: Tensor, measured: Tensor) -> dict[str, float]:
    """Agreement of predicted and measured sum-normalised images.

    Args:
        predicted: Predicted images ``(K, H, W)``.
        measured: Measured images ``(K, H, W)``.

    Returns:
        ``mae_over_peak``: mean over settings of ``mean|m - p| / max(m)``;
        ``relative_l1``: mean over settings of ``sum|m - p| / sum m``; and the
        per-setting ``relative_l1_per_setting`` list.

    Raises:
        ValueError: if the shapes differ or are empty, a pixel is NaN or
            infinite, or a measured image does not sum to > 0.
    """
    predicted = as_real_tensor(predicted, "predicted images")
    measured = as_real_tensor(measured, "measured images")
    if predicted.shape != measured.shape or predicted.ndim != 3:
        raise ValueError(
            f"predicted {tuple(predicted.shape)} and measured "
            f"{tuple(measured.shape)} must both be (K, H, W)."
        )
    if predicted.numel() == 0:
        raise ValueError(f"no images to compare (shape {tuple(predicted.shape)}).")
    p = predicted.detach().to(torch.float64)
    m = measured.detach().to(p.device, torch.float64)
    for name, t in (("predicted", p), ("measured", m)):
        if not bool(torch.isfinite(t).all()):
            raise ValueError(f"{name} images contain NaN or infinite pixels.")
    if not bool((m.sum((-2, -1)) > 0).all()):
        k = int(torch.nonzero(m.sum((-2, -1)) <= 0)[0])
        raise ValueError(
            f"measured image {k} sums to <= 0; relative errors need positive images."
        )
    diff = (m - p).abs()
    peak = m.amax((-2, -1)).clamp_min(1e-300)
    mae = diff.mean((-2, -1)) / peak
    rel = diff.sum((-2, -1)) / m.sum((-2, -1)).clamp_min(1e-300)
    return {
        "mae_over_peak": float(mae.mean()),
        "relative_l1": float(rel.mean()),
        "relative_l1_per_setting": rel.tolist(),
    }


def covariance_moments(mu: Tensor, cov: Tensor) -> dict[str, Tensor]:
    """Beam moments of centroids and covariances, batched (as ``beam_moments``).

    Each moment is computed from its own sub-block; negative variances and
    determinants (possible for posterior draws) are clamped at 0.

    Shapes:
        ``mu (*B, 6)``, ``cov (*B, 6, 6)`` -> ``centroid``, ``rms (*B, 6)``,
        ``cov``, ``corr (*B, 6, 6)`` and scalars ``(*B,)``.
    """
    var = cov.diagonal(dim1=-2, dim2=-1)
    rms = var.clamp_min(0).sqrt()
    corr = cov / (rms[..., :, None] * rms[..., None, :]).clamp_min(1e-300)

    def det_sqrt(idx: list[int]) -> Tensor:
        sub = cov[..., idx, :][..., :, idx]
        return torch.linalg.det(sub).clamp_min(0).sqrt()

    out = {
        "centroid": mu,
        "rms": rms,
        "cov": cov,
        "corr": corr,
        "emit_x": det_sqrt([0, 1]),
        "emit_y": det_sqrt([2, 3]),
        "emit_z": det_sqrt([4, 5]),
        "emit_4d": det_sqrt([0, 1, 2, 3]),
        "emit_6d": det_sqrt([0, 1, 2, 3, 4, 5]),
    }
    for name, i in (("x", 0), ("y", 2)):
        eps = out[f"emit_{name}"].clamp_min(1e-300)
        out[f"beta_{name}"] = cov[..., i, i] / eps
        out[f"alpha_{name}"] = -cov[..., i, i + 1] / eps
    return out


def prediction_noise_l1(predicted: Tensor, kappa: float, n_particles: int) -> Tensor:
    """Expected relative L1 that the sampling noise of predicted images adds.

    A pixel of an image of ``n`` particles with expected value ``p`` (unit-sum
    image) has variance ``kappa p / n`` (``kappa``:
    :meth:`~diffaccel.reconstruction.forward.ScreenForwardModel.pixel_kernel_sum_sq`),
    so its expected absolute error is ``sqrt(2 kappa p / (pi n))``; summed over
    the pixels of each image.

    Args:
        predicted: Unit-sum predicted images ``(K, H, W)``.
        kappa: Squared deposit weights of one particle, summed over pixels.
        n_particles: Particles behind each image (all ensemble members).

    Returns:
        ``(K,)`` float64.

    Example:
        >>> p = torch.full((1, 10, 10), 0.01)
        >>> prediction_noise_l1(p, 1.0, 100).round(decimals=3)
        tensor([0.7980], dtype=torch.float64)
    """
    p = predicted.detach().to(torch.float64).clamp_min(0.0)
    scale = math.sqrt(2.0 * kappa / (math.pi * n_particles))
    return scale * p.sqrt().sum((-2, -1))


def shot_noise_l1(images: Tensor) -> Tensor | None:
    """Relative L1 between the shot-mean images and their noise-free form.

    Estimated from the scatter of ``S >= 2`` shots: per pixel, the standard
    error of the shot mean (sample std over shots / sqrt(S), corrected for the
    bias of a sample std) times ``sqrt(2 / pi)``, summed, over the image's sum.
    This is the floor below which no prediction's error can go; ``None`` for
    single-shot data, whose floor the data cannot tell.

    Args:
        images: Shots ``(K, S, H, W)``.

    Returns:
        ``(K,)`` float64, or ``None`` when ``S < 2``.

    Example:
        >>> shots = torch.ones(1, 2, 4, 4); shots[0, 1] += 0.5
        >>> round(float(shot_noise_l1(shots)[0]), 3)
        0.2
    """
    if images.ndim != 4:
        raise ValueError(f"images must be (K, S, H, W); got {tuple(images.shape)}.")
    s = images.shape[1]
    if s < 2:
        return None
    x = images.detach().to(torch.float64)
    # E[sample std] = c4 sigma for Gaussian noise
    c4 = math.sqrt(2.0 / (s - 1)) * math.exp(
        math.lgamma(s / 2) - math.lgamma((s - 1) / 2)
    )
    sem = x.std(1) / (c4 * math.sqrt(s))
    mean = x.mean(1)
    total = mean.sum((-2, -1)).clamp_min(1e-300)
    return math.sqrt(2.0 / math.pi) * sem.sum((-2, -1)) / total
