"""Entropy estimates and image-mismatch penalties for phase-space reconstruction."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Literal

import torch
from torch import Tensor

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
        ``__call__(particles (N, D))`` -> ``(value (), aux (1 + D,))``: value is
        ``H - C`` (float64, differentiable); aux holds ``H`` and the plain rms
        widths of the particles (float64, not differentiable).
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
        self.var_factor = n / (n - 1)
        # plain covariance: N - 1 normalisation as in robust_covariance
        self.plain_shift = 0.5 * d * math.log(n / (n - 1))

    def __call__(self, particles: Tensor) -> tuple[Tensor, Tensor]:
        return _RelativeEntropyFn.apply(particles, self)


class _RelativeEntropyFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: Tensor, spec: RelativeEntropy) -> tuple[Tensor, Tensor]:  # type: ignore[override]
        n, d = x.shape
        z1 = x.new_ones(n, d + 1, dtype=torch.float64)
        torch.div(x, spec.scale, out=z1[:, :d])
        z1t = z1.t()
        m0 = torch.mm(z1t, z1)  # plain moments
        if spec.reduce is not None:
            spec.reduce(m0)
        m0 = m0.div_(spec.n)
        cross = 0.5 * torch.mul(spec.q, m0).sum()
        if spec.radius is None:
            w = None
            m = m0
        else:
            ref, factor = m0, spec.first
            for _ in range(_REWEIGHT_ITERATIONS):
                # (L^-1 z1)^2 summed = z1^T ref^-1 z1 (solve_triangular and
                # cholesky_ex never check for errors: no host synchronisation)
                lower = torch.linalg.cholesky_ex(ref)[0]
                inv_l = torch.linalg.solve_triangular(lower, spec.eye, upper=False)
                d2 = torch.mm(z1, inv_l.t()).square_().sum(1)
                w = d2.mul_(factor).exp_()
                raw = torch.mm(torch.mul(z1t, w), z1)
                if spec.reduce is not None:
                    spec.reduce(raw)
                ref = raw / raw[d, d]  # raw[d, d]: the sum of the weights
                factor = spec.later
            w = w.div_(raw[d, d])
            m = ref
        chol = torch.linalg.cholesky_ex(m)[0]
        entropy = chol.diagonal().log().sum()
        if w is None:
            entropy = entropy + spec.plain_shift
        inv_l = torch.linalg.solve_triangular(chol, spec.eye, upper=False)
        inv = torch.mm(inv_l.t(), inv_l)
        mean = m0[d, :d]
        var = (m0.diagonal()[:d] - mean * mean).mul_(spec.var_factor)
        rms = var.clamp_min_(0).sqrt_().mul_(spec.scale)
        aux = torch.cat([entropy.reshape(1), rms])
        ctx.mark_non_differentiable(aux)
        ctx.save_for_backward(z1, inv, w)
        ctx.spec = spec
        ctx.in_dtype = x.dtype
        return entropy - cross, aux

    @staticmethod
    def backward(ctx, grad: Tensor, _aux: Tensor) -> tuple[Tensor | None, None]:  # type: ignore[override]
        z1, inv, w = ctx.saved_tensors
        spec = ctx.spec
        d = spec.dims
        g = grad / spec.scale  # (D,): d(scaled)/dx and the incoming gradient
        dh = torch.mm(z1, inv[:, :d])  # rows: Sigma^-1 (z_i - mu_w)
        if w is None:
            dh = dh.div_(spec.n)
        else:
            dh = dh.mul_(w.unsqueeze(1))
        gz = torch.addmm(dh, z1, spec.q_cols, alpha=-1.0)
        return gz.mul_(g).to(ctx.in_dtype), None
