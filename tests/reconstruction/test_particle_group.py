"""A reconstruction as an openPMD-beamphysics ParticleGroup (the ``[pmd]`` extra)."""

from __future__ import annotations

import numpy as np
import pytest

from diffaccel.reconstruction import (
    ReconstructionConfig,
    reconstruct,
    to_particle_group,
)

beamphysics = pytest.importorskip("beamphysics", reason="needs diffaccel[pmd]")


def test_to_particle_group_holds_the_sampled_beam(small_scan) -> None:
    config = ReconstructionConfig(n_particles=1024, steps=4, snapshots=2)
    result = reconstruct(small_scan, config, train_indices=[0, 2, 4])
    pg = to_particle_group(result, 3000, charge_C=4e-12, seed=1)
    x = result.sample(3000, seed=1).double().numpy()
    assert isinstance(pg, beamphysics.ParticleGroup)
    assert pg.n_particle == 3000 and pg.species == small_scan.species
    assert pg.charge == pytest.approx(4e-12, rel=1e-12)
    np.testing.assert_allclose(pg.x, x[:, 0], rtol=1e-12)
    np.testing.assert_allclose(pg.px, x[:, 1] * small_scan.p0c, rtol=1e-12)
    np.testing.assert_allclose(pg.p, (1 + x[:, 5]) * small_scan.p0c, rtol=1e-12)
    assert pg["sigma_y"] == pytest.approx(x[:, 2].std(), rel=1e-9)
