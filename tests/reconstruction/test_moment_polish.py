"""Moment polish: exact-tracking image second moments matched to measured ones."""

from __future__ import annotations

import pytest
import torch

from diffaccel.data import MultiScanDataset
from diffaccel.reconstruction import ReconstructionConfig, ScreenForwardModel
from diffaccel.reconstruction.moment_polish import (
    image_second_moments,
    polish_transport,
)
from diffaccel.reconstruction.uncertainty import MOMENT_WINDOW, moment_window
from diffaccel.reconstruction.unseen import transport_map, unseen_directions


def test_image_second_moments_of_a_two_pixel_image(small_awa6d) -> None:
    fwd = _forwards_of(small_awa6d)[0]
    xs, ys = fwd.screen.pixel_centers(dtype=torch.float64)
    img = torch.zeros(1, len(ys), len(xs), dtype=torch.float64)
    img[0, 3, 4] = 1.0
    img[0, 5, 10] = 3.0
    m = image_second_moments(img, fwd)[0]
    px, py = torch.tensor([xs[4], xs[10]]), torch.tensor([ys[3], ys[5]])
    w = torch.tensor([0.25, 0.75], dtype=torch.float64)
    mx, my = (w * px).sum(), (w * py).sum()
    expected = [
        (w * (px - mx) ** 2).sum(),
        (w * (py - my) ** 2).sum(),
        (w * (px - mx) * (py - my)).sum(),
    ]
    assert torch.allclose(m, torch.stack(expected), rtol=1e-12, atol=0)


def _forwards_of(data: MultiScanDataset) -> list[ScreenForwardModel]:
    return [ScreenForwardModel.from_dataset(s) for _, s in data]


def _corr_units(cov: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    sig = ref.diagonal().sqrt()
    return cov / (sig[:, None] * sig[None, :])


def _truth_imaged(data: MultiScanDataset) -> tuple:
    """``(forwards, settings, truth, measured, mu, cov)``: "measured" is the
    truth imaged by the same forward models (the same rendering)."""
    forwards = _forwards_of(data)
    settings = [s.settings for _, s in data]
    truth = data.ground_truth.to(torch.float64)
    measured = [f.images(truth, s) for f, s in zip(forwards, settings, strict=True)]
    return forwards, settings, truth, measured, truth.mean(0), torch.cov(truth.T)


def test_polish_undoes_a_change_the_images_see(small_awa6d) -> None:
    forwards, settings, truth, measured, mu, cov = _truth_imaged(small_awa6d)
    sig = cov.diagonal().sqrt()
    d = torch.zeros(6, 6, dtype=torch.float64)
    # +4 % of x variance, a z-pz and an x-z correlation 0.03 off: all seen
    for (i, j), v in {(0, 0): 0.04, (4, 5): 0.03, (0, 4): -0.03}.items():
        d[i, j] = d[j, i] = v * sig[i] * sig[j]
    moved = mu + (truth - mu) @ transport_map(cov, cov + d).T
    a, report = polish_transport(moved, forwards, measured, settings)
    polished = mu + (moved - mu) @ a.T
    before = (_corr_units(torch.cov(moved.T) - cov, cov)).abs().max()
    after = (_corr_units(torch.cov(polished.T) - cov, cov)).abs().max()
    assert before > 0.029
    # one Gauss-Newton step on exact images: back within 0.005 (no correction
    # leaves 0.04)
    assert after < 0.005, (before, after)
    assert report.applied and report.kept < 21
    assert report.residual_after < 0.2 * report.residual_before


def test_polish_leaves_what_the_images_do_not_see(small_awa6d) -> None:
    forwards, settings, truth, measured, mu, cov = _truth_imaged(small_awa6d)
    maps = [f.transfer_maps(s) for f, s in zip(forwards, settings, strict=True)]
    direction = unseen_directions(maps, cov)[0]
    # a move along an unseen direction leaves every screen's moments: the
    # polish has nothing to correct and must not undo it
    target = cov + 0.05 * direction
    assert float(torch.linalg.eigvalsh(target).min()) > 0
    moved = mu + (truth - mu) @ transport_map(cov, target).T
    a, report = polish_transport(moved, forwards, measured, settings)
    polished = mu + (moved - mu) @ a.T
    kept = (torch.cov(polished.T) - cov) * direction
    assert float(kept.sum() / (0.05 * direction.square().sum())) == pytest.approx(
        1.0, abs=0.1
    )
    assert report.residual_after <= report.residual_before


def test_polish_refuses_particles_of_the_wrong_shape(small_awa6d) -> None:
    forwards = _forwards_of(small_awa6d)
    settings = [s.settings for _, s in small_awa6d]
    with pytest.raises(ValueError, match=r"particles must be \(N, 6\)"):
        polish_transport(torch.zeros(10, 4), forwards, [], settings)


def test_runs_before_the_polish_load_without_it() -> None:
    d = ReconstructionConfig(dims=6).to_dict()
    assert d["polish_moments"] is True
    del d["polish_moments"]
    assert ReconstructionConfig.from_dict(d).polish_moments is False
    with pytest.raises(ValueError, match="polish_moments must be True or False"):
        ReconstructionConfig(dims=6, polish_moments=1)


def test_polish_ignores_noise_far_from_the_beam(small_awa6d) -> None:
    forwards, settings, truth, measured, mu, cov = _truth_imaged(small_awa6d)
    g = torch.Generator().manual_seed(0)
    noisy = []
    for f, m in zip(forwards, measured, strict=True):
        xs, ys = f.screen.pixel_centers(dtype=torch.float64)
        outside = 1.0 - moment_window(m, xs, ys, MOMENT_WINDOW)
        # zero-mean read noise of 0.2 % of the peak, away from the beam
        noise = torch.randn(m.shape, generator=g, dtype=torch.float64)
        noisy.append(m + 2e-3 * m.amax((-2, -1), keepdim=True) * noise * outside)
    whole = torch.cat(
        [image_second_moments(m, f) for f, m in zip(forwards, noisy, strict=True)]
    )
    clean = torch.cat(
        [image_second_moments(m, f) for f, m in zip(forwards, measured, strict=True)]
    )
    # the whole frame's second moments weight that noise by r^2: 10 % off and more
    assert float((whole[:, :2] / clean[:, :2] - 1).abs().max()) > 0.1

    def change(window_sigma: float) -> float:
        a, _ = polish_transport(
            truth, forwards, noisy, settings, window_sigma=window_sigma
        )
        polished = mu + (truth - mu) @ a.T
        return float(_corr_units(torch.cov(polished.T) - cov, cov).abs().max())

    assert change(MOMENT_WINDOW) < 0.005
    assert change(1e3) > 0.05  # polished on the whole frame: the noise moves it
