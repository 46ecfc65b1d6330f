"""Issue 9's acceptance numbers on a beam of the shared file's family with
transverse curvature (slow).

The shared file's README describes its family (non-Gaussian, energy chirp with
curvature, x-z tilt, correlated in all six dimensions); this beam is our own
member of it (``chirp_negative`` of benchmarks/reconstruction_6d_beams.py,
built here): negative chirp with curvature, x-z tilt -0.6, and px following
x^2 (transverse curvature). Its px and pz then both follow x^2, so its px-pz
covariance is set by the shape, not traded: the Gaussian prior of the unseen
directions of before placed it wrong (2026-11-23, seed 0: pz +6.5 %, z
emittance +17.9 %, 6D +20.3 %, z-pz correlation +0.081, held-out L1 0.184).
With the prior given the quadratic transverse monomials, held during training
(1 thread, under load): pz +1.3 %, z emittance +2.1 %, 6D -5.5 %, z-pz +0.005,
held-out L1 0.066 / 0.082. Same geometry, split and limits as
test_acceptance_6d_other_beam_slow.
"""

from __future__ import annotations

import pytest
import torch
from test_acceptance_6d_other_beam_slow import TEST_K1, TRAIN_K1
from test_acceptance_6d_slow import LIMITS

from diffaccel.data import make_synthetic_awa6d
from diffaccel.reconstruction import (
    ReconstructionConfig,
    image_errors,
    moment_errors,
    reconstruct,
)

pytestmark = pytest.mark.slow


def curved_beam(n: int, seed: int) -> torch.Tensor:
    """Chirp -1.5/m, curvature -1500/m^2, tilt -0.6, px += 300/m x^2 (Bmad)."""
    g = torch.Generator().manual_seed(seed)
    u = torch.randn(n, 6, generator=g, dtype=torch.float64)
    x = 5e-4 * u[:, 0]
    px = 2.6e-4 * (0.3 * u[:, 0] + (1 - 0.3**2) ** 0.5 * u[:, 1])
    px = px + 300.0 * (x**2 - (x**2).mean())
    y = 5e-4 * u[:, 2]
    py = 2.6e-4 * (-0.3 * u[:, 2] + (1 - 0.3**2) ** 0.5 * u[:, 3])
    z = 8e-4 * u[:, 4] - 0.6 * x
    pz = -1.5 * z - 1500.0 * (z**2 - (z**2).mean()) + 0.6e-3 * u[:, 5]
    beam = torch.stack([x, px, y, py, z, pz], -1)
    return beam - beam.mean(0)


@pytest.fixture(scope="module")
def run():
    beam = curved_beam(200_000, seed=6)
    train = make_synthetic_awa6d(particles=beam, k1_values=TRAIN_K1, seed=6)
    test = make_synthetic_awa6d(particles=beam, k1_values=TEST_K1, seed=6)
    result = reconstruct(train, ReconstructionConfig(dims=6), uncertainty=False)
    errors = moment_errors(result.sample(200_000), beam)
    held = {
        name: image_errors(
            result.predict_images(scan.settings, scan=name), scan.mean_images()
        )["relative_l1"]
        for name, scan in test
    }
    return errors, held


@pytest.mark.parametrize("key", list(LIMITS))
def test_moments_match_the_truth(run, key: str) -> None:
    errors, _ = run
    assert abs(errors[key]) <= LIMITS[key], errors[key]


@pytest.mark.parametrize("key", [f"corr_diff_{p}" for p in ("x_z", "y_py", "z_pz")])
def test_correlations_within_0_05(run, key: str) -> None:
    errors, _ = run
    assert abs(errors[key]) <= 0.05, errors[key]


@pytest.mark.parametrize("scan", ["dipole_off", "dipole_on"])
def test_held_out_images_relative_l1_at_most_0_15(run, scan: str) -> None:
    _, held = run
    assert held[scan] <= 0.15, held[scan]
