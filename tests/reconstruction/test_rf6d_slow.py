"""6D reconstruction without a deflecting cavity: RF phase plus dipole (slow).

The rf6d layout (``make_synthetic_rf6d``): the AWA geometry with an S-band
accelerating cavity instead of the TDC, off or 4 MV at the zero crossing
(phase 0 and pi), then the spectrometer dipole at its nominal angle and at
0.8 of it (``dipole_scales=(0.8,)``). z is never imaged directly: the
cavity's chirp ``+-h z`` (h ~ 5.6 / m) mixes it into pz, which the dipole
maps to x on its screen. Beam: the ``correlated`` preset (z-pz correlation
-0.7). Default 6D settings; even quadrupole settings train, odd ones are held
out.

With the nominal bend alone the energy spread is not measured (the dipole
screen's R12 and R16 do not change over the scan, so pz-pz trades against
px-pz): rms pz +9.3 %, emittance z +6.7 % (seed 0). The second bend separates
them. Measured with it (seed 0; the data's and the run's seed): rms x, px, y,
py, z within 0.4 %, rms pz +0.6 %, emittance x -0.3 %, y +0.0 %, z +0.9 %, 6D
+0.6 %; correlations x-z 0.000, y-py +0.002, z-pz +0.002; held-out relative L1
0.052 / 0.077 / 0.073.
"""

from __future__ import annotations

import pytest
from test_acceptance_6d_slow import LIMITS  # the shared 6D benchmark's limits

from diffaccel.data import make_synthetic_rf6d
from diffaccel.reconstruction import (
    ReconstructionConfig,
    image_errors,
    moment_errors,
    reconstruct,
)

pytestmark = pytest.mark.slow

TRAIN_K1 = (-12.0, -6.0, 0.0, 6.0, 12.0)
TEST_K1 = (-9.0, -3.0, 3.0, 9.0)


@pytest.fixture(scope="module")
def run():
    kw = {"n_particles": 100_000, "dipole_scales": (0.8,)}
    train = make_synthetic_rf6d("correlated", k1_values=TRAIN_K1, **kw)
    test = make_synthetic_rf6d("correlated", k1_values=TEST_K1, **kw)
    result = reconstruct(train, ReconstructionConfig(dims=6), uncertainty=False)
    errors = moment_errors(result.sample(200_000), train.ground_truth)
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


@pytest.mark.parametrize("pair", ["x_z", "y_py", "z_pz"])
def test_correlations_within_0_05(run, pair: str) -> None:
    errors, _ = run
    assert abs(errors[f"corr_diff_{pair}"]) <= 0.05, errors[f"corr_diff_{pair}"]


@pytest.mark.parametrize("scan", ["dipole_off", "dipole_on", "dipole_on_0.8"])
def test_held_out_images_relative_l1_at_most_0_15(run, scan: str) -> None:
    _, held = run
    assert held[scan] <= 0.15, held[scan]
