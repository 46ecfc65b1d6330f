"""Quadratic holds on the beam's covariance during training.

A hold adds ``w sum_k t_k^2`` to the training loss, each ``t_k`` a linear
function of the beam's covariance ``S``: ``t_k = sum_ij Q_k,ij S_ij - b_k``.
Training computes the plain moment matrix of every step's particles anyway
(for the entropy), so the hold needs no extra pass over the particles: its
gradient enters through :meth:`MomentHold.surrogate`, exact also when the
particles are split across processes.

:class:`~diffaccel.reconstruction.unseen.UnseenHold`, the prior term of the
6D objective (``ReconstructionConfig.unseen_weight``), holds the directions the
scans cannot see at their prior point this way.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


def held_moments(moments: Tensor) -> Tensor:
    """The plain moments a hold reads: rounded to float32 (threaded float64
    sums scatter in the last bits from run to run, and the hold feeds them
    back into the step; rounded, a resume is bit for bit), as float64."""
    return moments.detach().float().double()


class MomentHold:
    """Penalty ``w sum_k t_k^2`` with ``t = sum_ij Q_k,ij S_ij - b_k``.

    Args:
        weight: ``w``.
        scale: Per-coordinate scale ``(6,)`` of the moments [Bmad units]
            (``RelativeEntropy.scale``).
        n: Particles of the beam (all processes together).

    Attributes:
        q: ``(F, 6, 6)`` coefficients of ``t`` on the covariance [Bmad units].
        b: ``(F,)`` offsets.
        ready: Whether ``q`` and ``b`` are set (else training calls
            :meth:`update` with the first step's moments; it calls it again
            every ``HOLD_EVERY`` steps, a host read of the moments).
        layout: Counts the changes of the number of held directions ``F``.
            Between them :meth:`set` writes ``q`` and ``b`` in place, so a
            training step captured as a CUDA graph reads the current ones.
    """

    def __init__(self, weight: float, scale: Tensor, n: int) -> None:
        if not (math.isfinite(weight) and weight >= 0):
            raise ValueError(f"weight must be finite and >= 0; got {weight}.")
        self.weight = weight
        # rounded to float32: the scale comes from the Gaussian fit to the
        # image moments, whose float64 least squares scatter in the last bits
        # from call to call (MKL), and the hold would carry that into the
        # step (a resume differed from the uninterrupted run)
        self.scale = scale.detach().float().double()
        self.n = n
        self.layout = 0
        self.set(torch.zeros(0, 6, 6, dtype=torch.float64), torch.zeros(6, 6))
        self.ready = False  # until a subclass or update() sets what to hold

    def set(self, q: Tensor, target: Tensor) -> None:
        """Hold ``t = sum_ij Q_k,ij (S - target)_ij`` from now on (``q``
        ``(F, 6, 6)``, ``target`` ``(6, 6)``, both Bmad units, host)."""
        device = self.scale.device
        q = q.to(torch.float64)
        b = (q * target.to(torch.float64)).sum((1, 2))
        if getattr(self, "q", None) is not None and self.q.shape == q.shape:
            self.q.copy_(q)  # in place: what a captured step reads
            self.b.copy_(b)
        else:
            self.q, self.b = q.to(device, copy=True), b.to(device, copy=True)
            self.layout += 1
        self.ready = True

    def covariance(self, moments: Tensor) -> Tensor:
        """Covariance ``(6, 6)`` [Bmad units] from the plain moment matrix.

        ``moments`` is ``M0 = mean(z1 z1^T)`` of ``z1 = (x / scale, 1)``
        ``(7, 7)`` (or flattened), as :class:`~.losses.RelativeEntropy`
        returns it; ``N - 1`` normalisation.
        """
        m = moments.to(self.scale.device, torch.float64).reshape(7, 7)
        mean = m[6, :6]
        cov = (m[:6, :6] - mean[:, None] * mean[None, :]) * (self.n / (self.n - 1))
        return cov * self.scale[:, None] * self.scale[None, :]

    def update(self, moments: Tensor) -> None:
        """Refresh ``q`` and ``b`` from the beam's plain moments (host)."""
        self.ready = True

    def displacement(self, moments: Tensor) -> Tensor:
        """``t (F,)`` of the beam with these plain moments."""
        return (self.q * self.covariance(moments)).sum((1, 2)) - self.b

    def penalty(self, moments: Tensor) -> Tensor:
        """``w sum_k t_k^2`` of the beam with these plain moments (a scalar)."""
        t = self.displacement(moments)
        return self.weight * (t * t).sum()

    def surrogate(self, particles: Tensor, moments: Tensor) -> Tensor:
        """A scalar whose gradient with respect to ``particles`` is the penalty's.

        ``t`` comes from ``moments`` (the whole beam's, detached), the gradient
        through this process's particles ``(N_local, 6)`` [Bmad units]:
        ``d/dx_i = 2 w sum_k t_k (Q_k + Q_k^T)(x_i - mu) / (N - 1)``, exactly
        the penalty's gradient also when the particles are split across
        processes (each holds its share's part). Its value is not the penalty.
        """
        if self.q.shape[0] == 0:
            return torch.zeros((), dtype=torch.float64, device=particles.device)
        m = moments.detach().to(self.scale.device, torch.float64).reshape(7, 7)
        mu = m[6, :6] * self.scale
        t = self.displacement(m)
        xc = particles.to(torch.float64) - mu
        s = xc.T @ xc / (self.n - 1)  # this share's part of the covariance
        return 2.0 * self.weight * ((t[:, None, None] * self.q).sum(0) * s).sum()
