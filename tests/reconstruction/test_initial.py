from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch

from diffaccel.data import make_synthetic_awa6d, read_scans
from diffaccel.dynamics import Beamline
from diffaccel.reconstruction import (
    ReconstructionConfig,
    ScreenForwardModel,
    fit_gaussian,
)
from diffaccel.reconstruction.unseen import unseen_directions

DATA = Path(__file__).resolve().parents[2] / "data" / "phase_space"
SHARED_6D = DATA / "sixd_synthetic_train.h5"

SPEC = [
    {"type": "Quadrupole", "name": "Q1", "length": 0.1, "k1": 0.0},
    {"type": "Drift", "name": "D1", "length": 1.0},
    {"type": "Screen", "name": "S", "shape": [64, 64], "pixel_size": [0.5e-3, 0.5e-3]},
]


def test_gaussian_fit_recovers_the_beam_covariance() -> None:
    g = torch.Generator().manual_seed(0)
    cov = torch.tensor(
        [
            [2.0e-6, -0.5e-6, 0.3e-6, 0.0],
            [-0.5e-6, 0.4e-6, 0.0, 0.05e-6],
            [0.3e-6, 0.0, 1.5e-6, 0.4e-6],
            [0.0, 0.05e-6, 0.4e-6, 0.3e-6],
        ],
        dtype=torch.float64,
    )
    chol = torch.linalg.cholesky(cov)
    x4 = torch.randn(10_000, 4, generator=g, dtype=torch.float64) @ chol.T
    x = torch.cat([x4, torch.zeros(10_000, 2, dtype=torch.float64)], 1).float()
    fwd = ScreenForwardModel(Beamline.from_spec(SPEC), ["Q1.k1"], 43e6)
    k1 = torch.linspace(-12, 12, 9, dtype=torch.float64)[:, None]
    img = fwd.images(x, k1)
    img = img / img.sum((-2, -1), keepdim=True)
    guess = fit_gaussian(fwd, img, k1)
    fitted = guess.cov[:4, :4]
    sample = torch.cov(x4.T)
    # moments of 10k particles seen through 0.5 mm pixels: a few % agreement
    rel = (fitted.diagonal() - sample.diagonal()).abs() / sample.diagonal()
    assert rel.max() < 0.05
    corr_f = fitted / fitted.diagonal().sqrt().outer(fitted.diagonal().sqrt())
    corr_s = sample / sample.diagonal().sqrt().outer(sample.diagonal().sqrt())
    # in-plane correlations are determined by a single-quad scan; the four x-y
    # cross terms are not (<x y> at the screen is quadratic in k1: 3 numbers for
    # 4 unknowns), so the fit may drop them to stay positive definite
    assert abs(corr_f[0, 1] - corr_s[0, 1]) < 0.05
    assert abs(corr_f[2, 3] - corr_s[2, 3]) < 0.05
    assert torch.linalg.eigvalsh(fitted).min() > 0


def test_gaussian_fit_is_the_same_on_every_call(awa6d_two_settings) -> None:
    # two settings of a 6D layout leave the least squares rank deficient; the
    # guess (and a seeded reconstruction with it) must not change call to call
    forwards, images, settings = awa6d_two_settings
    first = fit_gaussian(forwards, images, settings).cov
    for _ in range(6):
        assert torch.equal(fit_gaussian(forwards, images, settings).cov, first)


def _tilted_chirped_beam(n: int, seed: int) -> torch.Tensor:
    """A Gaussian transverse beam whose z is tilted along x and px and whose pz
    is a curved chirp of z (as the shared 6D file's truth), Bmad ``(n, 6)``."""
    g = torch.Generator().manual_seed(seed)
    u = torch.randn(n, 6, generator=g, dtype=torch.float64)
    x = 0.44e-3 * u[:, 0]
    px = 0.22e-3 * (-0.76 * u[:, 0] + 0.65 * u[:, 1])
    y = 0.63e-3 * u[:, 2]
    py = 0.29e-3 * (-0.29 * u[:, 2] + 0.96 * u[:, 3])
    d = 0.94 * u[:, 0] - 0.34 * u[:, 1]
    z = 0.89e-3 * (0.33 * d + 0.94 * u[:, 4])
    pz = -1.9 * z + 1300.0 * (z**2 - (z**2).mean()) + 1.5e-3 * u[:, 5]
    b = torch.stack([x, px, y, py, z, pz], -1)
    return b - b.mean(0)


def _screen_moments(maps: torch.Tensor, cov: torch.Tensor) -> torch.Tensor:
    """<xx>, <yy>, <xy> [m^2] at the screen of a beam of covariance ``cov``."""
    r = maps[:, :6, :6]
    s = r @ cov @ r.transpose(1, 2)
    return torch.stack([s[:, 0, 0], s[:, 2, 2], s[:, 0, 2]], -1)


def _inputs(dataset):
    """Forward models (the 6D default blur), images, settings and maps."""
    config = ReconstructionConfig(dims=6)
    forwards, images, settings, maps = [], [], [], []
    for _, scan in dataset:
        fwd = ScreenForwardModel.from_dataset(scan, blur_pixels=config.blur_for(scan))
        forwards.append(fwd)
        images.append(scan.mean_images())
        settings.append(scan.settings)
        maps.append(fwd.transfer_maps(scan.settings))
    return forwards, images, settings, maps


def test_6d_guess_is_widest_where_the_moments_leave_it_free() -> None:
    """Behind a deflecting cavity and a dipole the image moments leave the pz
    variance against the px-pz covariance free. The guess lies at the largest
    determinant (maximum entropy) along that direction (the least squares'
    minimum-norm point, projected, had d log det / dt = 9.1 against a scale
    of 19 on this beam), is positive definite, and still fits the moments."""
    truth = _tilted_chirped_beam(100_000, 12)
    ds = make_synthetic_awa6d(
        particles=truth, k1_values=(-12.0, -6.0, 0.0, 6.0, 12.0), seed=12
    )
    forwards, images, settings, maps = _inputs(ds)
    guess = fit_gaussian(forwards, images, settings, maps=maps)
    assert torch.linalg.eigvalsh(guess.cov).min() > 0
    true_cov = torch.cov(truth.T)
    wants = [_screen_moments(m, true_cov) for m in maps]
    unit = torch.cat([w[:, :2] for w in wants]).mean()  # mean screen variance
    for m, want in zip(maps, wants, strict=True):
        # as the truth's own linear moments, within 10 % of the mean variance
        # (the fit weighs every moment in that unit; measured 0.078)
        got = _screen_moments(m, guess.cov)
        assert ((got - want) / unit).abs().max() < 0.1
    # the direction the moments leave free (singular value ~1e-4 of the
    # largest; the py-z one, ~8e-3, is weakly seen and not at the maximum)
    directions = unseen_directions(maps, guess.cov, tolerance=1e-3)
    assert directions.shape[0] == 1
    prec = torch.linalg.inv(guess.cov)
    v = directions[0]
    # d log det / dt = tr(P V): zero at the largest determinant (measured
    # 8e-4), relative to |P| |V| summed (2.4)
    scale = (prec.abs() @ v.abs()).diagonal().sum()
    assert abs(float(torch.einsum("ij,ji->", prec, v))) < 0.01 * float(scale)


def test_6d_guess_of_the_shared_file_is_near_its_truth() -> None:
    """The shared 6D training file: the least squares' minimum-norm point,
    projected onto positive definite matrices, started training at rms pz
    -60 % with a correlation off by 0.86; the maximum-entropy fit starts it
    within 8.7 % in every rms size and 0.091 in every correlation (the
    covariance the moments allow is wider than the truth's: the largest
    determinant)."""
    ds = read_scans(SHARED_6D)
    forwards, images, settings, maps = _inputs(ds)
    guess = fit_gaussian(forwards, images, settings, maps=maps)
    true_cov = torch.cov(ds.ground_truth.to(torch.float64).T)
    sig, true_sig = guess.cov.diagonal().sqrt(), true_cov.diagonal().sqrt()
    assert ((sig / true_sig - 1).abs() < 0.1).all(), sig / true_sig - 1
    corr = guess.cov / sig.outer(sig) - true_cov / true_sig.outer(true_sig)
    assert corr.abs().max() < 0.12, corr


@pytest.mark.parametrize(
    ("pixel", "message"),
    [
        (1.0, r"rms px 0\.\d+ rad"),  # 1 mm typed as 1 (m): 1000 x the size
        (0.1, r"rms x 0\.\d+ m"),
    ],
    ids=["pixel_1m", "pixel_10cm"],
)
def test_reconstruct_refuses_a_guess_no_scan_could_image(
    small_scan, pixel: float, message: str
) -> None:
    from diffaccel.reconstruction import reconstruct

    # pixel sizes in the wrong units would train fully, then fail to write
    # particles with |px| >= 1 + pz: refused before training, naming the
    # screen calibration
    bad = dataclasses.replace(small_scan, pixel_size=(pixel, pixel))
    cfg = ReconstructionConfig(n_particles=64, steps=2, snapshots=1)
    with pytest.raises(ValueError, match=message) as info:
        reconstruct(bad, cfg)
    assert "unphysical beam" in str(info.value)
    assert "screen calibration" in str(info.value)
    assert "'scan'" in str(info.value)


def test_the_shared_files_guesses_are_plausible() -> None:
    from diffaccel.reconstruction.initial import check_guess

    for name in ("gpsr_4d_synthetic.h5", "awa_quad_scan_train.h5"):
        ms = read_scans(DATA / name)
        fwd = [ScreenForwardModel.from_dataset(s) for _, s in ms]
        guess = fit_gaussian(
            fwd, [s.mean_images() for _, s in ms], [s.settings for _, s in ms]
        )
        check_guess(guess, ms.names)  # does not raise


def test_an_unphysical_guess_without_a_focusing_scan_says_so_first() -> None:
    from diffaccel.reconstruction.initial import GaussianGuess, check_guess

    cov = torch.diag(torch.tensor([1e-6, 1.0, 1e-6, 1e-8, 1e-6, 1e-6]).double())
    guess = GaussianGuess(torch.zeros(6, dtype=torch.float64), cov)
    with pytest.raises(ValueError, match="rms px") as info:
        check_guess(guess, ["tdc_only"], focusing_scanned=False)
    text = str(info.value)
    assert text.index("no scan varies a focusing strength") < text.index(
        "screen calibration"
    )
    with pytest.raises(ValueError) as plain:
        check_guess(guess, ["scan"])
    assert "focusing strength" not in str(plain.value)
