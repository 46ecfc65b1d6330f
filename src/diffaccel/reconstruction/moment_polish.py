"""Moment polish: each member's covariance corrected so that its screens'
second moments, tracked exactly, equal the measured ones.

Training fits the *shapes* of the images (a KL distance), which leaves their
second moments a few tenths of a percent off per setting; the linear moment
design of :mod:`~diffaccel.reconstruction.unseen` does not describe how the
exact (smoothed) images respond to some entries of the covariance (on the
first member of a strongly chirped synthetic beam, a 0.01 change of px-pz,
pz-pz or x-z moves the tracked moments by 3.4e-3, 1.0e-3 and 2.4e-3 rms,
the design predicts 1.8e-3, 0.5e-3 and 2.9e-3; the cause, chromatic terms or
the screen edges, is not isolated). On a strongly chirped beam those small
errors, carried along the barely seen directions, move the z emittance by
tens of percent (z-pz +0.949 and 0.03 % uncorrelated spread: -30 %).

The polish is one Gauss-Newton step (or a few) on the relative second moments
``<xx>, <yy>, <xy>`` of every training image, the unknowns the 21 covariance
entries in correlation units. Its Jacobian is taken by finite differences of
the exact images of one fixed quasi-random particle set moved by transport
maps (:func:`~diffaccel.reconstruction.unseen.transport_map`), so nothing is
linearised but the step itself. Directions whose singular value is below
:data:`POLISH_TOLERANCE` of the largest are left as they are: the images do
not see them, and :func:`~diffaccel.reconstruction.unseen.place_members`
sets them afterwards. Measured and simulated images are compared after the
training's loss smoothing, so the point spreads agree
(:func:`~diffaccel.reconstruction.training.smoothed_for_loss`), and each in
the same box around the simulated image's centroid as the moment posterior
(:data:`~diffaccel.reconstruction.uncertainty.MOMENT_WINDOW`), so a camera's
residual background and read noise far from the beam do not enter the moments.

Measured with the default settings (``benchmarks/reconstruction_6d_beams.py``
and ``reconstruction_6d.py``; the polish on whole-frame moments), emit z
without / with the polish: the strongly chirped beam above -30.1 / +0.3 %, two
other shared-file-like beams -7.4 / -2.7 % (6D -15.4 / -8.9 %) and -1.0 /
+0.5 %, the shared 6D file -1.1 / -0.3 % (6D +2.1 / +0.0 %). Beams whose truth
the placement's prior misplaces stay off (-38.4 / -34.5 % for a px-pz partial
correlation of +0.09). With the moments in the box: the shared 6D file emit z
-0.5 %, 6D -1.1 %; camera frames of a DAQ folder (``benchmarks/daq_6d.py``:
pedestal, read and shot noise) agree with the noise-free file within 0.9
reported std and their held-out relative L1 is 0.089 / 0.092 against 0.102 /
0.093 (on whole-frame moments: 2.05 std, 0.190 / 0.174).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from diffaccel.reconstruction.forward import ScreenForwardModel
from diffaccel.reconstruction.generator import BeamGenerator
from diffaccel.reconstruction.uncertainty import (
    MOMENT_WINDOW,
    image_moments,
    moment_window,
)
from diffaccel.reconstruction.unseen import _fold, transport_map

__all__ = [
    "POLISH_TOLERANCE",
    "PolishReport",
    "image_second_moments",
    "polish_members",
    "polish_transport",
]

#: Singular values of the relative-moment Jacobian below this fraction of the
#: largest are not corrected. On the AWA 6D layout (a chirped beam's members) the
#: four smallest are 0.053, 0.027, 0.0055 and 0.0006: the last two are the
#: directions the placement sets (px-pz and py-z traded against pz and z).
POLISH_TOLERANCE = 0.02
#: Finite-difference step of the Jacobian [correlation units of each entry].
POLISH_STEP = 0.01
#: Quasi-random particles per member for the polish.
POLISH_PARTICLES = 2**14

_ENTRIES = [(i, j) for i in range(6) for j in range(i, 6)]


@dataclass
class PolishReport:
    """What the polish did to one member.

    Attributes:
        residual_before: Rms relative mismatch of the image second moments
            before the polish (dimensionless).
        residual_after: The same after it.
        kept: Jacobian directions corrected (of 21).
        applied: Whether a step was taken (False: no step lowered the
            mismatch or kept the covariance positive definite).
    """

    residual_before: float
    residual_after: float
    kept: int
    applied: bool

    def to_dict(self) -> dict:
        """Plain-Python form (JSON)."""
        return {
            "residual_before": self.residual_before,
            "residual_after": self.residual_after,
            "kept": self.kept,
            "applied": self.applied,
        }


def image_second_moments(
    images: Tensor, forward: ScreenForwardModel, window: Tensor | None = None
) -> Tensor:
    """Second moments about each image's centroid.

    Args:
        images: Screen images of one scan (any positive sum).
        forward: Its forward model (pixel centres).
        window: Optional ``(K, H, W)`` pixel weights (e.g. a
            :func:`~diffaccel.reconstruction.uncertainty.moment_window`).

    Shapes:
        ``(K, H, W) -> (K, 3)`` float64: ``<xx>, <yy>, <xy>`` [m^2].
    """
    xs, ys = forward.screen.pixel_centers(dtype=torch.float64)
    m = image_moments(images, xs.to(images.device), ys.to(images.device), window)
    return m[:, [2, 4, 3]]  # <x>, <y>, <xx>, <xy>, <yy> -> <xx>, <yy>, <xy>


def _relative(moments: Tensor, scale: Tensor) -> Tensor:
    """``(K, 3)`` moments divided by ``scale`` rows, flattened."""
    return (moments / scale).reshape(-1)


def _scale(moments: Tensor) -> Tensor:
    """Row scales ``<xx>, <yy>, sqrt(<xx><yy>)`` of ``(K, 3)`` moments."""
    vxx, vyy = moments[:, 0].abs(), moments[:, 1].abs()
    return torch.stack([vxx, vyy, (vxx * vyy).sqrt()], -1).clamp_min(1e-300)


def polish_transport(
    particles: Tensor,
    forwards: Sequence[ScreenForwardModel],
    measured: Sequence[Tensor],
    settings: Sequence[Tensor],
    *,
    tolerance: float = POLISH_TOLERANCE,
    step: float = POLISH_STEP,
    iterations: int = 1,
    window_sigma: float = MOMENT_WINDOW,
) -> tuple[Tensor, PolishReport]:
    """Linear map of a particle set whose images' second moments match ``measured``.

    Args:
        particles: Bmad coordinates ``(N, 6)`` (a fixed, e.g. quasi-random, set).
        forwards: Forward model of each scan (with the point spread the
            measured images have).
        measured: Measured images of each scan ``(K_s, H_s, W_s)``.
        settings: Settings of those images ``(K_s, P_s)``.
        tolerance: See :data:`POLISH_TOLERANCE`.
        step: Finite-difference step [correlation units].
        iterations: Gauss-Newton steps.
        window_sigma: Half-width of each image's moment box in rms of the
            image ``particles`` give (fixed through the steps; see
            :data:`~diffaccel.reconstruction.uncertainty.MOMENT_WINDOW`).

    Returns:
        ``(A, report)``: the particles become ``mu + (x - mu) A^T`` with ``mu``
        their centroid; ``A`` is ``(6, 6)`` float64 (the identity where no
        step helped).
    """
    if particles.ndim != 2 or particles.shape[-1] != 6:
        raise ValueError(f"particles must be (N, 6); got {tuple(particles.shape)}.")
    x0 = particles.detach()
    with torch.no_grad():
        windows = []
        for f, s in zip(forwards, settings, strict=True):
            xs, ys = f.screen.pixel_centers(dtype=torch.float64)
            img = f.images(x0, s)
            windows.append(
                moment_window(img, xs.to(img.device), ys.to(img.device), window_sigma)
            )
    target = torch.cat(
        [
            image_second_moments(m, f, w)
            for f, m, w in zip(forwards, measured, windows, strict=True)
        ]
    ).cpu()

    def moments(x: Tensor) -> Tensor:
        with torch.no_grad():
            return torch.cat(
                [
                    image_second_moments(f.images(x, s), f, w).cpu()
                    for f, s, w in zip(forwards, settings, windows, strict=True)
                ]
            )

    mu = x0.to(torch.float64).mean(0)
    total = torch.eye(6, dtype=torch.float64)

    def moved(a: Tensor) -> Tensor:
        out = mu + (x0.to(torch.float64) - mu) @ a.T
        return out.to(x0.dtype)

    m = moments(x0)  # of the current particles: updated with each step taken
    scale = _scale(target)
    before = float(_relative(target - m, scale).square().mean().sqrt())
    best, kept, applied = before, 0, False
    for _ in range(iterations):
        x = moved(total)
        cov = torch.cov(x.to(torch.float64).T)
        sig = cov.diagonal().clamp_min(1e-300).sqrt()
        columns = []
        for i, j in _ENTRIES:
            d = torch.zeros(6, 6, dtype=torch.float64)
            d[i, j] = d[j, i] = step * sig[i] * sig[j]
            a = transport_map(cov, cov + d)
            columns.append(_relative(moments(moved(a @ total)) - m, scale) / step)
        jac = torch.stack(columns, 1)
        resid = _relative(target - m, scale)
        u, sv, vh = torch.linalg.svd(jac, full_matrices=False)
        keep = sv > tolerance * sv[0]
        kept = int(keep.sum())
        dc = vh[keep].T @ ((u[:, keep].T @ resid) / sv[keep])
        d = torch.zeros(6, 6, dtype=torch.float64)
        for k, (i, j) in enumerate(_ENTRIES):
            d[i, j] = d[j, i] = dc[k] * sig[i] * sig[j]
        for frac in (1.0, 0.5, 0.25):  # a step that lowers the mismatch, or none
            new = cov + frac * d
            if float(torch.linalg.eigvalsh(new).min()) <= 0:
                continue
            a = transport_map(cov, new) @ total
            m_new = moments(moved(a))
            r = float(_relative(target - m_new, scale).square().mean().sqrt())
            if r < best:
                best, total, applied, m = r, a, True, m_new
                break
        else:
            break
    return total, PolishReport(before, best, kept, applied)


def polish_members(
    snapshots: Sequence[dict],
    forwards: Sequence[ScreenForwardModel],
    measured: Sequence[Tensor],
    settings: Sequence[Tensor],
    *,
    width: int,
    depth: int,
    seed: int = 0,
    n_particles: int = POLISH_PARTICLES,
    iterations: int = 1,
) -> tuple[list[dict], list[PolishReport]]:
    """Each 6D member's generator moved by :func:`polish_transport`.

    Args:
        snapshots: Generator state dicts (``BeamGenerator``, 6D) of the members.
        forwards: Forward model of each training scan (the loss's point spread).
        measured: Training images of each scan (the loss's smoothing).
        settings: Training settings of each scan.
        width: MLP width of the generators.
        depth: MLP depth of the generators.
        seed: Seed of each member's quasi-random particles.
        n_particles: Particles per member.
        iterations: Gauss-Newton steps per member.

    Returns:
        New state dicts (the inputs are not changed) and one
        :class:`PolishReport` per member.
    """
    out, reports = [], []
    for state in snapshots:
        gen = BeamGenerator(6, width=width, depth=depth, scale=torch.ones(6))
        gen.load_state_dict(state)
        gen.requires_grad_(False)
        g = torch.Generator().manual_seed(seed)
        with torch.no_grad():
            x = gen(n_particles, generator=g, quasi_random=True)
        a, report = polish_transport(
            x, forwards, measured, settings, iterations=iterations
        )
        reports.append(report)
        mu = x.to(torch.float64).mean(0)
        out.append(_fold(state, a, mu) if report.applied else dict(state))
    return out, reports
