"""Particle beams in openPMD-beamphysics HDF5 files.

Layout written (openPMD 2.0.0 with the ``BeamPhysics;SpeciesType`` extension, as
written by the openPMD-beamphysics package)::

    /                      attrs openPMD, openPMDextension, basePath="/data/%T/",
                                 particlesPath="particles/", dataType="openPMD"
    /data/0/particles/     attrs speciesType, numParticles, totalCharge, chargeLive,
                                 chargeUnitSI, p0c [eV] and tReference [s]
                                 (diffaccel extensions)
        position/{x,y,z}   [m]
        momentum/{x,y,z}   [eV/c]  (unitSI = e/c kg m/s)
        time               [s]
        weight             [C]     (macro-particle charge, positive)
        particleStatus     1 = alive

Text attributes are fixed-length ASCII strings, openPMD's type for text (what
openPMD-beamphysics, and cheetah's ``ParticleBeam.from_openpmd_file`` through
it, read). Records carry ``unitSI``, ``unitDimension`` and ``unitSymbol``; the reader
applies ``unitSI`` and accepts constant records (groups with ``value`` and
``shape`` attributes). Coordinates in memory are Bmad's, converted with
:mod:`diffaccel.dynamics.coordinates` (z = -beta c (t - t_ref),
pz = |P| / P0 - 1, particles at one longitudinal position).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import torch
from torch import Tensor

from diffaccel.data.atomic import atomic_write
from diffaccel.data.errors import FormatError
from diffaccel.data.quad_scan import check_p0c
from diffaccel.dynamics import Species
from diffaccel.dynamics.coordinates import bmad_to_openpmd, openpmd_to_bmad

__all__ = ["particle_group", "read_openpmd_particles", "write_openpmd_particles"]

_ELEMENTARY_CHARGE = 1.602176634e-19  # [C], exact (SI 2019)
_SPEED_OF_LIGHT = 299_792_458.0  # [m/s], exact
_EV_PER_C_SI = _ELEMENTARY_CHARGE / _SPEED_OF_LIGHT  # 1 eV/c in kg m/s

# (unitSI, unitDimension (L, M, T, I, theta, N, J), unitSymbol) per record
_UNITS = {
    "position": (1.0, (1, 0, 0, 0, 0, 0, 0), "m"),
    "momentum": (_EV_PER_C_SI, (1, 1, -1, 0, 0, 0, 0), "eV/c"),
    "time": (1.0, (0, 0, 1, 0, 0, 0, 0), "s"),
    "weight": (1.0, (0, 0, 1, 1, 0, 0, 0), "C"),
    "particleStatus": (1.0, (0, 0, 0, 0, 0, 0, 0), "1"),
}
#: Largest accepted transverse position |x|, |y| of a read particle [m]: beam
#: pipes are centimetres wide; metres are a unit error (mm stored as m).
MAX_TRANSVERSE = 1.0


def _drift_to_common_z(columns: dict[str, Tensor]) -> dict[str, Tensor]:
    """Drift particles in free space to their mean ``z`` (fixed-time snapshots).

    Straight lines: x += dz px/pz, y += dz py/pz, t += dz E / (pz c^2) with the
    momenta in eV/c and energies in eV.
    """
    z = columns["z"]
    if bool((z == z[:1]).all()):
        return columns
    out = dict(columns)
    dz = z.mean() - z
    out["x"] = columns["x"] + dz * columns["px"] / columns["pz"]
    out["y"] = columns["y"] + dz * columns["py"] / columns["pz"]
    out["t"] = columns["t"] + dz * columns["energy"] / (columns["pz"] * _SPEED_OF_LIGHT)
    out["z"] = torch.full_like(z, float(z.mean()))
    return out


def write_openpmd_particles(
    path: str | os.PathLike,
    particles_bmad: Tensor,
    p0c: float,
    species: str = "electron",
    charge_C: float = 1e-12,
    overwrite: bool = False,
) -> Path:
    """Write particles as an openPMD-beamphysics HDF5 file, atomically.

    Args:
        path: Destination file.
        particles_bmad: Bmad coordinates (x [m], px, y [m], py, z [m], pz).
        p0c: Reference momentum times c [eV]; stored as the ``p0c`` attribute.
        species: ``"electron"``, ``"positron"`` or ``"proton"``.
        charge_C: Total bunch charge [C] (> 0), shared equally by the particles.
        overwrite: Replace an existing file.

    Shapes:
        ``particles_bmad`` (N, 6).

    Returns:
        The path written.

    Raises:
        FileExistsError: if ``path`` exists and ``overwrite`` is false.
        ValueError: for a wrong shape (or fewer than 2 particles), NaN/inf
            coordinates, particles with no forward motion
            (``|(px, py)| >= 1 + pz``), ``p0c <= 0``,
            ``charge_C <= 0`` or an unknown species.
    """
    particles = torch.as_tensor(particles_bmad).detach()
    if particles.ndim != 2 or particles.shape[-1] != 6 or particles.shape[0] < 2:
        raise ValueError(
            "particles_bmad: expected shape (N, 6) with N >= 2 particles; got "
            f"{tuple(particles.shape)}"
        )
    if not bool(torch.isfinite(particles).all()):
        raise ValueError("particles_bmad: expected finite coordinates; found NaN/inf")
    if not p0c > 0:
        raise ValueError(f"p0c: expected > 0 [eV]; got {p0c}")
    if not charge_C > 0:
        raise ValueError(f"charge_C: expected > 0 [C]; got {charge_C}")
    spec = Species.from_name(species)
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(
            f"{path} exists; pass overwrite=True (CLI: --force) to replace it"
        )
    n = particles.shape[0]
    p = particles.double()
    stuck = p[:, 1].square() + p[:, 3].square() >= (1.0 + p[:, 5]).square()
    if bool(stuck.any()):
        raise ValueError(
            f"particles_bmad: {int(stuck.sum())} of {n} particles have "
            "|(px, py)| >= 1 + pz (no forward motion; largest |px|, |py| "
            f"{float(p[:, 1].abs().max()):.3g}, {float(p[:, 3].abs().max()):.3g}): "
            "not a beam. A reconstruction gives this when its images do not match "
            "the beamline: a wrong screen calibration (pixel_size_x/y in m: 1 mm "
            "is 1e-3), settings in the wrong units, a wrong beamline or p0c."
        )
    try:
        data = bmad_to_openpmd(p, p0c, spec, total_charge=charge_C)
    except ValueError as err:
        raise ValueError(f"particles_bmad: {err}") from err
    arrays = {k: np.asarray(v.detach().cpu().double().numpy()) for k, v in data.items()}
    path.parent.mkdir(parents=True, exist_ok=True)

    def _write(tmp: Path) -> None:
        with h5py.File(tmp, "w") as h5:
            h5.attrs["openPMD"] = _fixed("2.0.0")
            h5.attrs["openPMDextension"] = _fixed("BeamPhysics;SpeciesType")
            h5.attrs["basePath"] = _fixed("/data/%T/")
            h5.attrs["particlesPath"] = _fixed("particles/")
            h5.attrs["dataType"] = _fixed("openPMD")
            h5.attrs["iterationEncoding"] = _fixed("groupBased")
            h5.attrs["iterationFormat"] = _fixed("/data/%T/")
            g = h5.create_group("data/0/particles")
            g.attrs["speciesType"] = _fixed(spec.name)
            g.attrs["numParticles"] = np.int64(n)
            g.attrs["totalCharge"] = float(charge_C)
            g.attrs["chargeLive"] = float(charge_C)
            g.attrs["chargeUnitSI"] = 1.0
            g.attrs["p0c"] = float(p0c)
            g.attrs["tReference"] = 0.0
            for comp in "xyz":
                _write_record(g, f"position/{comp}", arrays[comp], "position")
                _write_record(g, f"momentum/{comp}", arrays[f"p{comp}"], "momentum")
            _write_record(g, "time", arrays["t"], "time")
            _write_record(g, "weight", arrays["weight"], "weight")
            _write_record(
                g, "particleStatus", np.ones(n, dtype=np.int32), "particleStatus"
            )

    return atomic_write(path, _write)


def _fixed(text: str) -> np.bytes_:
    """A text attribute as a fixed-length ASCII string (HDF5 ``H5T_STRING`` of
    fixed size, not variable-length UTF-8); h5py reads it back as bytes."""
    return np.bytes_(text.encode("ascii"))


def _write_record(group: h5py.Group, name: str, values: np.ndarray, kind: str) -> None:
    unit_si, dim, symbol = _UNITS[kind]
    dset = group.create_dataset(name, data=values)
    dset.attrs["unitSI"] = unit_si
    dset.attrs["unitDimension"] = np.asarray(dim, dtype=np.float64)
    dset.attrs["unitSymbol"] = _fixed(symbol)
    record = dset.parent if "/" in name else dset
    record.attrs["unitDimension"] = np.asarray(dim, dtype=np.float64)
    record.attrs["timeOffset"] = 0.0


def _as_str(value: object) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


def _particle_group(h5: h5py.File, where: Path) -> h5py.Group:
    """The first particle group: basePath (%T -> first iteration) + particlesPath."""
    if "basePath" not in h5.attrs:
        raise FormatError(f"{where}: missing root attribute 'basePath' (not openPMD?)")
    base = _as_str(h5.attrs["basePath"])
    if "%T" in base:
        head = base.split("%T")[0].rstrip("/") or "/"
        if head not in h5 or not len(h5[head]):
            raise FormatError(f"{where}: no iteration under {head!r}")
        base = base.replace("%T", sorted(h5[head])[0])
    particles_path = _as_str(h5.attrs.get("particlesPath", "./"))
    full = (base.rstrip("/") + "/" + particles_path.strip("./").strip("/")).rstrip("/")
    full = full or "/"
    if full not in h5:
        raise FormatError(f"{where}: missing particle group {full!r}")
    group = h5[full]
    if "position" in group:
        return group
    species = [
        k for k in group if isinstance(group[k], h5py.Group) and "position" in group[k]
    ]
    if not species:
        raise FormatError(
            f"{where}: no particle species with 'position' under {full!r}"
        )
    return group[species[0]]


def _number_attr(obj: h5py.HLObject, key: str, where: str) -> float:
    """A numeric (not text, not bool) scalar attribute as a float."""
    value = np.asarray(obj.attrs[key])
    if value.dtype.kind not in "iuf" or value.size != 1:
        raise FormatError(f"{where}.{key}: expected a number; found {obj.attrs[key]!r}")
    return float(value.item())


def _read_record(group: h5py.Group, name: str, n: int | None, where: str) -> np.ndarray:
    if name not in group:
        raise FormatError(f"{where}: missing record {name!r}")
    obj = group[name]
    here = f"{where}/{name}"
    if isinstance(obj, h5py.Group):  # constant record component
        if "value" not in obj.attrs:
            raise FormatError(f"{here}: constant record without 'value'")
        shape = tuple(obj.attrs.get("shape", (n,)))
        values = np.full(shape, _number_attr(obj, "value", here))
    else:
        if obj.dtype.kind not in "iuf":
            raise FormatError(f"{here}: expected real numbers; found dtype {obj.dtype}")
        values = np.asarray(obj[()], dtype=np.float64)
    unit_si = _number_attr(obj, "unitSI", here) if "unitSI" in obj.attrs else 1.0
    if not (np.isfinite(unit_si) and unit_si > 0):
        raise FormatError(
            f"{here}.unitSI: expected a finite number > 0; found {unit_si}"
        )
    kind = name.partition("/")[0]
    if "unitDimension" in obj.attrs and kind in _UNITS:
        dim = np.asarray(obj.attrs["unitDimension"])
        want = np.asarray(_UNITS[kind][1], dtype=np.float64)
        if (
            dim.dtype.kind not in "iuf"
            or dim.shape != want.shape
            or (not np.allclose(dim, want))
        ):
            raise FormatError(
                f"{here}.unitDimension: expected {want.tolist()} (powers of L, M, "
                f"T, I, theta, N, J for {kind} [{_UNITS[kind][2]}]); found "
                f"{obj.attrs['unitDimension']!r}"
            )
    return values * unit_si


#: Largest relative spread of the live particles' weights read as equal (the
#: round-off of a total charge shared out in float64).
WEIGHT_RELATIVE_TOLERANCE = 1e-6


def read_openpmd_particles(path: str | os.PathLike) -> tuple[Tensor, float, str]:
    """Read particles from an openPMD-beamphysics HDF5 file.

    Particles with ``particleStatus != 1`` (lost) are dropped. The live
    particles must carry equal weights (every particle counts once in the
    images and moments made from them). The reference
    momentum is the file's ``p0c`` attribute when present, else the mean total
    momentum of the live particles.

    Args:
        path: File to read.

    Returns:
        ``(particles_bmad, p0c, species)``: (N, 6) float64 Bmad coordinates,
        reference momentum times c [eV], species name.

    Raises:
        FileNotFoundError: if ``path`` does not exist.
        FormatError: naming the missing or invalid attribute/record, or
            unequal weights.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"particle file not found: {path}")
    try:
        h5 = h5py.File(path, "r")
    except OSError as err:
        raise FormatError(f"{path}: not a readable HDF5 file ({err})") from err
    with h5:
        g = _particle_group(h5, path)
        where = f"{path}:{g.name}"
        if "speciesType" not in g.attrs:
            raise FormatError(f"{where}: missing attribute 'speciesType'")
        species = _as_str(g.attrs["speciesType"])
        try:
            spec = Species.from_name(species)
        except ValueError as err:
            raise FormatError(f"{where}.speciesType: {err}") from err
        x = _read_record(g, "position/x", None, where)
        n = x.shape[0]
        si = {
            "x": x,
            "y": _read_record(g, "position/y", n, where),
            "z": _read_record(g, "position/z", n, where),
            "px": _read_record(g, "momentum/x", n, where) / _EV_PER_C_SI,
            "py": _read_record(g, "momentum/y", n, where) / _EV_PER_C_SI,
            "pz": _read_record(g, "momentum/z", n, where) / _EV_PER_C_SI,
            "t": _read_record(g, "time", n, where),
            "weight": _read_record(g, "weight", n, where),
        }
        alive = np.ones(n, dtype=bool)
        if "particleStatus" in g:
            alive = _read_record(g, "particleStatus", n, where) == 1
        p0c_attr = _number_attr(g, "p0c", where) if "p0c" in g.attrs else None
        t_ref = (
            _number_attr(g, "tReference", where) if "tReference" in g.attrs else None
        )
    for key, values in si.items():
        if values.shape != (n,):
            raise FormatError(
                f"{where}: record {key!r} has shape {values.shape}; expected ({n},)"
            )
        if not np.isfinite(values).all():
            raise FormatError(f"{where}: record {key!r} contains NaN/inf")
    if not (si["pz"][alive] > 0).all():
        raise FormatError(f"{where}: momentum/z must be > 0 (a forward-moving beam)")
    if not alive.any():
        raise FormatError(f"{where}: no live particles (particleStatus == 1)")
    if alive.sum() < 2:
        raise FormatError(
            f"{where}: expected at least 2 live particles (a beam); found "
            f"{int(alive.sum())}"
        )
    if not (si["weight"][alive] > 0).all():
        bad = int((si["weight"][alive] <= 0).sum())
        raise FormatError(
            f"{where}/weight: expected macro-particle charges > 0 [C]; found {bad} "
            f"<= 0 (min {si['weight'][alive].min():g})"
        )
    w = si["weight"][alive]
    if not w.max() <= w.min() * (1.0 + WEIGHT_RELATIVE_TOLERANCE):
        raise FormatError(
            f"{where}/weight: expected equal macro-particle charges (diffaccel "
            f"counts every particle once); found {w.min():g} .. {w.max():g} C. "
            "Resample the beam to equal weights (draw particles with probability "
            "proportional to their weight) before using it here"
        )
    data = {k: torch.from_numpy(v[alive]) for k, v in si.items()}
    p = torch.sqrt(data["px"] ** 2 + data["py"] ** 2 + data["pz"] ** 2)
    data["energy"] = torch.sqrt(p**2 + spec.mass_ev**2)
    data = _drift_to_common_z(data)
    if p0c_attr is None:
        p0c_attr = float(p.mean())
    if p0c_attr > 0:  # otherwise refused below, by the conversion
        check_p0c(p0c_attr, spec.name, f"{where}.p0c")
    try:
        particles, _ = openpmd_to_bmad(data, p0c_attr, spec, t_ref=t_ref)
    except ValueError as err:
        raise FormatError(f"{where}: {err}") from err
    far = particles[:, [0, 2]].abs().amax()
    if not bool(far <= MAX_TRANSVERSE):
        raise FormatError(
            f"{where}/position: expected |x|, |y| <= {MAX_TRANSVERSE:g} m (after "
            f"drifting to the mean z); found {float(far):g} m (a unit error?)"
        )
    return particles, p0c_attr, spec.name


def particle_group(
    particles_bmad: Tensor,
    p0c: float,
    species: str = "electron",
    charge_C: float = 1e-12,
) -> Any:
    """The particles as an openPMD-beamphysics ``ParticleGroup``.

    The particles are written with :func:`write_openpmd_particles` to a
    temporary file and read back by ``beamphysics.ParticleGroup``: the object is
    what openPMD-beamphysics makes of a ``particles.h5`` of these particles.

    Args:
        particles_bmad: Bmad coordinates (x [m], px, y [m], py, z [m], pz).
        p0c: Reference momentum times c [eV].
        species: ``"electron"``, ``"positron"`` or ``"proton"``.
        charge_C: Total bunch charge [C] (> 0), shared equally by the particles.

    Shapes:
        ``particles_bmad`` (N, 6).

    Returns:
        A ``beamphysics.ParticleGroup`` (SI units: m, eV/c, s, C).

    Raises:
        ImportError: if openPMD-beamphysics is not installed
            (``pip install diffaccel[pmd]``).
        ValueError: as :func:`write_openpmd_particles`.
    """
    try:
        from beamphysics import ParticleGroup
    except ImportError as err:
        raise ImportError(
            "particle_group needs openPMD-beamphysics: pip install diffaccel[pmd]"
        ) from err
    with tempfile.TemporaryDirectory(prefix="diffaccel-pmd-") as tmp:
        path = write_openpmd_particles(
            Path(tmp) / "particles.h5", particles_bmad, p0c, species, charge_C
        )
        return ParticleGroup(str(path))
