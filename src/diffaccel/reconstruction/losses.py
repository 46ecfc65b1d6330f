"""Entropy estimates and image-mismatch penalties for phase-space reconstruction."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from diffaccel.reconstruction.uncertainty import image_moments

ImageLoss = Literal["l1", "l2", "kl"]


def _check_particles(particles: Tensor) -> None:
    if particles.ndim != 2 or particles.shape[1] < 2:
        raise ValueError(
            "particles must have shape (N, D) with D >= 2; "
            f"got {tuple(particles.shape)}."
        )


_REWEIGHT_ITERATIONS = 4


def robust_covariance(particles: Tensor, radius: float | None = 4.0) -> Tensor:
    """Core covariance of a particle cloud with redescending weights, in float64.

    Each particle gets the weight ``exp(-d^2 / (2 radius^2))`` where ``d`` is its
    Mahalanobis distance from the core (found by a few re-weighting iterations
    starting from the plain covariance; weights are constants for the
    gradient). Far particles get weight ~0, so a halo pushed far out (e.g.
    off the screen, where sum-normalised images cannot see it) neither enlarges
    the estimate nor feels a gradient from it: an optimiser that maximises
    ``log det`` cannot gain entropy that way. For a fixed beam shape the result
    is a fixed fraction of the true covariance, which only shifts ``log det`` by
    a constant. ``radius=None`` returns the plain covariance.

    Args:
        particles: Coordinates, any units.
        radius: Mahalanobis scale of the weights; None disables them.

    Shapes:
        ``particles (N, D)`` -> ``(D, D)`` float64.

    Example:
        >>> x = torch.randn(4000, 2, generator=torch.Generator().manual_seed(0))
        >>> robust_covariance(x, radius=None).diagonal().round(decimals=1)
        tensor([1., 1.], dtype=torch.float64)
    """
    _check_particles(particles)
    x = particles.to(torch.float64)
    mu = x.mean(0)
    xc = x - mu
    cov = xc.T @ xc / (x.shape[0] - 1)
    if radius is None:
        return cov
    with torch.no_grad():
        # A far halo inflates the plain covariance, which hides the halo from its
        # own Mahalanobis test; re-weighting a few times converges to the core.
        # Small (D, D) algebra only: the Mahalanobis distances come from one
        # (N, D) @ (D, D) product with the inverse Cholesky factor, and the
        # weighted sums are matrix-vector products.
        xd = x.detach()
        eye = torch.eye(cov.shape[0], dtype=cov.dtype, device=cov.device)
        ref_mu, ref_cov = mu.detach(), cov.detach()
        for _ in range(_REWEIGHT_ITERATIONS):
            jitter = 1e-12 * ref_cov.diagonal().mean().clamp_min(1e-300) * eye
            chol = torch.linalg.cholesky(ref_cov + jitter)
            inv = torch.linalg.solve_triangular(chol, eye, upper=False)
            z = (xd - ref_mu) @ inv.T
            w = torch.exp(z.square().sum(1) * (-0.5 / radius**2))
            w_sum = w.sum()
            ref_mu = (w @ xd) / w_sum
            xr = xd - ref_mu
            # undo the shrinkage of Gaussian weights for a Gaussian core
            ref_cov = (xr.T * w) @ xr * ((1 + radius**-2) / w_sum)
        w = w / w_sum
    mu_w = w @ x
    xw = x - mu_w
    return (xw.T * w) @ xw


def gaussian_entropy(
    particles: Tensor, radius: float | None = 4.0, scale: Tensor | None = None
) -> Tensor:
    """Entropy bound ``1/2 log det Sigma`` of a particle cloud [nats, up to a constant].

    The covariance is the tail-robust one of :func:`robust_covariance`, computed in
    float64 after dividing each coordinate by ``scale`` (so the determinant is
    well conditioned; this only shifts the result by a constant). The log
    determinant comes from a Cholesky factor, which is stable for the tiny
    eigenvalues of beam covariances.

    Args:
        particles: Coordinates ``(N, D)``.
        radius: See :func:`robust_covariance`.
        scale: Per-coordinate normalisation ``(D,)``; unit if None.

    Shapes:
        ``(N, D)`` -> ``()`` float64.

    Example:
        >>> x = torch.randn(4000, 2, generator=torch.Generator().manual_seed(0))
        >>> bool(gaussian_entropy(2 * x, radius=None) - gaussian_entropy(x, radius=None)
        ...      - math.log(4.0) < 1e-9)
        True
    """
    _check_particles(particles)
    x = particles.to(torch.float64)
    if scale is not None:
        x = x / torch.as_tensor(scale, dtype=torch.float64, device=x.device)
    cov = robust_covariance(x, radius=radius)
    eye = torch.eye(cov.shape[0], dtype=cov.dtype, device=cov.device)
    chol = torch.linalg.cholesky(cov + 1e-12 * eye)
    return chol.diagonal().log().sum()


def gaussian_prior_term(particles: Tensor, prior_std: Tensor) -> Tensor:
    """Cross-entropy ``E[x^2 / (2 sigma_p^2)]`` of a zero-mean Gaussian prior [nats].

    Subtracting it from :func:`gaussian_entropy` gives the entropy *relative* to a
    broad Gaussian prior (maximum-entropy with a prior, as in MENT), which keeps
    coordinates that the measurement cannot see (e.g. ``z`` in a quad scan) at the
    prior width instead of letting them grow without bound.

    Args:
        particles: Coordinates ``(N, D)``.
        prior_std: Prior rms width of each coordinate ``(D,)``, same units.

    Shapes:
        ``(N, D)``, ``(D,)`` -> ``()`` float64.
    """
    _check_particles(particles)
    x = particles.to(torch.float64)
    s = torch.as_tensor(prior_std, dtype=torch.float64, device=x.device)
    return 0.5 * (x / s).square().sum(1).mean()


def image_distance(
    simulated: Tensor, measured: Tensor, kind: ImageLoss = "l1"
) -> Tensor:
    """Mismatch between two sets of sum-normalised screen images, one per image.

    * ``"l1"``: ``sum |s - m|`` (0 = perfect, 2 = disjoint); the default.
    * ``"l2"``: ``sum (s - m)^2 / sum m^2`` (relative squared error).
    * ``"kl"``: ``sum m log(m / s)`` (KL divergence, floor ``1e-12`` on both).

    Args:
        simulated: Simulated images ``(*K, H, W)``, each summing to 1.
        measured: Measured images ``(*K, H, W)``, each summing to 1.
        kind: ``"l1"``, ``"l2"`` or ``"kl"``.

    Shapes:
        ``(*K, H, W)``, ``(*K, H, W)`` -> ``(*K,)``.

    Raises:
        ValueError: for mismatched shapes or an unknown ``kind``.

    Example:
        >>> m = torch.full((2, 4, 4), 1 / 16)
        >>> s = m.clone(); s[:, 0, 0] += 1 / 16; s[:, 0, 1] -= 1 / 16
        >>> image_distance(s, m)
        tensor([0.1250, 0.1250])
    """
    if simulated.shape != measured.shape:
        raise ValueError(
            f"simulated {tuple(simulated.shape)} and measured "
            f"{tuple(measured.shape)} images differ in shape."
        )
    if kind == "l1":
        return (simulated - measured).abs().sum((-2, -1))
    if kind == "l2":
        num = (simulated - measured).square().sum((-2, -1))
        return num / measured.square().sum((-2, -1)).clamp_min(1e-30)
    if kind == "kl":
        m = measured.clamp_min(1e-12)
        s = simulated.clamp_min(1e-12)
        return (m * (m / s).log()).sum((-2, -1))
    raise ValueError(f"image loss must be 'l1', 'l2' or 'kl'; got {kind!r}.")


def off_screen_allowance(measured: Tensor, border: int = 2) -> Tensor:
    """Fraction of the beam allowed to miss the screen, from the measured border.

    A beam clipped by the screen edge leaves intensity in the outer pixels of
    its (sum-normalised) image; one that is fully on the screen does not. We
    allow twice the mass of the outer ``border``-pixel ring to be off screen
    (at most 5 %); more than that is penalised by :func:`image_penalty`.

    Shapes:
        ``(*K, H, W)`` -> ``(*K,)``.

    Example:
        >>> off_screen_allowance(torch.full((1, 10, 10), 0.01))
        tensor([0.0500])
    """
    inner = measured[..., border:-border, border:-border].sum((-2, -1))
    ring = measured.sum((-2, -1)) - inner
    return (2.0 * ring).clamp(0.0, 0.05)


def image_penalty(
    simulated: Tensor,
    measured: Tensor,
    kind: ImageLoss = "l1",
    allowance: Tensor | None = None,
) -> Tensor:
    """Image mismatch plus mass missing from the screen, one value per image.

    ``D = image_distance(s / sum s, m) + relu(1 - sum s - a)``: the simulated
    image (whose sum is the fraction of the beam on the screen) is compared in
    shape with the sum-normalised measurement, and mass off the screen beyond
    the allowance ``a`` (see :func:`off_screen_allowance`) is penalised in the
    same units (fraction of the beam). Sum-normalisation alone hides a halo
    pushed off the screen; comparing unnormalised images instead
    would bias beams whose real tails are clipped by the screen.

    Args:
        simulated: Simulated images ``(*K, H, W)`` with sums in [0, 1].
        measured: Sum-normalised measured images ``(*K, H, W)``.
        kind: Distance, see :func:`image_distance`.
        allowance: Off-screen fraction allowed per image ``(*K,)``; 0 if None.

    Shapes:
        ``(*K, H, W)``, ``(*K, H, W)`` -> ``(*K,)``.

    Example:
        >>> m = torch.full((1, 4, 4), 1 / 16)
        >>> image_penalty(0.9 * m, m)
        tensor([0.1000])
    """
    total = simulated.sum((-2, -1))
    shape = simulated / total.clamp_min(1e-6)[..., None, None]
    off = 1.0 - total
    if allowance is not None:
        off = off - allowance
    return image_distance(shape, measured, kind) + off.clamp_min(0.0)


class ImagePenalty:
    """Training form of ``weight * image_penalty(s, m, kind, allowance).sum()``.

    The measured images, their clamp and the allowance are prepared once; with
    ``kind = "kl"`` (the default of training) a call is a dozen whole-image
    kernels with a hand-written gradient instead of the ~100 small autograd
    operations of :func:`image_penalty` (fewer ATen ops per step). Other
    kinds use :func:`image_penalty` itself.

    Args:
        measured: Sum-normalised measured images ``(K, H, W)``. With ``kind =
            "kl"`` pixels may be negative (the zero-mean noise of a
            background-subtracted image): the distance is ``sum m log m+ -
            sum m log s`` (``m+`` the positive pixels, a constant), linear in
            ``m``, so the noise leaves its expectation and minimum unbiased;
            images without negative pixels give the plain KL.
        kind: Image distance, see :func:`image_distance`.
        allowance: Off-screen fraction allowed per image ``(K,)``; 0 if None.
        weight: Factor of the sum over images (e.g. 1 / number of images of
            all scans, so that the penalties of all scans average).
        offset: With ``kind = "kl"``: ``eps`` added to every pixel of the
            sum-normalised simulated image, ``sum m log(m / (s + eps))``, in
            place of the ``1e-12`` floor. The simulated image of ``N``
            particles is noisy (pixel variance ``kappa s / N``, see
            :meth:`~diffaccel.reconstruction.forward.ScreenForwardModel.pixel_kernel_sum_sq`),
            and ``E[log s_hat] < log s``: without the offset the KL distance is
            lowest for a beam ~0.4-1.5 % wider than the one it was sampled
            from (AWA 6D, 16 384 particles). An offset of order ``kappa / N``
            cancels that bias (``ReconstructionConfig.sampling_offset``). The
            constant ``sum m log(1 + H W eps)`` is added so that the value stays
            >= 0 for unit-sum images (the gradient is that of the formula).

    Shapes:
        ``__call__(simulated (K, H, W))`` -> ``()``.
    """

    def __init__(
        self,
        measured: Tensor,
        kind: ImageLoss = "kl",
        allowance: Tensor | None = None,
        weight: float = 1.0,
        offset: float = 0.0,
    ) -> None:
        if kind not in ("l1", "l2", "kl"):
            raise ValueError(f"image loss must be 'l1', 'l2' or 'kl'; got {kind!r}.")
        if not (math.isfinite(offset) and offset >= 0.0):
            raise ValueError(f"image offset must be finite and >= 0; got {offset}.")
        if offset > 0.0 and kind != "kl":
            raise ValueError(f"an image offset needs kind 'kl'; got {kind!r}.")
        self.offset = float(offset)
        self.kind = kind
        self.measured = measured
        self.allowance = allowance
        self.weight = float(weight)
        self.k = measured.shape[0]
        allow = torch.zeros(self.k) if allowance is None else allowance
        allow = allow.to(dtype=measured.dtype, device=measured.device)
        self.one_minus_allowance = torch.sub(1.0, allow)  # (K,)
        # pixels >= 0 floored at 1e-12 as in image_distance's "kl"; negative
        # pixels (zero-mean noise of a background-subtracted image) are kept:
        # the distance's dependence on s, -sum m log s, is linear in m, so
        # noise of zero mean leaves its expectation (and minimum) unbiased,
        # where clipping it at 0 would add a positive floor to the tails
        self.m = torch.where(measured < 0, measured, measured.clamp_min(1e-12))
        self.signed = bool((measured < 0).any())
        # sum m log m over the pixels > 0: the constant part of the distance
        # (for images without negative pixels the value is the plain KL)
        self.m_log_m = (self.m.clamp_min(1e-12).log() * self.m.clamp_min(0)).sum()
        kw = {"dtype": measured.dtype, "device": measured.device}
        self.constants = {
            name: torch.tensor(v, **kw)
            for name, v in (
                ("tiny", 1e-12),
                ("min_total", 1e-6),
                ("zero", 0.0),
                ("one", 1.0),
                ("weight", self.weight),
                ("offset", self.offset),
            )
        }
        # with an offset the compared image sums to 1 + H W eps per unit of
        # m: adding sum_k M_k log(1 + H W eps) (M_k = sum m_k) keeps the value
        # >= the plain distance's floor (0 for unit-sum m), a constant
        h, w = measured.shape[-2:]
        shift = self.m.sum((-2, -1)).sum() * math.log1p(h * w * self.offset)
        self.constants["kl_shift"] = shift.to(**kw)

    def __call__(self, simulated: Tensor) -> Tensor:
        if simulated.shape != self.measured.shape:
            raise ValueError(
                f"simulated {tuple(simulated.shape)} and measured "
                f"{tuple(self.measured.shape)} images differ in shape."
            )
        if self.kind != "kl":
            d = image_penalty(simulated, self.measured, self.kind, self.allowance)
            return d.sum() * self.weight
        return _KLPenaltyFn.apply(simulated, self)


class MomentMatch:
    """Second moments of each simulated image against the measured image's.

    ``weight * sum_k sum_a ((S_ka(sim) - S_ka(meas)) / s_ka)^2`` over the
    images ``k`` and ``a = xx, yy, xy``: the second central moments inside a
    fixed window of each image (the same pixels on both sides), relative to
    the measured ``s = S_xx, S_yy, sqrt(S_xx S_yy)``. The image distance fits
    the shapes of the images; where the generator cannot take the true shape
    exactly, its optimum trades second moments for shape, and a strong chirp
    (z-pz correlation 0.9 and more) turns a few tenths of a percent of an
    image's second moment into 10-25 % of the z emittance. This term makes the
    moments part of what the fit must reproduce.

    Args:
        measured: Sum-normalised measured images ``(K, H, W)`` (pixels may be
            negative: signed weights, as in
            :func:`~diffaccel.reconstruction.uncertainty.image_moments`).
        window: 0/1 weights ``(K, H, W)``: the pixels that count.
        weight: ``weight`` (e.g. the term's strength / number of images).

    Shapes:
        ``__call__(simulated (K, H, W))`` -> ``()``.
    """

    def __init__(self, measured: Tensor, window: Tensor, weight: float) -> None:
        if window.shape != measured.shape:
            raise ValueError(
                f"window {tuple(window.shape)} and measured "
                f"{tuple(measured.shape)} images differ in shape."
            )
        if not (math.isfinite(weight) and weight >= 0):
            raise ValueError(f"moment weight must be finite and >= 0; got {weight}.")
        k, h, w = measured.shape
        win = window.detach().to(torch.float64)
        # pixel offsets from the measured centroid in the window (float64, once):
        # the sums below are then moments about a point near each image's
        # centroid, free of the cancellation of raw moments in float32
        xs = torch.arange(w, dtype=torch.float64, device=win.device)
        ys = torch.arange(h, dtype=torch.float64, device=win.device)
        c = image_moments(measured.detach().to(torch.float64), xs, ys, win)
        dx = (xs[None, :] - c[:, 0:1])[:, None, :]  # (K, 1, W)
        dy = (ys[None, :] - c[:, 1:2])[:, :, None]  # (K, H, 1)
        terms = (torch.ones_like(dx), dx, dy, dx * dx, dy * dy, dx * dy)
        basis = torch.stack(torch.broadcast_tensors(*terms), 1)  # (K, 6, H, W)
        basis = basis * win[:, None]  # 1, x, y, xx, yy, xy in the window
        #: ``(K, H W, 6)``: an image's six windowed sums are one batched product
        basis = basis.reshape(k, 6, h * w).transpose(1, 2)
        self.basis = basis.to(measured.dtype).contiguous()
        self.weight = float(weight)
        # columns of the sums (1, x, y, xx, yy, xy) that the means of each
        # second moment (xx, yy, xy) multiply
        self._a = torch.tensor([1, 2, 1], device=measured.device)
        self._b = torch.tensor([1, 2, 2], device=measured.device)
        self.target = self.moments(measured)
        sxx, syy = self.target[:, 0], self.target[:, 1]
        scale = torch.stack([sxx, syy, (sxx * syy).clamp_min(0).sqrt()], -1)
        self.scale = scale.clamp_min(1e-6)
        self.inv_scale = 1.0 / self.scale

    def sums(self, images: Tensor) -> Tensor:
        """``(K, 6)``: the windowed sums of ``images`` (1, x, y, xx, yy, xy
        about the measured centroid)."""
        k = images.shape[0]
        return torch.bmm(images.reshape(k, 1, -1), self.basis)[:, 0]

    def moments(self, images: Tensor) -> Tensor:
        """``(K, 3)``: ``S_xx, S_yy, S_xy`` [pixel^2] of ``images`` in the window."""
        s = self.sums(images)
        q = s / s[:, :1].clamp_min(torch.finfo(s.dtype).tiny)
        return q[:, 3:] - q.index_select(1, self._a) * q.index_select(1, self._b)

    def __call__(self, simulated: Tensor) -> Tensor:
        return _MomentMatchFn.apply(simulated, self)


class _MomentMatchFn(torch.autograd.Function):
    """:class:`MomentMatch`'s value with its gradient written out.

    With the windowed sums ``s_j = sum_p B_pj I_p`` (``B``: the basis 1, x, y,
    xx, yy, xy), ``q = s / s_0`` and the moments ``S_a = q_a - q_i(a) q_j(a)``
    (``xx: q_3 - q_1^2``, ``yy: q_4 - q_2^2``, ``xy: q_5 - q_1 q_2``), the
    value is ``w sum r^2`` with ``r = (S - target) / scale``. Backward:
    ``g = 2 w r / scale``; ``dq_a = g``, ``dq_i -= g q_j``, ``dq_j -= g q_i``;
    ``ds = (dq - (dq . q) e_0) / s_0``; ``dI = B ds``.
    """

    @staticmethod
    def forward(ctx, images: Tensor, spec: MomentMatch) -> Tensor:  # type: ignore[override]
        sums = spec.sums(images)
        inv_t = sums[:, :1].clamp_min(torch.finfo(sums.dtype).tiny).reciprocal()
        q = sums * inv_t
        qa, qb = q.index_select(1, spec._a), q.index_select(1, spec._b)
        r = (q[:, 3:] - qa * qb - spec.target) * spec.inv_scale
        ctx.save_for_backward(q, qa, qb, r, inv_t)
        ctx.spec, ctx.image_shape = spec, images.shape
        return (r * r).sum() * spec.weight

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None]:  # type: ignore[override]
        q, qa, qb, r, inv_t = ctx.saved_tensors
        spec = ctx.spec
        g = r * spec.inv_scale * (2.0 * spec.weight) * grad  # (K, 3)
        dq = torch.zeros_like(q)
        dq[:, 3:] = g
        dq.index_add_(1, spec._a, -g * qb)
        dq.index_add_(1, spec._b, -g * qa)
        dq[:, :1] -= (dq * q).sum(1, keepdim=True)
        ds = dq * inv_t
        d_images = torch.bmm(spec.basis, ds[:, :, None]).reshape(ctx.image_shape)
        return d_images, None


class _KLPenaltyFn(torch.autograd.Function):
    """``weight * sum_k [KL(m_k, s_k / T_k) + relu(1 - T_k - a_k)]``, clamps as in
    :func:`image_penalty`, with its gradient written out: with ``t = max(T,
    1e-6)``, ``s = max(sim / t, 1e-12)``, ``mask = sim / t >= 1e-12``,
    ``d/dsim = weight * (-mask m / (s t) + [T >= 1e-6] sum(mask m sim / (s t))
    / t - [1 - T - a >= 0])``. With an offset ``eps > 0``: ``s = sim / t + eps``
    and ``mask = 1``."""

    @staticmethod
    def forward(ctx, sim: Tensor, spec: ImagePenalty) -> Tensor:  # type: ignore[override]
        k = spec.k
        total = sim.sum((-2, -1))  # (K,) fraction of the beam on the screen
        t = total.clamp_min(1e-6).view(k, 1, 1)
        s_raw = sim / t
        if spec.offset > 0.0:  # m / (s + eps): positive, no clamp
            s_eff = s_raw.add(spec.constants["offset"])
        else:
            s_eff = s_raw.clamp_min(1e-12)
        q = torch.div(spec.m, s_eff)  # m / s
        if spec.signed:  # m log(m / s) = m log m - m log s; q < 0 where m < 0
            kl = torch.sub(spec.m_log_m, torch.mul(spec.m, s_eff.log()).sum())
        else:
            kl = torch.mul(spec.m, q.log()).sum()
        if spec.offset > 0.0:
            kl = torch.add(kl, spec.constants["kl_shift"])
        off = torch.sub(spec.one_minus_allowance, total)
        value = torch.add(kl, off.clamp_min(0.0).sum()).mul_(spec.constants["weight"])
        ctx.save_for_backward(total, t, s_raw, q, off)
        ctx.spec = spec
        return value

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None]:  # type: ignore[override]
        total, t, s_raw, q, off = ctx.saved_tensors
        spec = ctx.spec
        k = spec.k
        c = spec.constants  # 0-d tensors: comparisons with Python floats convert
        if spec.offset == 0.0:
            q = torch.where(s_raw >= c["tiny"], q, c["zero"])  # where the clamp passes
        mass = torch.mul(q, s_raw).sum((-2, -1))  # (K,): sum(mask m s_raw / s)
        a = torch.where(total >= c["min_total"], mass, c["zero"]).div_(t.view(k))
        a = a.sub_(torch.heaviside(off, c["one"]))  # the off-screen term's gradient
        g = torch.addcdiv(a.view(k, 1, 1), q, t, value=-1.0)
        return g.mul_(torch.mul(grad, c["weight"])), None


def penalty_schedule(
    step: int, total_first_cycle: int, start: float, end: float
) -> float:
    """Image-penalty weight at a step: geometric ramp over the first cycle, then flat.

    The weight rises geometrically from ``start`` to ``end`` during the first
    ``total_first_cycle`` steps (early on the entropy shapes a smooth, wide beam;
    later the images dominate), and stays at ``end`` afterwards so that every
    snapshot is taken with the same, final trade-off.

    Args:
        step: 0-based optimisation step.
        total_first_cycle: Length of the ramp [steps].
        start: Initial weight (> 0).
        end: Final weight (> 0).

    Returns:
        The weight (dimensionless).

    Example:
        >>> penalty_schedule(0, 100, 10.0, 1000.0)
        10.0
        >>> penalty_schedule(100, 100, 10.0, 1000.0)
        1000.0
    """
    if start <= 0 or end <= 0:
        raise ValueError(f"penalty weights must be > 0; got {start}, {end}.")
    frac = min(max(step / max(total_first_cycle, 1), 0.0), 1.0)
    return float(start * (end / start) ** frac)


def cyclic_cosine_lr(
    step: int, cycle_length: int, lr_max: float, lr_min: float
) -> float:
    """Learning rate of a cosine cyclic schedule (snapshot ensembling).

    Within each cycle of ``cycle_length`` steps the rate falls from ``lr_max`` to
    ``lr_min`` along half a cosine; a snapshot is taken at the end of each cycle.

    Example:
        >>> cyclic_cosine_lr(0, 10, 1e-2, 1e-4), cyclic_cosine_lr(10, 10, 1e-2, 1e-4)
        (0.01, 0.01)
    """
    t = (step % cycle_length) / cycle_length
    return lr_min + 0.5 * (lr_max - lr_min) * (1.0 + math.cos(math.pi * t))


@dataclass(frozen=True)
class StepSchedule:
    """Learning rate and image-penalty weight of every training step, and the
    steps after which the generator is an ensemble member.

    The learning rate follows :func:`cyclic_cosine_lr` within each cycle of
    ``cycle`` steps, the penalty weight :func:`penalty_schedule` (a ramp over
    the first cycle, then flat); the generator at the end of each cycle after
    the first ``burn_in`` cycles is one member.

    Args:
        cycle: Steps per learning-rate cycle.
        lr_max: Learning rate at the start of each cycle.
        lr_min: Learning rate at the end of each cycle.
        penalty_start: Penalty weight at step 0 (> 0).
        penalty_end: Penalty weight from the end of the first cycle on (> 0).
        burn_in: Cycles at the start whose ends yield no member.

    Example:
        >>> s = StepSchedule(10, 1e-2, 1e-4, 10.0, 1000.0, burn_in=1)
        >>> s.lr(0), s.penalty(10), s.member(10), s.member(20)
        (0.01, 1000.0, False, True)
    """

    cycle: int
    lr_max: float
    lr_min: float
    penalty_start: float
    penalty_end: float
    burn_in: int = 0

    def lr(self, step: int) -> float:
        """Learning rate of step ``step`` (0-based)."""
        return cyclic_cosine_lr(step, self.cycle, self.lr_max, self.lr_min)

    def penalty(self, step: int) -> float:
        """Image-penalty weight of step ``step`` (0-based)."""
        return penalty_schedule(step, self.cycle, self.penalty_start, self.penalty_end)

    def cycle_end(self, done: int) -> bool:
        """Whether the first ``done`` steps end with a whole cycle."""
        return done % self.cycle == 0

    def member(self, done: int) -> bool:
        """Whether the generator after ``done`` steps is an ensemble member
        (the end of a cycle after the burn-in)."""
        return self.cycle_end(done) and done > self.burn_in * self.cycle


class RelativeEntropy:
    """Training form of ``gaussian_entropy(x) - gaussian_prior_term(x - m, s_p)``.

    The same value as the two functions (tail-robust Gaussian entropy bound minus
    the cross-entropy of the prior), for a fixed number of particles, with the
    constants prepared once and a hand-written gradient: a few
    ``(N, D + 1)`` matrix products per call and no host synchronisation, instead
    of the ~400 small operations of the autograd version.

    All moments come from the augmented coordinates ``z1 = (x / scale, 1)``: their
    weighted second-moment matrix ``M = sum_i w_i z1_i z1_i^T / sum_i w_i`` holds
    the weighted mean and covariance, ``det M`` is the determinant of that
    covariance, and ``z1^T M^-1 z1 = 1 + d^2`` gives each Mahalanobis distance
    ``d`` from one product. Rescaling the reference covariance (``N - 1``
    normalisation at the start, the ``1 + radius^-2`` de-shrinking of
    :func:`robust_covariance`) rescales ``d^2``, which is folded into the
    exponent. With the redescending weights held constant (as in
    :func:`robust_covariance`) the gradient of ``1/2 log det`` with respect to
    particle ``i`` is ``w_i Sigma^-1 (x_i - mu_w)`` (in scaled units).

    Args:
        n: Number of particles of every call.
        scale: Per-coordinate normalisation ``(D,)`` (as in :func:`gaussian_entropy`).
        prior_mean: Prior centre ``(D,)``.
        prior_std: Prior rms widths ``(D,)``.
        radius: Mahalanobis scale of the weights; None for the plain covariance.
        reduce: For particles split across processes: sums a small moment
            matrix over all of them in place (e.g.
            ``torch.distributed.all_reduce``); ``n`` is then the total number
            of particles and each process passes its own share. The value, aux
            and gradients equal those of one process holding all particles.

    Shapes:
        ``__call__(particles (N, D))`` -> ``(value (), moments (D + 1, D + 1))``:
        value is ``H - C`` (float64, differentiable); moments is the plain
        moment matrix ``M0`` of ``z1`` (float64, not differentiable; see
        :meth:`entropy_and_rms`). The spec keeps work buffers: call ``backward``
        of one call before the next call (autograd raises otherwise).
    """

    def __init__(
        self,
        n: int,
        scale: Tensor,
        prior_mean: Tensor,
        prior_std: Tensor,
        radius: float | None = 4.0,
        reduce: Callable[[Tensor], object] | None = None,
    ) -> None:
        if n < 2:
            raise ValueError(f"need at least 2 particles; got {n}.")
        f64 = {"dtype": torch.float64, "device": scale.device}
        self.n = n
        self.reduce = reduce
        self.scale = scale.to(**f64)
        d = self.scale.shape[0]
        self.dims = d
        a = self.scale / prior_std.to(**f64)  # prior term in scaled units
        c = prior_mean.to(**f64) / prior_std.to(**f64)
        q = torch.zeros(d + 1, d + 1, **f64)
        q[:d, :d] = torch.diag(a * a)
        q[:d, d] = q[d, :d] = -a * c
        q[d, d] = (c * c).sum()
        self.q = q  # C = 1/2 sum(q * M_plain)
        self.eye = torch.eye(d + 1, **f64)
        self.q_cols = q[:, :d] / n  # dC/dz1_i = q z1_i / n
        self.radius = radius
        # exponent factors of the weights (see the class docstring): the first
        # reference is the plain covariance with N - 1 normalisation, the later
        # ones the weighted covariance times 1 + radius^-2
        if radius is not None:
            self.first = -0.5 / radius**2 * (n - 1) / n
            self.later = -0.5 / radius**2 / (1 + radius**-2)
            self.first_vec = torch.full((d + 1,), self.first, **f64)
            self.later_vec = torch.full((d + 1,), self.later, **f64)
        self.var_factor = n / (n - 1)
        # plain covariance: N - 1 normalisation as in robust_covariance
        self.plain_shift = 0.5 * d * math.log(n / (n - 1))
        self.q_half = 0.5 * q
        self._q_half_list = self.q_half.reshape(-1).tolist()
        self._scale_list = self.scale.tolist()
        self.scale_col = self.scale[:, None]
        self.inv_scale = 1.0 / self.scale
        self._buffers(n)

    def _buffers(self, n_local: int) -> None:
        """Work buffers for calls with ``n_local`` particles (reused by every call)."""
        d = self.dims
        f64 = {"dtype": torch.float64, "device": self.scale.device}
        self.n_local = n_local
        self.zt = torch.ones(d + 1, n_local, **f64)  # z1^T; the last row stays 1
        self.zt_x = self.zt[:d]
        self.z = _transposed(self.zt)
        # column-major buffers: what LAPACK writes, so no copies
        self.y = _transposed(torch.empty(n_local, d + 1, **f64))
        self.inv_l = _transposed(torch.empty(d + 1, d + 1, **f64))
        self.y_rows = _transposed(self.y)  # (N, D + 1), contiguous
        self.raw = torch.empty(d + 1, d + 1, **f64)
        self.raw_total = self.raw.view(-1)[-1:]
        self.inv = torch.empty(d + 1, d + 1, **f64)
        self.inv_cols = self.inv[:, :d]

    def __call__(self, particles: Tensor) -> tuple[Tensor, Tensor]:
        if particles.ndim != 2 or particles.shape[1] != self.dims:
            raise ValueError(
                f"particles must have shape (N, {self.dims}); got "
                f"{tuple(particles.shape)}."
            )
        if particles.shape[0] != self.n_local:
            self._buffers(particles.shape[0])
        return _RelativeEntropyFn.apply(particles, self)

    def entropy_and_rms(
        self, value: float, moments: Sequence[float]
    ) -> tuple[float, list[float]]:
        """``H`` and the plain rms widths from a call's value and moments.

        Host-side bookkeeping for the training history (read every few steps,
        in plain Python), so that a step computes neither: ``H = value + C``
        with the prior cross-entropy ``C = 1/2 sum(q * M0)``, and the rms widths
        from the first and second moments in ``M0`` (``N - 1`` normalisation).

        Args:
            value: ``H - C`` as returned by a call.
            moments: The call's plain moment matrix ``M0``, flattened
                (``(D + 1)^2`` numbers, row-major).
        """
        m = [float(v) for v in moments]
        d = self.dims
        cross = sum(q * v for q, v in zip(self._q_half_list, m, strict=True))
        rms = []
        for i in range(d):
            mean = m[d * (d + 1) + i]
            var = (m[i * (d + 2)] - mean * mean) * self.var_factor
            rms.append(math.sqrt(max(var, 0.0)) * self._scale_list[i])
        return value + cross, rms


def _transposed(t: Tensor) -> Tensor:
    """The transpose of a 2-D tensor as one strided view (a single ATen op)."""
    return t.as_strided(
        (t.shape[1], t.shape[0]), (t.stride(1), t.stride(0)), t.storage_offset()
    )


class _RelativeEntropyFn(torch.autograd.Function):
    # Every tensor op below is counted by benchmarks/reconstruction_step.py
    # (budget: <= 300 ATen ops per training step): the buffers of the spec
    # are filled with out= / in-place ops and the transposes are single views.
    @staticmethod
    def forward(ctx, x: Tensor, spec: RelativeEntropy) -> tuple[Tensor, Tensor]:  # type: ignore[override]
        zt, z = spec.zt, spec.z  # (D + 1, N) and its (N, D + 1) view
        spec.zt_x.copy_(_transposed(x)).div_(spec.scale_col)
        # plain moments M0 = z1^T z1 / n (beta = 0: the input is ignored)
        m0 = torch.addmm(spec.eye, zt, z, beta=0.0, alpha=1.0 / spec.n)
        if spec.reduce is not None:
            spec.reduce(m0)
        cross = torch.mul(spec.q_half, m0).sum()
        if spec.radius is None:
            w = None
            m = m0
        else:
            ref, factor = m0, spec.first_vec
            for _ in range(_REWEIGHT_ITERATIONS):
                # ||L^-1 z1||^2 = z1^T ref^-1 z1 (solve_triangular and
                # cholesky_ex never check for errors: no host synchronisation)
                lower = torch.linalg.cholesky_ex(ref)[0]
                y = torch.linalg.solve_triangular(lower, zt, upper=False, out=spec.y)
                y.mul_(y)
                # factor * d2 of every particle as one matrix-vector product
                w = torch.mv(spec.y_rows, factor).exp_()  # (N,)
                raw = torch.mm(torch.mul(zt, w), z, out=spec.raw)
                if spec.reduce is not None:
                    spec.reduce(raw)
                ref = raw / spec.raw_total  # raw[d, d]: the sum of the weights
                factor = spec.later_vec
            w = w.div_(spec.raw_total)
            m = ref
        chol = torch.linalg.cholesky_ex(m)[0]
        # log det / 2 = trace(log L): the zeros above the diagonal turn to -inf,
        # which the trace never reads (3 ATen ops instead of 6)
        entropy = torch.log(chol).trace()
        if w is None:
            entropy = entropy + spec.plain_shift
        inv_l = torch.linalg.solve_triangular(
            chol, spec.eye, upper=False, out=spec.inv_l
        )
        torch.mm(_transposed(inv_l), inv_l, out=spec.inv)
        ctx.mark_non_differentiable(m0)
        ctx.set_materialize_grads(False)  # no zero gradient made for m0
        # the buffers too: a second call before this backward changes their
        # version, and autograd then raises instead of using the wrong values
        ctx.save_for_backward(w, spec.zt, spec.inv)
        ctx.spec = spec
        ctx.in_dtype = x.dtype
        return entropy - cross, m0

    @staticmethod
    def backward(ctx, grad: Tensor, _aux: Tensor) -> tuple[Tensor | None, None]:  # type: ignore[override]
        w, _, _ = ctx.saved_tensors
        spec = ctx.spec
        n, d = spec.n_local, spec.dims
        # rows: w_i Sigma^-1 (z_i - mu_w) - q z1_i / n, times d(scaled)/dx
        dh = torch.mm(spec.z, spec.inv_cols)
        if w is None:
            dh = dh.div_(spec.n)
        else:
            dh = dh.mul_(w.view(n, 1))
        gz = torch.addmm(dh, spec.z, spec.q_cols, alpha=-1.0)
        out = torch.empty((n, d), dtype=ctx.in_dtype, device=gz.device)
        return torch.mul(gz, torch.mul(spec.inv_scale, grad), out=out), None
