"""Synthetic quad-scan datasets: track a known beam and record its screen images.

Presets give 6D beams (Bmad coordinates, with energy spread) sized for the
default geometry, a 0.1 m quadrupole and a 1 m drift to a screen of
64 x 64 pixels of 1 mm, scanned over k1 = -25 ... 15 1/m^2 (the GPSR
benchmark geometry on a smaller screen): a few mm rms at the screen, more than
99.9 % of the beam on the screen at every setting.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import Literal

import torch
from torch import Tensor

from diffaccel.data.particles_io import read_openpmd_particles
from diffaccel.data.quad_scan import QuadScanDataset
from diffaccel.data.scans import MultiScanDataset
from diffaccel.dynamics import Beamline, Species

__all__ = [
    "AWA6D_BEAMLINES",
    "AWA6D_BEAM_SCALE",
    "DEFAULT_BEAMLINE",
    "PRESETS",
    "RF6D_BEAMLINES",
    "RF6D_STATES",
    "make_synthetic_awa6d",
    "make_synthetic_quad_scan",
    "make_synthetic_rf6d",
    "sample_preset_beam",
]

#: Quadrupole 0.1 m + drift 1.0 m + screen, as in the GPSR 4D benchmark.
DEFAULT_BEAMLINE: list[dict] = [
    {"type": "Quadrupole", "name": "Q1", "length": 0.1, "k1": 0.0},
    {"type": "Drift", "name": "D1", "length": 1.0},
    {"type": "Screen", "name": "SCREEN"},
]
PRESETS = ("gaussian", "correlated", "nonlinear")
_MIN_ON_SCREEN = 0.01  # refuse settings where less of the beam hits the screen

# rms of the uncorrelated presets: x, px, y, py, z, pz [m, 1, m, 1, m, 1]
_SIGMA = (1.5e-3, 0.6e-3, 1.5e-3, 0.6e-3, 1.0e-3, 5.0e-3)
# correlation matrix of the "correlated" preset (positive definite)
_CORRELATION = (
    (1.0, -0.6, 0.2, 0.0, 0.0, 0.1),
    (-0.6, 1.0, 0.0, 0.1, 0.0, 0.0),
    (0.2, 0.0, 1.0, 0.5, 0.0, 0.0),
    (0.0, 0.1, 0.5, 1.0, 0.0, 0.0),
    (0.0, 0.0, 0.0, 0.0, 1.0, -0.7),
    (0.1, 0.0, 0.0, 0.0, -0.7, 1.0),
)


def sample_preset_beam(
    preset: Literal["gaussian", "correlated", "nonlinear"],
    n_particles: int,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float64,
) -> Tensor:
    """Particles of a preset beam in Bmad coordinates.

    Presets:
        ``"gaussian"``: uncorrelated 6D Gaussian, rms 1.5 mm / 0.6 mrad per
        transverse plane, 1 mm in z and 0.5 % energy spread.
        ``"correlated"``: the same rms with x-px, y-py, x-y and z-pz (chirp)
        correlations.
        ``"nonlinear"``: a three-mode Gaussian mixture in x-y with an x-px
        curvature (px += kappa x^2), a y-dependent py tilt and a quadratic
        energy-position correlation (pz += c z^2): non-Gaussian and
        multi-modal, rms of the same order as the other presets.

    Args:
        preset: Name of the preset.
        n_particles: Number of particles N.
        generator: Random generator (seed it for reproducibility).
        dtype: Floating dtype of the result.

    Returns:
        (N, 6) tensor (x [m], px, y [m], py, z [m], pz), centred on zero mean.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> sample_preset_beam("nonlinear", 1000, g).shape
        torch.Size([1000, 6])
    """
    if preset not in PRESETS:
        raise ValueError(f"preset: expected one of {PRESETS}; got {preset!r}")
    if int(n_particles) < 2:
        raise ValueError(f"n_particles: expected >= 2; got {n_particles}")
    n = int(n_particles)
    sigma = torch.tensor(_SIGMA, dtype=torch.float64)
    u = torch.randn(n, 6, generator=generator, dtype=torch.float64)
    if preset == "gaussian":
        out = u * sigma
    elif preset == "correlated":
        chol = torch.linalg.cholesky(torch.tensor(_CORRELATION, dtype=torch.float64))
        out = (u @ chol.T) * sigma
    else:
        # three modes in (x, y) [m] with weights 0.5, 0.3, 0.2
        centres = torch.tensor(
            [[-1.8e-3, -0.9e-3], [1.8e-3, -0.6e-3], [0.3e-3, 1.8e-3]],
            dtype=torch.float64,
        )
        mode = torch.multinomial(
            torch.tensor([0.5, 0.3, 0.2], dtype=torch.float64),
            n,
            replacement=True,
            generator=generator,
        )
        x = centres[mode, 0] + 0.6e-3 * u[:, 0]
        y = centres[mode, 1] + 0.5e-3 * u[:, 2]
        # curvature: 0.4 mrad at |x| = 2 mm; tilt of py with y
        px = 0.3e-3 * u[:, 1] + 100.0 * (x**2) - 0.2 * x
        py = 0.3e-3 * u[:, 3] + 0.25 * y
        z = 1.0e-3 * u[:, 4]
        pz = 3.0e-3 * u[:, 5] + 2.0e3 * z**2 + 1.0 * x
        out = torch.stack([x, px, y, py, z, pz], dim=-1)
    out = out - out.mean(dim=0)
    return out.to(dtype)


def _histogram_images(
    at_screen: Tensor,
    shape: Sequence[int],
    pixel_size: Sequence[float],
    center: Sequence[float],
) -> Tensor:
    """Nearest-pixel counts / N of positions at a screen, float64.

    Pixel ``(i, j)`` collects the particles within half a pixel of its centre
    (the centres of :func:`~diffaccel.dynamics.images.pixel_centers`); particles
    off the screen are dropped, so an image sums to the fraction on the screen.

    Shapes:
        ``at_screen (K, N, 6)`` -> ``(K, H, W)``.
    """
    h, w = (int(v) for v in shape)
    psx, psy = (float(v) for v in pixel_size)
    x, y = at_screen[..., 0].double(), at_screen[..., 2].double()
    col = torch.floor((x - float(center[0])) / psx + w / 2).long()
    row = torch.floor((y - float(center[1])) / psy + h / 2).long()
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    k, n = x.shape
    flat = (torch.arange(k)[:, None] * (h * w) + row * w + col)[inside]
    counts = torch.bincount(flat, minlength=k * h * w).double()
    return counts.reshape(k, h, w) / n


def _add_noise(
    images: Tensor,
    noise: float,
    model: str,
    generator: torch.Generator,
) -> Tensor:
    """Noisy copies of sum-normalised images (..., H, W); float64 in and out."""
    if noise == 0:
        return images.clone()
    peak = images.flatten(-2).amax(dim=-1)[..., None, None]
    if model == "poisson":
        # counts such that the peak pixel has relative noise `noise`
        scale = 1.0 / (noise**2 * peak.clamp_min(1e-300))
        return torch.poisson(images * scale, generator=generator) / scale
    if model == "gaussian":
        draw = torch.randn(images.shape, generator=generator, dtype=images.dtype)
        # zero mean over each image (a perfectly estimated background), so the
        # image sum, and with it the sum-normalisation, is not perturbed
        draw = draw - draw.mean(dim=(-2, -1), keepdim=True)
        return images + noise * peak * draw
    raise ValueError(f"noise_model: expected 'poisson' or 'gaussian'; got {model!r}")


def make_synthetic_quad_scan(
    preset: Literal["gaussian", "correlated", "nonlinear"] = "gaussian",
    *,
    particles: Tensor | None = None,
    particle_file: str | os.PathLike | None = None,
    n_particles: int = 10_000,
    beamline_spec: Sequence[dict] | None = None,
    p0c: float | None = None,
    species: str | None = None,
    settings: Tensor | None = None,
    setting_names: Sequence[str] = ("Q1.k1",),
    setting_units: Sequence[str] | None = None,
    n_settings: int = 20,
    k1_range: tuple[float, float] = (-25.0, 15.0),
    screen_shape: tuple[int, int] = (64, 64),
    pixel_size: tuple[float, float] = (1e-3, 1e-3),
    center: tuple[float, float] = (0.0, 0.0),
    image_method: Literal["kde", "cic", "histogram"] = "kde",
    bandwidth: float | None = None,
    noise: float = 0.0,
    noise_model: Literal["poisson", "gaussian"] = "poisson",
    shots: int = 1,
    seed: int = 0,
    dtype: torch.dtype = torch.float32,
) -> QuadScanDataset:
    """Simulate a quad scan of a known beam, ground truth included.

    The beam (a preset, a tensor, or an openPMD particle file) is tracked
    through the beamline at every setting; the screen image of each setting is
    rendered, ``shots`` noisy copies are drawn, and every shot is normalised to
    unit sum.

    Args:
        preset: Beam preset (see :func:`sample_preset_beam`) when neither
            ``particles`` nor ``particle_file`` is given.
        particles: Initial particles in Bmad coordinates, (N, 6).
        particle_file: openPMD-beamphysics HDF5 file with the initial beam; its
            ``p0c`` and species are used unless given here (a different ``p0c``
            re-references the same physical momenta).
        n_particles: Number of preset particles N.
        beamline_spec: Element list; default :data:`DEFAULT_BEAMLINE`.
        p0c: Reference momentum times c [eV]; default 43.36e6.
        species: ``"electron"`` (default), ``"positron"`` or ``"proton"``.
        settings: Scan values (K, P) [setting_units]; default ``n_settings``
            values of k1 evenly spaced over ``k1_range`` [1/m^2].
        setting_names: ``"ELEMENT.parameter"`` per settings column.
        setting_units: Units per column; default "1/m^2" for ``k1``.
        n_settings: K of the default scan.
        k1_range: (min, max) of the default scan [1/m^2].
        screen_shape: (H, W) [pixels].
        pixel_size: (x, y) [m].
        center: Screen centre (x, y) [m].
        image_method: ``"kde"`` (Gaussian KDE), ``"cic"`` (cloud-in-cell) or
            ``"histogram"`` (particles counted in the pixel they land in, as a
            camera does: a point spread of 1/12 pixel^2 variance, the images of
            the shared 6D benchmark files).
        bandwidth: KDE bandwidth [m]; default one pixel.
        noise: Relative noise level: ``"poisson"`` scales counts so the peak
            pixel has relative rms ``noise``; ``"gaussian"`` adds noise of rms
            ``noise`` times the peak to every pixel, with zero mean over each
            image (as after a background subtraction), so pixels may be
            negative. 0 gives identical shots.
        noise_model: ``"poisson"`` or ``"gaussian"``.
        shots: Shots S per setting.
        seed: Seed of the beam sample and the noise.
        dtype: Tracking and imaging dtype.

    Returns:
        A :class:`QuadScanDataset` with images (K, S, H, W), the initial beam
        as ``ground_truth`` (float64, Bmad) and ``metadata["synthetic"]``
        (options and the fraction of the beam on the screen per setting).

    Raises:
        ValueError: for inconsistent options (shapes, negative noise, both
            ``particles`` and ``particle_file``) or a beam that misses the screen.

    Example:
        >>> ds = make_synthetic_quad_scan(
        ...     "gaussian", n_particles=2000, n_settings=4,
        ...     screen_shape=(32, 32), pixel_size=(2e-3, 2e-3))
        >>> ds.shape, ds.ground_truth.shape
        ((4, 1, 32, 32), torch.Size([2000, 6]))
    """
    if particles is not None and particle_file is not None:
        raise ValueError("give particles or particle_file, not both")
    if noise < 0 or not math.isfinite(noise):
        raise ValueError(f"noise: expected a finite value >= 0; got {noise}")
    if int(shots) < 1:
        raise ValueError(f"shots: expected >= 1; got {shots}")
    generator = torch.Generator().manual_seed(int(seed))
    source: dict = {"kind": "preset", "preset": preset}
    if particle_file is not None:
        beam, file_p0c, file_species = read_openpmd_particles(particle_file)
        if p0c is not None and float(p0c) != file_p0c:
            # same physical momenta, new reference: scale px, py and 1 + pz
            ratio = file_p0c / float(p0c)
            beam = beam.clone()
            beam[:, [1, 3]] *= ratio
            beam[:, 5] = (1.0 + beam[:, 5]) * ratio - 1.0
        p0c = file_p0c if p0c is None else p0c
        species = file_species if species is None else species
        source = {"kind": "openpmd", "file": os.fspath(particle_file)}
    elif particles is not None:
        beam = torch.as_tensor(particles)
        source = {"kind": "tensor"}
    else:
        beam = sample_preset_beam(preset, n_particles, generator)
    beam = beam.detach().to(torch.float64)
    if beam.ndim != 2 or beam.shape[-1] != 6:
        raise ValueError(f"particles: expected shape (N, 6); got {tuple(beam.shape)}")
    if not bool(torch.isfinite(beam).all()):
        raise ValueError("particles: expected finite coordinates; found NaN/inf")
    p0c = 43.36e6 if p0c is None else float(p0c)
    species = "electron" if species is None else str(species)
    spec = [dict(e) for e in (beamline_spec or DEFAULT_BEAMLINE)]
    names = list(setting_names)
    if settings is None:
        settings = torch.linspace(
            float(k1_range[0]), float(k1_range[1]), int(n_settings), dtype=torch.float64
        )[:, None]
    settings = torch.as_tensor(settings, dtype=torch.float64)
    if settings.ndim == 1:
        settings = settings[:, None]
    if setting_units is None:
        setting_units = ["1/m^2" if n.endswith(".k1") else "" for n in names]
    screen = next((e["name"] for e in spec if e.get("type") == "Screen"), None)
    if screen is None:
        raise ValueError("beamline_spec: needs a Screen element")
    line = Beamline.from_spec(spec).with_screen(
        screen, shape=screen_shape, pixel_size=pixel_size, center=center
    )
    at_screen = line.track_screens(
        beam.to(dtype),
        p0c=p0c,
        settings=settings.to(dtype),
        names=names,
        species=Species.from_name(species),
    )[screen]
    if image_method == "histogram":
        clean = _histogram_images(at_screen, screen_shape, pixel_size, center)
    else:
        kwargs = {"bandwidth": bandwidth} if image_method == "kde" else {}
        clean = line[screen].image(at_screen, method=image_method, **kwargs).double()
    on_screen = clean.sum(dim=(-2, -1))
    if bool((on_screen < _MIN_ON_SCREEN).any()):
        k = int(torch.nonzero(on_screen < _MIN_ON_SCREEN)[0])
        raise ValueError(
            f"the beam misses the screen at setting {k} ({settings[k].tolist()}): "
            f"{float(on_screen[k]):.2%} of it lands on the screen; use a larger "
            "screen or pixel size"
        )
    clean = clean / on_screen[:, None, None]
    shots_t = clean[:, None].expand(-1, int(shots), -1, -1)
    noisy = _add_noise(shots_t, float(noise), noise_model, generator)
    totals = noisy.sum(dim=(-2, -1), keepdim=True)
    if bool((totals <= 0).any()):
        k, s = (int(v) for v in torch.nonzero(totals[..., 0, 0] <= 0)[0])
        raise ValueError(
            f"noise: at noise={noise} the image of setting {k} (shot {s}) has no "
            "signal left; lower the noise"
        )
    noisy = noisy / totals
    if image_method == "kde":  # a Gaussian of the bandwidth (default one pixel)
        bw = [1.0, 1.0] if bandwidth is None else [bandwidth / p for p in pixel_size]
        resolution = 0.5 * (bw[0] + bw[1])
    elif image_method == "histogram":  # a box of one pixel
        resolution = math.sqrt(1.0 / 12.0)
    else:  # cloud-in-cell deposit: a triangle of one pixel half-width
        resolution = math.sqrt(1.0 / 6.0)
    metadata = {
        "synthetic": {
            "source": source,
            "n_particles": int(beam.shape[0]),
            "image_method": image_method,
            "bandwidth": bandwidth,
            "noise": float(noise),
            "noise_model": noise_model,
            "shots": int(shots),
            "seed": int(seed),
            "fraction_on_screen": [round(float(v), 6) for v in on_screen],
        },
        "preprocessing": [],
    }
    return QuadScanDataset(
        images=noisy.float(),
        settings=settings,
        setting_names=names,
        setting_units=list(setting_units),
        p0c=p0c,
        species=species,
        beamline_spec=spec,
        pixel_size=pixel_size,
        center=center,
        ground_truth=beam,
        metadata=metadata,
        resolution_pixels=resolution,
    )


# ---------------------------------------------------------------------- 6D layout
#: The AWA 6D layout (GPSR 6D experiment, Argonne Wakefield Accelerator): a
#: 0.11 m quadrupole, a 1.3 GHz deflecting cavity (tilt pi/2: vertical streak,
#: Bmad convention) and either a drift to screen DYG1 ("dipole_off") or a
#: 20 degree spectrometer dipole to screen DYG2 ("dipole_on"). Geometry as in
#: the beamline attributes of the shared ``sixd_synthetic_*.h5`` files.
_AWA6D_UPSTREAM: tuple[dict, ...] = (
    {"type": "Quadrupole", "name": "SCAN_QUAD", "length": 0.11, "k1": 0.0},
    {"type": "Drift", "name": "D1", "length": 0.730702},
    {
        "type": "TransverseDeflectingCavity",
        "name": "SCAN_TDC",
        "length": 0.01,
        "voltage": 0.0,
        "frequency": 1.3e9,
        "phase": 0.0,
        "tilt": math.pi / 2,
    },
    {"type": "Drift", "name": "D2", "length": 0.475798},
)
AWA6D_BEAMLINES: dict[str, list[dict]] = {
    "dipole_off": [
        *(dict(e) for e in _AWA6D_UPSTREAM),
        {"type": "Drift", "name": "SCAN_DIPOLE_OFF", "length": 0.3018},
        {"type": "Drift", "name": "D3", "length": 0.7381},
        {"type": "Screen", "name": "DYG1"},
    ],
    "dipole_on": [
        *(dict(e) for e in _AWA6D_UPSTREAM),
        {
            "type": "Dipole",
            "name": "SCAN_DIPOLE",
            "length": 0.3080171612876794,
            "angle": -math.radians(20.0),
            "e1": 0.0,
            "e2": -math.radians(20.0),
        },
        {"type": "Drift", "name": "D3", "length": 0.7284155741333849},
        {"type": "Screen", "name": "DYG2"},
    ],
}
#: A 6D layout without a deflecting cavity: the AWA geometry with the TDC
#: replaced by a 0.2 m S-band accelerating cavity (``SCAN_RF``, Bmad rfcavity
#: convention) whose voltage and phase are scanned; near the zero crossing it
#: chirps the bunch (``pz += V / p0c * sin(phase + k z)``) and the dipole
#: turns the chirp into x on DYG2, as RF-phase-plus-dipole measurements at
#: PAL-XFEL do. The drift after it is shortened so the screens stay in place.
RF6D_BEAMLINES: dict[str, list[dict]] = {
    name: [
        (
            {
                "type": "RFCavity",
                "name": "SCAN_RF",
                "length": 0.2,
                "voltage": 0.0,
                "frequency": 2.856e9,
                "phase": 0.0,
            }
            if e["name"] == "SCAN_TDC"
            else {**e, "length": e["length"] - 0.19}
            if e["name"] == "D2"
            else dict(e)
        )
        for e in spec
    ]
    for name, spec in AWA6D_BEAMLINES.items()
}
#: RF states of the rf6d layout, ``(voltage [V], phase [rad])``: off, zero
#: crossing with the head gaining energy, zero crossing with the head losing.
RF6D_STATES = ((0.0, 0.0), (4e6, 0.0), (4e6, math.pi))
#: Pixel sizes of DYG1 and DYG2 [m] (square pixels).
AWA6D_PIXEL_SIZE = {
    "dipole_off": 2.7253091221439543e-4,
    "dipole_on": 2.2466741181235926e-4,
}
#: Scale of the preset beams for this layout (x, px, y, py, z, pz): about
#: 0.5 mm, 0.26 mrad, 0.8 mm and 0.37 % rms, so that every setting stays on
#: the 96 x 96 pixel screens.
AWA6D_BEAM_SCALE = (1 / 3, 0.43, 1 / 3, 0.43, 0.8, 0.74)


def make_synthetic_rf6d(
    preset: Literal["gaussian", "correlated", "nonlinear"] = "nonlinear",
    *,
    particles: Tensor | None = None,
    n_particles: int = 100_000,
    p0c: float = 43.36e6,
    k1_values: Sequence[float] | Tensor | None = None,
    rf_states: Sequence[tuple[float, float]] = RF6D_STATES,
    dipole_scales: Sequence[float] = (),
    screen_shape: tuple[int, int] = (96, 96),
    image_method: Literal["kde", "cic", "histogram"] = "histogram",
    noise: float = 0.0,
    noise_model: Literal["poisson", "gaussian"] = "poisson",
    shots: int = 1,
    seed: int = 0,
) -> MultiScanDataset:
    """Simulate a 6D measurement by RF phase plus dipole (no deflecting cavity).

    With the two scans alone the energy spread is not measured: the
    quadrupole is the first element, so the dipole screen's ``R12`` and
    ``R16`` do not change over the scan and ``<pz pz>`` enters its images only
    in the fixed combination ``2 R12 <px pz> + R16 <pz pz>`` with the px-pz
    covariance (``diffaccel design`` reports it left to the prior). A second
    dipole current changes ``R16 / R12`` and separates the two:
    ``dipole_scales`` adds, per scale ``f``, a scan ``dipole_on_<f>`` of the
    quadrupole strengths with the cavity off and the dipole at ``f`` times its
    angle (pole faces unchanged; the screen on the orbit the weaker bend
    defines, i.e. a screen wide enough for both orbits, its image cropped
    around the beam).

    The layout is :data:`RF6D_BEAMLINES`. Scan ``"dipole_off"`` records the
    quadrupole strengths with the cavity off (the straight screen does not see
    ``pz``); scan ``"dipole_on"`` records every strength at every RF state of
    ``rf_states`` (default :data:`RF6D_STATES`), in the order ``(k1_0,
    state_0), (k1_0, state_1), ...``. Settings are ``SCAN_QUAD.k1``,
    ``SCAN_RF.voltage`` and ``SCAN_RF.phase`` in both scans. The beam (the
    preset scaled as for :func:`make_synthetic_awa6d`) is tracked exactly and
    imaged as in :func:`make_synthetic_quad_scan`.

    Args:
        preset: Beam preset when ``particles`` is not given.
        particles: Initial particles in Bmad coordinates ``(N, 6)``.
        n_particles: Preset particles N.
        p0c: Reference momentum times c [eV].
        k1_values: Quadrupole strengths [1/m^2]; default -12 ... 12 in 9 steps.
        rf_states: ``(voltage [V], phase [rad])`` of the dipole-on scan.
        dipole_scales: Dipole angle fractions of the added scans (e.g.
            ``(0.8,)``; none by default).
        screen_shape: (H, W) of both screens [pixels].
        image_method: ``"histogram"``, ``"cic"`` or ``"kde"``.
        noise: Relative noise at the peak pixel (0: none).
        noise_model: ``"poisson"`` or ``"gaussian"``.
        shots: Shots per setting.
        seed: Seed of the beam sample and the noise.

    Returns:
        A :class:`MultiScanDataset` with the scans ``dipole_off``,
        ``dipole_on`` and one per ``dipole_scales``, and the beam as ground
        truth.

    Example:
        >>> ms = make_synthetic_rf6d(n_particles=2000, k1_values=[-6.0, 6.0],
        ...                          screen_shape=(32, 32))
        >>> ms["dipole_off"].shape, ms["dipole_on"].shape
        ((2, 1, 32, 32), (6, 1, 32, 32))
    """
    generator = torch.Generator().manual_seed(int(seed))
    if particles is None:
        beam = sample_preset_beam(preset, n_particles, generator)
        beam = beam * torch.tensor(AWA6D_BEAM_SCALE, dtype=beam.dtype)
    else:
        beam = torch.as_tensor(particles, dtype=torch.float64)
    k1 = torch.as_tensor(
        torch.linspace(-12.0, 12.0, 9) if k1_values is None else k1_values,
        dtype=torch.float64,
    ).flatten()
    states = torch.as_tensor(rf_states, dtype=torch.float64).reshape(-1, 2)
    off = torch.zeros(k1.shape[0], 2, dtype=torch.float64)
    settings = {
        "dipole_off": torch.cat([k1.unsqueeze(-1), off], dim=-1),
        "dipole_on": torch.cat(
            [
                k1.repeat_interleave(states.shape[0]).unsqueeze(-1),
                states.repeat(k1.shape[0], 1),
            ],
            dim=-1,
        ),
    }
    specs = dict(RF6D_BEAMLINES)
    pixel = dict(AWA6D_PIXEL_SIZE)
    for f in dipole_scales:
        if not (math.isfinite(f) and 0.0 < f):
            raise ValueError(f"dipole_scales must be positive; got {f}.")
        name = f"dipole_on_{f:g}"
        specs[name] = [
            {**e, "angle": f * e["angle"]} if e["name"] == "SCAN_DIPOLE" else dict(e)
            for e in RF6D_BEAMLINES["dipole_on"]
        ]
        settings[name] = settings["dipole_on"]
        pixel[name] = AWA6D_PIXEL_SIZE["dipole_on"]
    scans = {}
    for name, spec in specs.items():
        ps = pixel[name] * 96 / screen_shape[1]
        scans[name] = make_synthetic_quad_scan(
            particles=beam,
            beamline_spec=spec,
            p0c=p0c,
            settings=settings[name],
            setting_names=("SCAN_QUAD.k1", "SCAN_RF.voltage", "SCAN_RF.phase"),
            setting_units=("1/m^2", "V", "rad"),
            screen_shape=screen_shape,
            pixel_size=(ps, ps),
            image_method=image_method,
            noise=noise,
            noise_model=noise_model,
            shots=shots,
            seed=seed,
            dtype=torch.float64,
        )
    source = "tensor" if particles is not None else f"preset {preset}"
    return MultiScanDataset(
        scans,
        metadata={
            "description": f"synthetic RF-phase-plus-dipole 6D layout, {source}, "
            f"seed {seed}"
        },
    )


def make_synthetic_awa6d(
    preset: Literal["gaussian", "correlated", "nonlinear"] = "nonlinear",
    *,
    particles: Tensor | None = None,
    n_particles: int = 100_000,
    p0c: float = 43.36e6,
    k1_values: Sequence[float] | Tensor | None = None,
    voltages: Sequence[float] = (0.0, 4e6),
    screen_shape: tuple[int, int] = (96, 96),
    image_method: Literal["kde", "cic", "histogram"] = "histogram",
    noise: float = 0.0,
    noise_model: Literal["poisson", "gaussian"] = "poisson",
    shots: int = 1,
    seed: int = 0,
) -> MultiScanDataset:
    """Simulate the AWA 6D measurement of a known beam (two scans, version 2).

    Each scan (``"dipole_off"``, ``"dipole_on"``; see :data:`AWA6D_BEAMLINES`)
    records every quadrupole strength at every TDC voltage, in the order
    ``(k1_0, V_0), (k1_0, V_1), (k1_1, V_0), ...``. The beam is tracked exactly
    (chromatic quadrupole, RF curvature, exact dipole) and imaged as in
    :func:`make_synthetic_quad_scan`.

    Args:
        preset: Beam preset (see :func:`sample_preset_beam`), scaled to this
            layout, when ``particles`` is not given.
        particles: Initial particles in Bmad coordinates ``(N, 6)``.
        n_particles: Preset particles N.
        p0c: Reference momentum times c [eV].
        k1_values: Quadrupole strengths [1/m^2]; default -12 ... 12 in 9 steps.
        voltages: TDC voltages [V]; default off and 4 MV.
        screen_shape: (H, W) of both screens [pixels].
        image_method: ``"histogram"`` (default: nearest-pixel counts, as the
            shared 6D files and the 6D default ``blur_pixels`` of the
            reconstruction assume), ``"cic"`` or ``"kde"`` (one-pixel bandwidth).
        noise: Relative noise at the peak pixel (0: none).
        noise_model: ``"poisson"`` or ``"gaussian"``.
        shots: Shots per setting.
        seed: Seed of the beam sample and the noise.

    Returns:
        A :class:`MultiScanDataset` with the scans ``dipole_off``,
        ``dipole_on`` and one per ``dipole_scales``, and the beam as ground
        truth.

    Example:
        >>> ms = make_synthetic_awa6d(n_particles=2000, k1_values=[-6.0, 6.0],
        ...                           screen_shape=(32, 32))
        >>> ms.names, ms["dipole_on"].shape
        (['dipole_off', 'dipole_on'], (4, 1, 32, 32))
    """
    generator = torch.Generator().manual_seed(int(seed))
    if particles is None:
        beam = sample_preset_beam(preset, n_particles, generator)
        beam = beam * torch.tensor(AWA6D_BEAM_SCALE, dtype=beam.dtype)
    else:
        beam = torch.as_tensor(particles, dtype=torch.float64)
    k1 = torch.as_tensor(
        torch.linspace(-12.0, 12.0, 9) if k1_values is None else k1_values,
        dtype=torch.float64,
    ).flatten()
    volts = torch.as_tensor(voltages, dtype=torch.float64).flatten()
    settings = torch.stack(torch.meshgrid(k1, volts, indexing="ij"), dim=-1).reshape(
        -1, 2
    )
    scans = {}
    for name, spec in AWA6D_BEAMLINES.items():
        ps = AWA6D_PIXEL_SIZE[name] * 96 / screen_shape[1]
        scans[name] = make_synthetic_quad_scan(
            particles=beam,
            beamline_spec=spec,
            p0c=p0c,
            settings=settings,
            setting_names=("SCAN_QUAD.k1", "SCAN_TDC.voltage"),
            setting_units=("1/m^2", "V"),
            screen_shape=screen_shape,
            pixel_size=(ps, ps),
            image_method=image_method,
            noise=noise,
            noise_model=noise_model,
            shots=shots,
            seed=seed,
            dtype=torch.float64,
        )
    source = "tensor" if particles is not None else f"preset {preset}"
    return MultiScanDataset(
        scans,
        metadata={"description": f"synthetic AWA 6D layout, {source}, seed {seed}"},
    )
