"""openPMD-beamphysics particle files: layout, units and round trips."""

from __future__ import annotations

import math
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from diffaccel.data import FormatError, read_openpmd_particles, write_openpmd_particles
from diffaccel.data.synthetic import sample_preset_beam

C = 299_792_458.0
EV_PER_C = 1.602176634e-19 / C  # kg m/s per eV/c
MC2 = {"electron": 0.51099895069e6, "proton": 938.27208816e6}


@pytest.fixture
def beam() -> torch.Tensor:
    return sample_preset_beam("nonlinear", 1000, torch.Generator().manual_seed(0))


@pytest.mark.parametrize(
    ("species", "p0c"),
    [("electron", 43.36e6), ("positron", 5e6), ("proton", 1e9)],
    ids=["electron", "positron", "proton"],
)
def test_round_trip(tmp_path: Path, beam, species: str, p0c: float) -> None:
    path = write_openpmd_particles(tmp_path / "b.h5", beam, p0c=p0c, species=species)
    back, p0c_back, species_back = read_openpmd_particles(path)
    assert species_back == species and p0c_back == p0c
    # float64 through momenta in eV/c and times in s: round-off only
    torch.testing.assert_close(back, beam, rtol=1e-9, atol=1e-15)


def test_layout_and_units(tmp_path: Path, beam) -> None:
    p0c = 43.36e6
    path = write_openpmd_particles(tmp_path / "b.h5", beam, p0c=p0c, charge_C=2e-12)
    with h5py.File(path, "r") as h5:
        # text attributes: fixed-length strings, read back as bytes (openPMD)
        assert h5.attrs["openPMD"] == b"2.0.0"
        assert h5.attrs["openPMDextension"] == b"BeamPhysics;SpeciesType"
        assert h5.attrs["basePath"] == b"/data/%T/"
        for key in ("openPMD", "basePath", "particlesPath", "dataType"):
            assert not h5.attrs.get_id(key).get_type().is_variable_str()
        g = h5["data/0/particles"]
        assert g.attrs["speciesType"] == b"electron"
        assert g["position/x"].attrs["unitSymbol"] == b"m"
        assert g.attrs["numParticles"] == 1000
        assert g.attrs["totalCharge"] == pytest.approx(2e-12)
        assert g["weight"][()].sum() == pytest.approx(2e-12, rel=1e-12)
        assert g["momentum/x"].attrs["unitSI"] == pytest.approx(EV_PER_C, rel=1e-12)
        assert list(g["momentum/x"].attrs["unitDimension"]) == [1, 1, -1, 0, 0, 0, 0]
        assert list(g["weight"].attrs["unitDimension"]) == [0, 0, 1, 1, 0, 0, 0]
        px = g["momentum/x"][()]
        pz = g["momentum/z"][()]
        t = g["time"][()]
    b = beam.numpy()
    # physics of the conversion, independently: Px = px p0c, |P| = (1 + pz) p0c,
    # t = -z / (beta c) with beta = P / E
    np.testing.assert_allclose(px, b[:, 1] * p0c, rtol=1e-13)
    p = (1 + b[:, 5]) * p0c
    np.testing.assert_allclose(
        np.sqrt(px**2 + (b[:, 3] * p0c) ** 2 + pz**2), p, rtol=1e-13
    )
    beta = p / np.sqrt(p**2 + MC2["electron"] ** 2)
    np.testing.assert_allclose(t, -b[:, 4] / (beta * C), rtol=1e-12, atol=1e-25)


def test_reads_foreign_layout_with_constants_and_lost(tmp_path: Path) -> None:
    """A file as other codes write it: SI momenta, constant records, lost particles."""
    path = tmp_path / "foreign.h5"
    n, p0c = 4, 10e6
    pz_ev = np.array([1.0, 1.01, 0.99, 1.0]) * p0c
    with h5py.File(path, "w") as h5:
        h5.attrs["basePath"] = "/data/%T/"
        h5.attrs["particlesPath"] = "./"
        g = h5.create_group("data/000042/beam")
        g.attrs["speciesType"] = "electron"
        for comp, values in (("x", [1e-3, 0, 0, 0]), ("y", [0, 2e-3, 0, 0])):
            g[f"position/{comp}"] = np.array(values)
        zc = g.create_group("position/z")  # constant record component
        zc.attrs["value"] = 0.5
        zc.attrs["shape"] = (n,)
        for comp, values in (("x", [0.0, 0, 1e-3 * p0c, 0]), ("y", [0.0] * 4)):
            g[f"momentum/{comp}"] = np.array(values) * EV_PER_C  # SI
            g[f"momentum/{comp}"].attrs["unitSI"] = 1.0
        g["momentum/z"] = pz_ev * EV_PER_C
        g["momentum/z"].attrs["unitSI"] = 1.0
        g["time"] = np.zeros(n)
        g["weight"] = np.full(n, 1e-15)
        g["particleStatus"] = np.array([1, 1, 1, -1])
    particles, p0c_read, species = read_openpmd_particles(path)
    assert species == "electron" and particles.shape == (3, 6)
    # no p0c attribute: mean total momentum of the live particles
    p = np.sqrt(pz_ev[:3] ** 2 + np.array([0, 0, 1e-3 * p0c]) ** 2)
    assert p0c_read == pytest.approx(p.mean(), rel=1e-12)
    assert particles[0, 0].item() == pytest.approx(1e-3)
    assert particles[2, 1].item() == pytest.approx(1e-3 * p0c / p0c_read, rel=1e-12)
    assert particles[1, 5].item() == pytest.approx(1.01 * p0c / p0c_read - 1, rel=1e-9)


def test_snapshot_at_fixed_time_is_drifted_to_common_z(tmp_path: Path) -> None:
    """Particles at different z are drifted to the mean z (free space)."""
    path = tmp_path / "t.h5"
    p0c = 100e6
    with h5py.File(path, "w") as h5:
        h5.attrs["basePath"] = "/data/%T/"
        h5.attrs["particlesPath"] = "particles/"
        g = h5.create_group("data/1/particles")
        g.attrs["speciesType"] = "electron"
        g["position/x"] = np.array([0.0, 0.0])
        g["position/y"] = np.array([0.0, 0.0])
        g["position/z"] = np.array([-0.01, 0.01])  # 2 cm apart at t = 0
        g["momentum/x"] = np.array([1e-3 * p0c, 0.0])
        g["momentum/y"] = np.array([0.0, 0.0])
        g["momentum/z"] = np.array([p0c, p0c])
        g["time"] = np.zeros(2)
        g["weight"] = np.full(2, 1e-15)
        g.attrs["p0c"] = p0c
    particles, _, _ = read_openpmd_particles(path)
    # the rear particle drifts 1 cm forward: x grows by px/pz * 1 cm = 10 um
    assert particles[0, 0].item() == pytest.approx(1e-5, rel=1e-9)
    # the front particle is ahead: Bmad z > 0 (z = -beta c dt, dt < 0), ~1 cm
    assert particles[1, 4].item() == pytest.approx(0.01, rel=1e-4)
    assert particles[0, 4].item() == pytest.approx(-0.01, rel=1e-4)


def test_refuses_to_overwrite(tmp_path: Path, beam) -> None:
    path = tmp_path / "b.h5"
    path.write_bytes(b"mine")
    with pytest.raises(FileExistsError, match="overwrite=True"):
        write_openpmd_particles(path, beam, p0c=1e7)
    assert path.read_bytes() == b"mine"
    write_openpmd_particles(path, beam, p0c=1e7, overwrite=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.h5"]


BAD_WRITE = [
    ("shape", {"particles_bmad": torch.zeros(5, 4)}, r"expected shape \(N, 6\)"),
    ("nan", {"particles_bmad": torch.full((5, 6), math.nan)}, "NaN"),
    ("p0c", {"p0c": 0.0}, r"p0c: expected > 0"),
    ("charge", {"charge_C": -1e-12}, r"charge_C: expected > 0"),
    ("species", {"species": "muon"}, "Unknown species"),
    (
        "no_forward_motion",
        {"particles_bmad": torch.tensor([[0.0, 1.5, 0.0, 0.0, 0.0, 0.0]] * 3)},
        r"3 of 3 particles have \|\(px, py\)\| >= 1 \+ pz .*screen calibration",
    ),
]


@pytest.mark.parametrize(
    ("kwargs", "message"), [b[1:] for b in BAD_WRITE], ids=[b[0] for b in BAD_WRITE]
)
def test_write_errors(tmp_path: Path, beam, kwargs: dict, message: str) -> None:
    args = {"particles_bmad": beam, "p0c": 1e7, **kwargs}
    with pytest.raises(ValueError, match=message):
        write_openpmd_particles(tmp_path / "b.h5", **args)


def _break(path: Path, action: str) -> None:
    with h5py.File(path, "r+") as h5:
        g = h5["data/0/particles"]
        if action == "no_base_path":
            del h5.attrs["basePath"]
        elif action == "no_species":
            del g.attrs["speciesType"]
        elif action == "no_time":
            del g["time"]
        elif action == "nan":
            g["position/x"][0] = np.nan
        elif action == "backward":
            g["momentum/z"][0] = -1.0
        elif action == "unequal_weights":
            # dropped on reading before: the images ignored them
            g["weight"][0] = 3 * g["weight"][1]


BAD_READ = [
    ("no_base_path", "missing root attribute 'basePath'"),
    ("no_species", "missing attribute 'speciesType'"),
    ("no_time", "missing record 'time'"),
    ("nan", "record 'x' contains NaN"),
    ("backward", "momentum/z must be > 0"),
    ("unequal_weights", r"/weight: expected equal macro-particle charges"),
]


@pytest.mark.parametrize(("action", "message"), BAD_READ, ids=[b[0] for b in BAD_READ])
def test_read_errors(tmp_path: Path, beam, action: str, message: str) -> None:
    path = write_openpmd_particles(tmp_path / "b.h5", beam, p0c=1e7)
    _break(path, action)
    with pytest.raises(FormatError, match=message):
        read_openpmd_particles(path)


def test_reads_particles_at_file_root(tmp_path: Path) -> None:
    """openPMD-beamphysics' ParticleGroup.write puts the records at the root."""
    path = tmp_path / "root.h5"
    p0c = 20e6
    with h5py.File(path, "w") as h5:
        h5.attrs["basePath"] = "/"
        h5.attrs["particlesPath"] = "."
        h5.attrs["speciesType"] = "positron"
        for comp in "xyz":
            h5[f"position/{comp}"] = np.zeros(3)
        h5["momentum/x"] = np.array([0.0, 2e-3, 0.0]) * p0c
        h5["momentum/y"] = np.zeros(3)
        h5["momentum/z"] = np.full(3, p0c)
        h5["time"] = np.zeros(3)
        h5["weight"] = np.full(3, 1e-15)
    particles, _, species = read_openpmd_particles(path)
    assert species == "positron"
    # no p0c attribute: the reference is the mean total momentum
    p_ref = np.mean([p0c, np.hypot(p0c, 2e-3 * p0c), p0c])
    assert particles[1, 1].item() == pytest.approx(2e-3 * p0c / p_ref, rel=1e-12)
