"""The 6D acceptance numbers on beams other than the shared file's (slow).

"Do not tune to this one file": the same AWA 6D geometry (quadrupole x TDC x
dipole, two screens, 96 x 96 histogram images as in the shared files, even
quadrupole settings for training, odd ones held out), but beams of other
shapes, generated here. Default 6D settings, as a user would run them; the
limits are the shared benchmark's.

The first beam is the three-mode ``nonlinear`` preset with a strong y-py
correlation (0.93) and half the energy spread. The longitudinal plane relies on
the prior term of the objective (``ReconstructionConfig.unseen_weight``): the
AWA 6D scans do not see the pz variance apart from the px-pz covariance (nor
the z variance apart from py-z), and training without it drifts there (rms pz
+29 %, z emittance +39 %, 6D emittance -23 %).

The second beam, ``wide``, fills the screens differently: a beam of the shared
file's README family (energy chirp with curvature, x-z tilt) with 2x its rms x,
1.6x its rms y, 0.37x its energy spread, converging in y (``wide`` of
``benchmarks/reconstruction_6d_beams.py``, built here again so the test does
not import the benchmarks).

The third beam, ``double_horn`` (a compressed bunch: arcsine current profile,
chirp z-pz -0.91 with curvature, built here again), checks the prior point of
the unseen directions on a strong chirp: a criterion over the direction's whole
off-diagonal part (z-pz chirp included) would place its truth at z emittance
+11.9 %; the traded pair's partial correlation leaves its truth where it is.

Measured at the defaults (seed 0, one thread, the same beams in
``benchmarks/reconstruction_6d_beams.py``): three-mode rms within 2.8 %,
z emittance +2.7 %, 6D -7.9 %, held-out relative L1 0.083 / 0.076; ``wide``
rms within 1.7 %, z emittance +1.9 %, 6D +0.2 %, L1 0.073 / 0.082;
``double_horn`` rms within 0.6 %, z emittance +4.0 %, 6D 0.0 %, L1 0.054 /
0.066.
"""

from __future__ import annotations

import math

import pytest
import torch
from test_acceptance_6d_slow import LIMITS  # the shared 6D benchmark's limits

from diffaccel.data import make_synthetic_awa6d
from diffaccel.data.synthetic import AWA6D_BEAM_SCALE, sample_preset_beam
from diffaccel.reconstruction import (
    ReconstructionConfig,
    image_errors,
    moment_errors,
    reconstruct,
)

pytestmark = pytest.mark.slow

#: the shared 6D benchmark's split: k1 = -12, -6, 0, 6, 12 train; -9, -3, 3, 9 test
TRAIN_K1 = (-12.0, -6.0, 0.0, 6.0, 12.0)
TEST_K1 = (-9.0, -3.0, 3.0, 9.0)


def other_beam(n: int, seed: int) -> torch.Tensor:
    """Three-mode beam in the AWA 6D scale: y-py correlation 0.93, 0.17 % spread."""
    g = torch.Generator().manual_seed(seed)
    beam = sample_preset_beam("nonlinear", n, g)
    # the AWA 6D layout's scale of the presets, half the energy spread
    half_spread = torch.tensor([1, 1, 1, 1, 1, 0.5], dtype=beam.dtype)
    beam = beam * torch.tensor(AWA6D_BEAM_SCALE, dtype=beam.dtype) * half_spread
    beam[:, 3] += 0.5 * beam[:, 2]  # y-py correlation 0.69 -> 0.93
    return beam - beam.mean(0)


def wide_beam(n: int, seed: int) -> torch.Tensor:
    """Chirped, tilted family beam: rms x 1.0 mm, y 0.75 mm, pz 0.14 %, Bmad (n, 6)."""
    g = torch.Generator().manual_seed(seed)
    u = torch.randn(n, 6, generator=g, dtype=torch.float64)
    x = 1.0e-3 * u[:, 0]
    px = 3.5e-4 * (-0.85 * u[:, 0] + (1 - 0.85**2) ** 0.5 * u[:, 1])
    y = 0.75e-3 * u[:, 2]
    py = 2.6e-4 * (-0.6 * u[:, 2] + 0.8 * u[:, 3])  # converging in y
    z = 0.7e-3 * u[:, 4] + 0.3 * x  # x-z tilt
    # energy chirp with curvature [1/m, 1/m^2] and an uncorrelated spread
    pz = 1.5 * z + 600.0 * (z**2 - (z**2).mean()) + 0.6e-3 * u[:, 5]
    beam = torch.stack([x, px, y, py, z, pz], -1)
    return beam - beam.mean(0)


def double_horn_beam(n: int, seed: int) -> torch.Tensor:
    """Compressed bunch: double-horn current profile, chirp -0.91, Bmad (n, 6)."""
    g = torch.Generator().manual_seed(seed)
    u = torch.randn(n, 6, generator=g, dtype=torch.float64)
    theta = (torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * math.pi
    x = 5e-4 * u[:, 0]
    px = 2.6e-4 * (-0.7 * u[:, 0] + 0.51**0.5 * u[:, 1])
    y = 4.6e-4 * u[:, 2]
    py = 2.6e-4 * (0.8 * u[:, 2] + 0.6 * u[:, 3])
    # arcsine profile of a folded chirp (spikes at head and tail), x-z tilt
    z = 1.3e-3 * torch.sin(theta) + 0.08 * 1.3e-3 * u[:, 4] + 0.2 * x
    pz = -2.5 * z + 1200.0 * (z**2 - (z**2).mean()) + 0.7e-3 * u[:, 5]
    beam = torch.stack([x, px, y, py, z, pz], -1)
    return beam - beam.mean(0)


#: beam -> (its construction, the seed of its particles and image noise)
BEAMS = {
    "nonlinear_ypy": (other_beam, 3),
    "wide": (wide_beam, 14),
    "double_horn": (double_horn_beam, 13),
}


@pytest.fixture(scope="module", params=list(BEAMS))
def run(request):
    make, seed = BEAMS[request.param]
    beam = make(200_000, seed=seed)
    train = make_synthetic_awa6d(particles=beam, k1_values=TRAIN_K1, seed=seed)
    test = make_synthetic_awa6d(particles=beam, k1_values=TEST_K1, seed=seed)
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
