"""Synthetic quad-scan files: a known beam through a layout, written to HDF5.

:func:`write_synthetic` simulates the scans a :class:`SyntheticRequest`
asks for (:func:`~diffaccel.data.make_synthetic_quad_scan`,
:func:`~diffaccel.data.make_synthetic_awa6d`,
:func:`~diffaccel.data.make_synthetic_rf6d`), writes them with their ground
truth and returns a one-line account of the file; :func:`check_synthetic`
refuses a request and output file before any simulation.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from diffaccel.data.errors import FormatError, OptionError
from diffaccel.data.owned_files import check_out_file
from diffaccel.data.particles_io import read_openpmd_particles
from diffaccel.data.quad_scan import check_p0c, write_quad_scan
from diffaccel.data.scans import write_scans
from diffaccel.data.synthetic import (
    make_synthetic_awa6d,
    make_synthetic_quad_scan,
    make_synthetic_rf6d,
)

__all__ = ["SyntheticRequest", "check_synthetic", "write_synthetic"]


@dataclass(frozen=True)
class SyntheticRequest:
    """What to simulate (None: the layout's default).

    Attributes:
        layout: ``quad`` (one scan, format version 1), ``awa6d`` or ``rf6d``
            (two scans of a 6D layout, format version 2).
        preset: Ground-truth beam preset (:data:`PRESETS`).
        particle_file: openPMD-beamphysics beam to use instead of a preset.
        n_particles: Preset particles.
        n_settings: Quadrupole settings [default: 20; awa6d, rf6d: 9].
        k1_min: Lowest k1 [1/m^2] [default: -25; awa6d, rf6d: -12].
        k1_max: Highest k1 [1/m^2] [default: 15; awa6d, rf6d: 12].
        shape: Screen rows and columns [pixels] [default: 64 x 64; 96 x 96].
        pixel_size: Square pixel size [m] (``quad`` only) [default: 1e-3].
        p0c: Reference momentum times c [eV] [default: the file's, else 43.36e6].
        image_method: ``kde``, ``cic`` or ``histogram`` [default: kde; histogram].
        noise: Relative noise at the peak pixel (0: none).
        noise_model: ``poisson`` or ``gaussian``.
        shots: Shots per setting.
        seed: Random seed.
    """

    layout: str
    preset: str
    particle_file: Path | None
    n_particles: int
    n_settings: int | None
    k1_min: float | None
    k1_max: float | None
    shape: tuple[int, int] | None
    pixel_size: float | None
    p0c: float | None
    image_method: str | None
    noise: float
    noise_model: str
    shots: int
    seed: int


def _quad(opts: SyntheticRequest, out: Path, force: bool, beam: str) -> str:
    """The ``quad`` layout: one scan (format version 1); returns the report line."""
    lo = -25.0 if opts.k1_min is None else opts.k1_min
    hi = 15.0 if opts.k1_max is None else opts.k1_max
    pixel_size = 1e-3 if opts.pixel_size is None else opts.pixel_size
    image_method = opts.image_method or "kde"
    ds = make_synthetic_quad_scan(
        opts.preset,  # type: ignore[arg-type]
        particle_file=opts.particle_file,
        n_particles=opts.n_particles,
        p0c=opts.p0c,
        n_settings=20 if opts.n_settings is None else opts.n_settings,
        k1_range=(lo, hi),
        screen_shape=(64, 64) if opts.shape is None else opts.shape,
        pixel_size=(pixel_size, pixel_size),
        image_method=image_method,  # type: ignore[arg-type]
        noise=opts.noise,
        noise_model=opts.noise_model,  # type: ignore[arg-type]
        shots=opts.shots,
        seed=opts.seed,
    )
    write_quad_scan(ds, out, overwrite=force)
    k, s, h, w = ds.shape
    return (
        f"wrote {out}: {k} settings (k1 {lo:g} .. {hi:g} 1/m^2) x {s} shot(s) "
        f"of {h}x{w} px at {pixel_size * 1e3:g} mm, {beam}, "
        f"{ds.ground_truth.shape[0]} particles, p0c {ds.p0c / 1e6:g} MeV, "
        f"{image_method} images, noise {opts.noise:g} ({opts.noise_model}), "
        f"seed {opts.seed}"
    )


def _awa6d(opts: SyntheticRequest, out: Path, force: bool, beam: str) -> str:
    """The ``awa6d`` and ``rf6d`` layouts: two scans (format version 2)."""
    if opts.pixel_size is not None:
        raise ValueError(
            f"the {opts.layout} layout uses the DYG1/DYG2 calibration (no pixel "
            "size); scale it with the screen shape"
        )
    k = 9 if opts.n_settings is None else opts.n_settings
    lo = -12.0 if opts.k1_min is None else opts.k1_min
    hi = 12.0 if opts.k1_max is None else opts.k1_max
    image_method = opts.image_method or "histogram"
    p0c = opts.p0c
    particles = None
    if opts.particle_file is not None:
        particles, file_p0c, _ = read_openpmd_particles(opts.particle_file)
        p0c = file_p0c if p0c is None else p0c
    make = make_synthetic_rf6d if opts.layout == "rf6d" else make_synthetic_awa6d
    ms = make(
        opts.preset,  # type: ignore[arg-type]
        particles=particles,
        n_particles=opts.n_particles,
        p0c=43.36e6 if p0c is None else p0c,
        k1_values=torch.linspace(lo, hi, k, dtype=torch.float64),
        screen_shape=(96, 96) if opts.shape is None else opts.shape,
        image_method=image_method,  # type: ignore[arg-type]
        noise=opts.noise,
        noise_model=opts.noise_model,  # type: ignore[arg-type]
        shots=opts.shots,
        seed=opts.seed,
    )
    write_scans(ms, out, overwrite=force)
    sizes = ", ".join(
        f"{name} {s.n_settings}x{s.n_shots} of {s.screen_shape[0]}x{s.screen_shape[1]}"
        for name, s in ms
    )
    scanned = (
        "RF {off, 4 MV at phase 0, pi} (dipole_on)"
        if opts.layout == "rf6d"
        else "TDC {0, 4 MV}"
    )
    layout = "RF-phase-plus-dipole 6D" if opts.layout == "rf6d" else "AWA 6D"
    return (
        f"wrote {out} (format version 2, {layout} layout): scans {sizes}; k1 {lo:g} "
        f".. {hi:g} 1/m^2 x {scanned}; {beam}, "
        f"{ms.ground_truth.shape[0]} particles, {image_method} images, noise "
        f"{opts.noise:g}, seed {opts.seed}"
    )


def check_synthetic(request: SyntheticRequest, out: Path, force: bool) -> None:
    """Refuse a request or output file of ``diffaccel synthetic`` before any work.

    In this order: ``out`` not named ``.h5``/``.hdf5`` (``OUT``); a ``p0c``
    of a preset beam below the electron's limit (``--p0c``, see
    :func:`~diffaccel.data.quad_scan.check_p0c`); an ``out`` that ``force``
    may not replace (:func:`~diffaccel.data.owned_files.check_out_file`); a
    ``pixel_size`` for a 6D layout, whose screens are calibrated
    (``--pixel-size``).

    Raises:
        OptionError: naming the option; ``OutputFileError`` for ``out``.
    """
    if out.suffix.lower() not in (".h5", ".hdf5"):
        raise OptionError(
            f"{out}: expected a .h5 or .hdf5 file name (the quad-scan file is HDF5)",
            "OUT",
        )
    if request.p0c is not None and request.particle_file is None:
        try:
            check_p0c(request.p0c, "electron", "--p0c")
        except FormatError as err:
            raise OptionError(str(err).removeprefix("--p0c: "), "--p0c") from err
    check_out_file(out, force, {"--particle-file": request.particle_file})
    if request.layout != "quad" and request.pixel_size is not None:
        raise OptionError(
            f"the {request.layout} layout uses the DYG1/DYG2 calibration; scale it "
            "with --shape",
            "--pixel-size",
        )


def write_synthetic(request: SyntheticRequest, out: Path, overwrite: bool) -> str:
    """Simulate the scans of ``request`` and write them to ``out`` (HDF5).

    Args:
        request: What to simulate.
        out: The file to write (``.h5``).
        overwrite: Replace an existing ``out``.

    Returns:
        One line: the file, its scans and settings, the beam, the image model,
        noise and seed.

    Raises:
        ValueError: options that do not fit the layout or the beam (e.g. a
            pixel size for ``awa6d``), or a bad particle file.
        FileExistsError: ``out`` exists and not ``overwrite``.
    """
    beam = (
        f"preset {request.preset}"
        if request.particle_file is None
        else f"beam {request.particle_file}"
    )
    build = _quad if request.layout == "quad" else _awa6d
    return build(request, out, overwrite, beam)
