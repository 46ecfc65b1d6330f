"""Our particles.h5 read by openPMD-beamphysics and by cheetah (the ``[pmd]`` extra)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from diffaccel.data import particle_group, write_openpmd_particles
from diffaccel.data.synthetic import sample_preset_beam

beamphysics = pytest.importorskip("beamphysics", reason="needs diffaccel[pmd]")

C = 299_792_458.0
MC2 = {"electron": 0.51099895069e6, "proton": 938.27208816e6}
P0C = 43.36e6


@pytest.fixture
def beam() -> torch.Tensor:
    return sample_preset_beam("nonlinear", 5000, torch.Generator().manual_seed(0))


def _expected(beam: torch.Tensor, p0c: float, mc2: float) -> dict[str, np.ndarray]:
    """openPMD columns of Bmad particles, from the definitions: Px = px p0c,
    |P| = (1 + pz) p0c, t = -z / (beta c) at s = 0."""
    b = beam.double().numpy()
    p = (1.0 + b[:, 5]) * p0c
    energy = np.hypot(p, mc2)
    return {
        "x": b[:, 0],
        "px": b[:, 1] * p0c,
        "y": b[:, 2],
        "py": b[:, 3] * p0c,
        "p": p,
        "energy": energy,
        "t": -b[:, 4] / (p / energy * C),
    }


def _norm_emit(u: np.ndarray, pu_ev: np.ndarray, mc2: float) -> float:
    """sqrt(det cov(u, P_u / mc)) [m], with the N - 1 normalisation of the
    weighted covariance that openPMD-beamphysics uses."""
    cov = np.cov(u, pu_ev / mc2)
    return float(np.sqrt(np.linalg.det(cov)))


@pytest.mark.parametrize(
    ("species", "p0c"), [("electron", P0C), ("proton", 1e9)], ids=["e", "p"]
)
def test_particle_group_reads_our_file(tmp_path: Path, beam, species, p0c) -> None:
    path = write_openpmd_particles(
        tmp_path / "particles.h5", beam, p0c=p0c, species=species, charge_C=2.5e-12
    )
    pg = beamphysics.ParticleGroup(str(path))
    want = _expected(beam, p0c, MC2[species])
    # its energies use its own mass (CODATA 2018 and 2022 differ by 1e-9)
    assert pg.mass == pytest.approx(MC2[species], rel=1e-8)
    want["energy"] = np.hypot(want["p"], pg.mass)
    assert pg.species == species
    assert pg.n_particle == beam.shape[0]
    assert pg.charge == pytest.approx(2.5e-12, rel=1e-12)
    for key in ("x", "px", "y", "py", "p", "energy", "t"):
        np.testing.assert_allclose(pg[key], want[key], rtol=1e-12, atol=1e-30)
    assert np.all(pg.status == 1) and np.all(pg.z == 0.0)
    # moments as openPMD-beamphysics computes them
    for key in ("x", "y", "px", "py", "t", "energy"):
        scale = want[key].std()
        assert pg[f"mean_{key}"] == pytest.approx(want[key].mean(), abs=1e-10 * scale)
        assert pg[f"sigma_{key}"] == pytest.approx(want[key].std(), rel=1e-10)
    for u in ("x", "y"):
        expected = _norm_emit(want[u], want[f"p{u}"], pg.mass)
        assert pg[f"norm_emit_{u}"] == pytest.approx(expected, rel=1e-9)


def test_particle_group_helper_matches_the_file(tmp_path: Path, beam) -> None:
    pg = particle_group(beam, P0C, "electron", charge_C=3e-12)
    path = write_openpmd_particles(tmp_path / "b.h5", beam, p0c=P0C, charge_C=3e-12)
    from_file = beamphysics.ParticleGroup(str(path))
    assert pg.species == "electron" and pg.charge == pytest.approx(3e-12, rel=1e-12)
    for key in ("x", "px", "y", "py", "z", "pz", "t", "weight"):
        np.testing.assert_array_equal(pg[key], from_file[key])
    assert pg["norm_emit_x"] == pytest.approx(
        _norm_emit(beam[:, 0].numpy(), beam[:, 1].numpy() * P0C, MC2["electron"]),
        rel=1e-9,
    )


def test_particle_group_helper_errors(beam) -> None:
    with pytest.raises(ValueError, match="charge_C: expected > 0"):
        particle_group(beam, P0C, charge_C=0.0)


def test_cheetah_reads_our_file(tmp_path: Path, beam) -> None:
    cheetah = pytest.importorskip("cheetah", reason="needs cheetah-accelerator")
    path = write_openpmd_particles(
        tmp_path / "particles.h5", beam, p0c=P0C, charge_C=2e-12
    )
    mc2 = MC2["electron"]
    energy = float(np.hypot(P0C, mc2))
    cb = cheetah.ParticleBeam.from_openpmd_file(
        str(path), energy=torch.tensor(energy, dtype=torch.float64), dtype=torch.float64
    )
    want = _expected(beam, P0C, mc2)
    p0c_cheetah = float(np.sqrt(energy**2 - mc2**2))
    assert p0c_cheetah == pytest.approx(P0C, rel=1e-12)
    assert cb.species.name == "electron"
    assert float(cb.total_charge) == pytest.approx(2e-12, rel=1e-12)
    got = cb.particles.numpy()
    np.testing.assert_allclose(got[:, 0], want["x"], rtol=1e-12, atol=1e-18)
    np.testing.assert_allclose(got[:, 1], beam[:, 1].numpy(), rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(got[:, 2], want["y"], rtol=1e-12, atol=1e-18)
    np.testing.assert_allclose(got[:, 3], beam[:, 3].numpy(), rtol=1e-9, atol=1e-15)
    # cheetah's reader: tau = c t, delta = (E - E0) / p0c
    np.testing.assert_allclose(got[:, 4], want["t"] * C, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(
        got[:, 5], (want["energy"] - energy) / P0C, rtol=1e-9, atol=1e-13
    )
    # cheetah's beam moments (its std has the N - 1 normalisation)
    for name, col in (("sigma_x", want["x"]), ("sigma_y", want["y"])):
        assert float(getattr(cb, name)) == pytest.approx(col.std(ddof=1), rel=1e-9)
