"""Gaussian first guess of a beam from the second moments of quad-scan images."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from diffaccel.reconstruction.forward import ScreenForwardModel


@dataclass(frozen=True)
class GaussianGuess:
    """Centroid and covariance of a Gaussian beam fitted to image moments.

    Args:
        mean: Centroid in Bmad coordinates ``(6,)`` float64.
        cov: Covariance ``(6, 6)`` float64; the longitudinal block is zero
            (images at one screen after quads and drifts do not constrain it).
    """

    mean: Tensor
    cov: Tensor

    def generator_init(
        self,
        dims: int,
        longitudinal_scale: tuple[float, float],
        prior_factor: float,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Initial scale, offset, correlation and prior widths for a generator.

        Returns:
            ``scale (dims,)``, ``offset (dims,)``, ``correlation (dims, dims)`` and
            ``prior_std (dims,)`` (transverse: ``prior_factor`` times the fitted
            widths; longitudinal: ``longitudinal_scale``), all float64.
        """
        cov = self.cov[:dims, :dims].clone()
        mean = self.mean[:dims].clone()
        if dims == 6:
            cov[4:, :] = 0.0
            cov[:, 4:] = 0.0
            cov[4, 4] = longitudinal_scale[0] ** 2
            cov[5, 5] = longitudinal_scale[1] ** 2
        scale = cov.diagonal().sqrt()
        corr = cov / (scale[:, None] * scale[None, :])
        prior = scale.clone()
        prior[:4] *= prior_factor
        return scale, mean, corr, prior


def _psd_2x2(s00: Tensor, s01: Tensor, s11: Tensor, floor: float) -> tuple:
    """Project a 2x2 (s00, s01, s11) onto positive definite with |r| <= 0.95."""
    s00 = s00.clamp_min(floor**2)
    s11 = s11.clamp_min(floor**2 * 1e-6)
    lim = 0.95 * (s00 * s11).sqrt()
    return s00, s01.clamp(-lim, lim), s11


def fit_gaussian(
    forward: ScreenForwardModel, images: Tensor, settings: Tensor
) -> GaussianGuess:
    """Fit the transverse 4x4 centroid and covariance of a beam to image moments.

    Linear optics: for each setting the transfer matrix ``R_k`` comes from the
    forward model (finite differences of the tracking), the screen centroid is
    ``R_k mean`` and the screen second moments are ``R_k Sigma R_k^T``; the
    measured centroids, ``<x^2>``, ``<y^2>`` and ``<xy>`` of the images (minus the
    blur the forward model adds) give a linear least-squares problem for the 4
    centroid and 10 covariance entries. The result is projected onto a positive
    definite matrix; it is a starting point, not a reconstruction.

    Args:
        forward: Forward model of the scan.
        images: Sum-normalised images.
        settings: Settings of those images.

    Shapes:
        ``images (K, H, W)``, ``settings (K, P)``.

    Returns:
        A :class:`GaussianGuess` (float64, on the CPU).
    """
    img = images.detach().to("cpu", torch.float64)
    img = img / img.sum((-2, -1), keepdim=True).clamp_min(1e-300)
    xs, ys = (a.to("cpu", torch.float64) for a in forward.pixel_axes())
    px = img.sum(-2)  # (K, W)
    py = img.sum(-1)  # (K, H)
    mx = (px * xs).sum(-1)
    my = (py * ys).sum(-1)
    blur_x, blur_y = (b**2 for b in forward.blur_sigma())
    vxx = (px * (xs - mx[:, None]) ** 2).sum(-1) - blur_x
    vyy = (py * (ys - my[:, None]) ** 2).sum(-1) - blur_y
    dx = xs[None, None, :] - mx[:, None, None]
    dy = ys[None, :, None] - my[:, None, None]
    vxy = (img * dx * dy).sum((-2, -1))
    r = forward.transfer_matrices(settings).to("cpu", torch.float64)  # (K, 6, 6)
    rx, ry = r[:, 0, :4], r[:, 2, :4]
    # centroid: [mx; my] = [rx; ry] @ mean4
    a = torch.cat([rx, ry], 0)
    b = torch.cat([mx, my], 0)
    mean4 = torch.linalg.lstsq(a, b[:, None]).solution[:, 0]
    # second moments: linear in the 10 upper-triangular entries of Sigma4
    iu = torch.triu_indices(4, 4)
    mult = torch.where(iu[0] == iu[1], 1.0, 2.0).to(torch.float64)

    def rows(u: Tensor, v: Tensor) -> Tensor:
        # <(u.x)(v.x)> = sum_ij u_i v_j S_ij, symmetrised
        uv = 0.5 * (u[:, :, None] * v[:, None, :] + v[:, :, None] * u[:, None, :])
        return uv[:, iu[0], iu[1]] * mult

    a2 = torch.cat([rows(rx, rx), rows(ry, ry), rows(rx, ry)], 0)
    b2 = torch.cat([vxx, vyy, vxy], 0)
    # scale unknowns for conditioning
    col = a2.abs().amax(0).clamp_min(1e-300)
    sol = torch.linalg.lstsq(a2 / col, b2[:, None]).solution[:, 0] / col
    s4 = torch.zeros(4, 4, dtype=torch.float64)
    s4[iu[0], iu[1]] = sol
    s4 = s4 + s4.T - torch.diag(s4.diagonal())
    floor = float(xs.diff().abs().mean()) * 0.5
    for p, q in ((0, 1), (2, 3)):
        s00, s01, s11 = _psd_2x2(s4[p, p], s4[p, q], s4[q, q], floor)
        if s4[q, q] <= 0 or s4[p, p] <= 0:
            # quad scan did not resolve the divergence: use a beam waist guess
            s11 = s00 / float(forward.drift_length()) ** 2
            s01 = torch.zeros_like(s01)
        s4[p, p], s4[p, q], s4[q, p], s4[q, q] = s00, s01, s01, s11
    if torch.linalg.eigvalsh(s4).min() <= 0:
        s4[:2, 2:] = 0.0
        s4[2:, :2] = 0.0
    mean = torch.zeros(6, dtype=torch.float64)
    mean[:4] = mean4
    cov = torch.zeros(6, 6, dtype=torch.float64)
    cov[:4, :4] = s4
    return GaussianGuess(mean=mean, cov=cov)
