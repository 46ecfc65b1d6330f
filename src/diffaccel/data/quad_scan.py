"""Quad-scan datasets: screen images recorded while scanning beamline parameters.

The on-disk layout ("quad-scan", format version 1) is documented in
``docs/file_formats.md``. :class:`QuadScanDataset` is the in-memory container;
:func:`read_quad_scan` and :func:`write_quad_scan` convert between the two and
validate every field on the way in and out.
"""

from __future__ import annotations

import copy
import json
import math
import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import torch
from torch import Tensor

from diffaccel.data.atomic import atomic_write, os_condition
from diffaccel.data.errors import FormatError
from diffaccel.data.owned_files import H5_ATTRIBUTE, h5_mark
from diffaccel.dynamics import ELEMENT_TYPES, Beamline, Species, pixel_centers
from diffaccel.dynamics.coordinates import cheetah_to_bmad

__all__ = [
    "BMAD_COORDINATES",
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "PARAMETER_LIMITS",
    "PARAMETER_UNITS",
    "QuadScanDataset",
    "check_p0c",
    "check_setting_limits",
    "read_quad_scan",
    "write_quad_scan",
]

FORMAT_NAME = "quad-scan"
FORMAT_VERSION = 1
#: Versions read by this module (2: several scans, see diffaccel.data.scans).
READ_VERSIONS = (1, 2)
BMAD_COORDINATES = ("x", "px", "y", "py", "z", "pz")
CHEETAH_COORDINATES = ("x", "px", "y", "py", "tau", "delta")
BMAD_CONVENTION = (
    "bmad (x, y, z [m]; px = Px/P0, py = Py/P0; z = -beta*c*(t - t0); pz = dP/P0)"
)
SPECIES = ("electron", "positron", "proton")

#: Accepted unit strings of scanned element parameters (first = canonical).
PARAMETER_UNITS: dict[str, tuple[str, ...]] = {
    "k1": ("1/m^2", "m^-2", "1/m**2"),
    "length": ("m",),
    "dx": ("m",),
    "dy": ("m",),
    "tilt": ("rad",),
    "angle": ("rad",),
    "e1": ("rad",),
    "e2": ("rad",),
    "phase": ("rad",),
    "voltage": ("V",),
    "frequency": ("Hz",),
}

#: Plausible magnitudes of element parameters and scan settings (``|value| <=
#: limit``, SI units). Larger values are almost always a unit or typing error
#: (a 1e30 m drift, k1 in T/m) and would silently put the beam off the screen.
PARAMETER_LIMITS: dict[str, float] = {
    "length": 1e3,  # m
    # LinearMap entries (m, rad, 1/m, ...: R12 of a 1 km drift is 1e3); 1e300
    # passed the finite check, then the moment fit's least squares overflowed
    "matrix": 1e6,
    "k1": 1e4,  # 1/m^2 (a 0.1 m quadrupole of k1 = 1e4 has f = 1 mm)
    "dx": 1.0,  # m
    "dy": 1.0,  # m
    "tilt": 10.0,  # rad
    "angle": 10.0,  # rad
    "e1": 1.5,  # rad (tan(e) diverges at pi / 2)
    "e2": 1.5,  # rad
    "phase": 1e3,  # rad
    "voltage": 1e10,  # V
    "frequency": 1e12,  # Hz
}
#: Pixel sizes accepted [m]: 1 nm (below any camera pixel; image moments square
#: the pixel size, and a denormal one underflows to 0) to 10 m. Largest
#: screen-centre offset accepted [m].
MIN_PIXEL_SIZE = 1e-9
MAX_PIXEL_SIZE = 10.0
MAX_CENTER = 1.0
#: Largest accepted screen resolution (point-spread rms) [pixels].
MAX_RESOLUTION_PIXELS = 100.0
#: Smallest screen: image moments need at least two pixels per axis.
MIN_PIXELS = 2
#: Smallest accepted ``p0c / (m c^2)`` (beta * gamma): 511 eV for electrons,
#: 938 keV for protons. Below it ``p0c`` is almost surely in the wrong unit
#: (43.36 for 43.36 MeV); no beam this tool images is that slow.
MIN_BETA_GAMMA = 1e-3
#: Largest accepted ``p0c`` [eV]: 1 PeV, over 100 times the LHC's 7 TeV (a value
#: beyond it is a unit error, and its Lorentz factors overflow the conversions).
MAX_P0C = 1e15


@dataclass(frozen=True, eq=False)
class QuadScanDataset:
    """Screen images of one beam recorded at K settings of scanned beamline parameters.

    Constructing the dataclass validates every field (and casts ``images`` to
    float32, ``settings`` to float64); all transformations return new datasets.

    Args:
        images: Screen intensities, ``images[k, s, i, j]`` at
            y = center_y + (i - (H-1)/2) * pixel_size_y and
            x = center_x + (j - (W-1)/2) * pixel_size_x [arbitrary units].
        settings: Value of each scanned parameter at each setting [setting_units].
        setting_names: ``"ELEMENT.parameter"`` per settings column, e.g. ``"Q1.k1"``.
        setting_units: Unit string per settings column, e.g. ``"1/m^2"``.
        p0c: Reference momentum times c [eV].
        species: ``"electron"``, ``"positron"`` or ``"proton"``.
        beamline_spec: Ordered element dicts (``type``, ``name``, parameters in SI),
            as accepted by ``Beamline.from_spec``; exactly one ``Screen``.
        pixel_size: Screen pixel size (x, y) [m], both > 0.
        center: Screen position of the image centre (x, y) [m].
        ground_truth: Known initial particles in Bmad coordinates
            (x [m], px, y [m], py, z [m], pz), or ``None`` for measured data.
        metadata: JSON-serialisable provenance; ``metadata["preprocessing"]`` is
            the list of processing steps (dicts with ``"step"`` and parameters).
        resolution_pixels: Rms of the screen's point spread (image formation:
            optics, scintillator, binning) [pixels], or ``None`` when unknown.
            A reconstruction models its images with this blur unless told
            otherwise (a wrong value biases the divergences: a constant
            screen-variance offset is degenerate with ``<px px>`` in a
            quadrupole + drift scan).

    Shapes:
        ``images`` (K, S, H, W), ``settings`` (K, P), ``ground_truth`` (N, 6).

    Raises:
        FormatError: naming the field when a value is missing, has the wrong
            shape, contains NaN/inf, an all-zero image, an image with a pixel
            more negative than its brightest pixel is bright (small negative
            pixels of background-subtracted images are accepted), a non-positive
            pixel size, a ``p0c`` below ``MIN_BETA_GAMMA`` times the rest energy
            (a unit error), a setting name that is not a parameter of the
            beamline or a negative setting of a parameter that must be >= 0.

    Example:
        >>> import torch
        >>> spec = [{"type": "Quadrupole", "name": "Q1", "length": 0.1, "k1": 0.0},
        ...         {"type": "Drift", "name": "D1", "length": 1.0},
        ...         {"type": "Screen", "name": "SCREEN"}]
        >>> ds = QuadScanDataset(
        ...     images=torch.rand(3, 2, 8, 8),
        ...     settings=torch.tensor([[-1.0], [0.0], [1.0]]),
        ...     setting_names=["Q1.k1"], setting_units=["1/m^2"], p0c=43e6,
        ...     species="electron", beamline_spec=spec, pixel_size=(1e-3, 1e-3),
        ...     center=(0.0, 0.0))
        >>> ds.shape, ds.n_settings, ds.screen_shape
        ((3, 2, 8, 8), 3, (8, 8))
        >>> ds.subset([0, 2]).settings.squeeze(-1).tolist()
        [-1.0, 1.0]
    """

    images: Tensor
    settings: Tensor
    setting_names: list[str]
    setting_units: list[str]
    p0c: float
    species: str
    beamline_spec: list[dict]
    pixel_size: tuple[float, float]
    center: tuple[float, float]
    ground_truth: Tensor | None = None
    metadata: dict = field(default_factory=dict)
    resolution_pixels: float | None = None

    def __post_init__(self) -> None:
        _set = object.__setattr__
        if not isinstance(self.images, Tensor):
            _set(self, "images", torch.as_tensor(np.asarray(self.images)))
        if not isinstance(self.settings, Tensor):
            _set(self, "settings", torch.as_tensor(np.asarray(self.settings)))
        if self.images.is_complex() or self.images.dtype == torch.bool:
            raise FormatError(
                f"images: expected real intensities; found dtype {self.images.dtype}"
            )
        _set(self, "images", _float32_images(self.images.detach()))
        _set(self, "settings", self.settings.detach().to(torch.float64))
        if self.ground_truth is not None:
            gt = self.ground_truth
            if not isinstance(gt, Tensor):
                gt = torch.as_tensor(np.asarray(gt))
            _set(self, "ground_truth", gt.detach())
        _set(self, "setting_names", [str(n) for n in self.setting_names])
        _set(self, "setting_units", [str(u) for u in self.setting_units])
        _set(self, "beamline_spec", copy.deepcopy(list(self.beamline_spec)))
        _set(self, "metadata", copy.deepcopy(dict(self.metadata)))
        _set(self, "pixel_size", _pair("pixel_size", self.pixel_size))
        _set(self, "center", _pair("center", self.center))
        _set(self, "p0c", _positive_float("p0c", self.p0c, unit="eV"))
        _validate(self)

    # ------------------------------------------------------------------ shapes
    @property
    def shape(self) -> tuple[int, int, int, int]:
        """Image array shape (K, S, H, W)."""
        return tuple(self.images.shape)  # type: ignore[return-value]

    @property
    def n_settings(self) -> int:
        """Number of scan settings K."""
        return int(self.images.shape[0])

    @property
    def n_shots(self) -> int:
        """Number of shots per setting S."""
        return int(self.images.shape[1])

    @property
    def screen_shape(self) -> tuple[int, int]:
        """Image rows and columns (H, W)."""
        return (int(self.images.shape[2]), int(self.images.shape[3]))

    @property
    def screen_name(self) -> str:
        """Name of the ``Screen`` element of ``beamline_spec``."""
        return next(e["name"] for e in self.beamline_spec if e["type"] == "Screen")

    # ------------------------------------------------------------------ views
    def mean_images(self) -> Tensor:
        """Shot-averaged images, each normalised to unit sum.

        Returns:
            Tensor of shape (K, H, W), float32; ``out[k].sum() == 1``.
        """
        mean = self.images.mean(dim=1)
        total = mean.sum(dim=(-2, -1), keepdim=True)
        return mean / total.clamp_min(torch.finfo(mean.dtype).tiny)

    def pixel_centers(self) -> tuple[Tensor, Tensor]:
        """Screen coordinates of the pixel centres (the screen's, see ``Screen``).

        Returns:
            ``(xs, ys)``: float64 tensors of shapes (W,) and (H,) [m], ascending
            with the column and row index, on the images' device.
        """
        return pixel_centers(
            self.screen_shape,
            self.pixel_size,
            self.center,
            dtype=torch.float64,
            device=self.images.device,
        )

    def beamline(self) -> Beamline:
        """The beamline with the screen geometry of this dataset.

        Returns:
            ``Beamline.from_spec(beamline_spec)`` whose screen has ``shape``
            (H, W), ``pixel_size`` and ``center`` of this dataset.
        """
        return Beamline.from_spec(self.beamline_spec).with_screen(
            self.screen_name,
            shape=self.screen_shape,
            pixel_size=self.pixel_size,
            center=self.center,
        )

    def subset(self, indices: Sequence[int] | Tensor | slice) -> QuadScanDataset:
        """The dataset restricted to some scan settings.

        Args:
            indices: Setting indices (ints, a slice, or an int/bool tensor), e.g.
                ``range(0, ds.n_settings, 2)`` for the customary training split.

        Returns:
            A new dataset with ``images[indices]``, ``settings[indices]``; the
            step is appended to ``metadata["preprocessing"]``.

        Raises:
            IndexError: if an index is outside ``[-K, K)``.
            ValueError: if no setting is selected.
        """
        k = self.n_settings
        if isinstance(indices, slice):
            idx = torch.arange(k)[indices]
        else:
            idx = torch.as_tensor(
                indices if isinstance(indices, Tensor) else list(indices)
            )
            if idx.dtype == torch.bool:
                if idx.shape != (k,):
                    raise ValueError(
                        f"subset: boolean mask must have shape ({k},); got "
                        f"{tuple(idx.shape)}"
                    )
                idx = torch.nonzero(idx).flatten()
            idx = idx.to(torch.long).flatten().cpu()
        if idx.numel() == 0:
            raise ValueError("subset: no setting selected; pass at least one index")
        if bool(((idx < -k) | (idx >= k)).any()):
            raise IndexError(
                f"subset: indices {idx.tolist()} out of range for {k} settings"
            )
        idx = idx % k
        return self.with_step(
            {"step": "subset", "indices": idx.tolist()},
            images=self.images[idx.to(self.images.device)],
            settings=self.settings[idx.to(self.settings.device)],
        )

    def with_step(self, step: dict[str, Any], **changes: Any) -> QuadScanDataset:
        """A new dataset with some fields changed and a processing step recorded.

        Args:
            step: JSON-serialisable description, ``{"step": name, **parameters}``.
            **changes: Dataclass fields to replace (``images``, ``pixel_size``, ...).

        Returns:
            The new, validated dataset; ``self`` is unchanged.
        """
        metadata = copy.deepcopy(self.metadata)
        metadata.setdefault("preprocessing", []).append(copy.deepcopy(step))
        return replace(self, metadata=metadata, **changes)


# ---------------------------------------------------------------------- validation
def _check_preprocessing(metadata: dict, where: str) -> None:
    """Refuse a ``preprocessing`` record that is not a list of step objects."""
    steps = metadata.get("preprocessing", [])
    if not isinstance(steps, list) or not all(isinstance(s, dict) for s in steps):
        raise FormatError(
            f"{where}.preprocessing: expected a list of step objects "
            '([{"step": name, ...}, ...], the steps applied to the images); '
            f"found {type(steps).__name__} {steps!r:.80}"
        )


def _pair(name: str, value: Any) -> tuple[float, float]:
    try:
        pair = tuple(float(v) for v in value)
    except (TypeError, ValueError) as err:
        raise FormatError(
            f"{name}: expected two numbers (x, y) [m]; found {value!r}"
        ) from err
    if len(pair) != 2:
        raise FormatError(f"{name}: expected two numbers (x, y) [m]; found {value!r}")
    if not all(math.isfinite(v) for v in pair):
        raise FormatError(f"{name}: expected finite values [m]; found {pair}")
    return pair  # type: ignore[return-value]


def _positive_float(name: str, value: Any, unit: str) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError) as err:
        raise FormatError(
            f"{name}: expected a number [{unit}]; found {value!r}"
        ) from err
    if not math.isfinite(out) or out <= 0:
        raise FormatError(f"{name}: expected a finite value > 0 [{unit}]; found {out}")
    return out


def check_p0c(p0c: float, species: str, where: str = "p0c") -> None:
    """Refuse a reference momentum far below the particle's rest energy.

    Args:
        p0c: Reference momentum times c [eV], already checked to be > 0.
        species: ``"electron"``, ``"positron"`` or ``"proton"``.
        where: Field or option named in the message.

    Raises:
        FormatError: if ``p0c < MIN_BETA_GAMMA * m c^2`` (a unit error: p0c is
            in eV).
    """
    if species not in SPECIES:
        return  # reported by the species check
    low = MIN_BETA_GAMMA * Species.from_name(species).mass_ev
    if not p0c >= low:
        raise FormatError(
            f"{where}: expected >= {low:g} eV for {species}s (p0c / (m c^2) >= "
            f"{MIN_BETA_GAMMA:g}); found {p0c:g} eV (p0c is in eV: 43.36 MeV is "
            "43.36e6)"
        )


def _check_p0c_max(p0c: float, where: str) -> None:
    """Refuse a dataset's ``p0c`` above :data:`MAX_P0C` (a unit error)."""
    if not p0c <= MAX_P0C:
        raise FormatError(
            f"{where}: expected <= {MAX_P0C:g} eV (1 PeV); found {p0c:g} eV (p0c is "
            "in eV: 43.36 MeV is 43.36e6)"
        )


def _is_real_number(value: Any) -> bool:
    """Whether ``value`` is a real number (int or float; not bool, str, None)."""
    return isinstance(value, int | float | np.integer | np.floating) and not (
        isinstance(value, bool | np.bool_)
    )


def _validate_spec(spec: list[dict]) -> dict[str, dict]:
    """Check the beamline element list; return elements by name."""
    if not isinstance(spec, list) or not spec:
        raise FormatError(
            f"beamline: expected a non-empty list of element dicts; found {spec!r}"
        )
    by_name: dict[str, dict] = {}
    for i, element in enumerate(spec):
        if not isinstance(element, dict):
            raise FormatError(f"beamline[{i}]: expected a dict; found {element!r}")
        for key in ("type", "name"):
            if not isinstance(element.get(key), str) or not element[key]:
                raise FormatError(
                    f"beamline[{i}]: expected a non-empty string field {key!r}; "
                    f"found {element!r}"
                )
        if element["name"] in by_name:
            raise FormatError(
                f"beamline[{i}]: duplicate element name {element['name']!r}"
            )
        by_name[element["name"]] = element
        cls = ELEMENT_TYPES.get(element["type"])
        scalar = () if cls is None or cls.__name__ == "LinearMap" else cls.param_names
        for key in scalar:
            if key in element and not _is_real_number(element[key]):
                raise FormatError(
                    f"beamline[{i}] ({element['type']} {element['name']!r}).{key}: "
                    f"expected a real number; found {type(element[key]).__name__} "
                    f"{element[key]!r}"
                )
    try:
        Beamline.from_spec(spec)
    except (ValueError, TypeError) as err:
        raise FormatError(f"beamline: {err}") from err
    screens = [e["name"] for e in spec if e["type"] == "Screen"]
    if len(screens) != 1:
        raise FormatError(
            f"beamline: expected exactly one element of type 'Screen'; found "
            f"{len(screens)} ({screens})"
        )
    if spec[-1]["type"] != "Screen":
        raise FormatError(
            f"beamline: the Screen {screens[0]!r} must be the last element (the "
            f"beamline ends at the screen); found {spec[-1]['type']} "
            f"{spec[-1]['name']!r} after it"
        )
    for i, element in enumerate(spec):
        for key, value in element.items():
            limit = PARAMETER_LIMITS.get(key)
            if limit is None or isinstance(value, bool):
                continue
            try:
                big = float(np.max(np.abs(np.asarray(value, dtype=np.float64))))
            except (TypeError, ValueError):
                continue  # Beamline.from_spec above reports non-numbers
            if not big <= limit:
                unit = PARAMETER_UNITS.get(key, ("(SI)",))[0]
                found = f"{value!r}" if np.ndim(value) == 0 else f"an entry {big:g}"
                raise FormatError(
                    f"beamline[{i}] ({element['type']} {element['name']!r}).{key}: "
                    f"expected |value| <= {limit:g} {unit}; found {found} (a unit or "
                    "typing error?)"
                )
    return by_name


def _validate_settings_names(
    names: list[str], units: list[str], elements: dict[str, dict], p: int
) -> None:
    if len(names) != p:
        raise FormatError(
            f"settings.names: expected {p} names (one per settings column); "
            f"found {len(names)}: {names}"
        )
    if len(units) != p:
        raise FormatError(
            f"settings.units: expected {p} units (one per settings column); "
            f"found {len(units)}: {units}"
        )
    if len(set(names)) != len(names):
        raise FormatError(f"settings.names: duplicate names in {names}")
    for name, unit in zip(names, units, strict=True):
        element, _, parameter = name.partition(".")
        if not element or not parameter or "." in parameter:
            raise FormatError(
                f"settings.names: expected 'ELEMENT.parameter' (e.g. 'Q1.k1'); "
                f"found {name!r}"
            )
        if element not in elements:
            raise FormatError(
                f"settings.names: {name!r} names element {element!r}, which is not "
                f"in the beamline (elements: {list(elements)})"
            )
        params = list(ELEMENT_TYPES[elements[element]["type"]].param_names)
        if parameter not in params:
            raise FormatError(
                f"settings.names: {name!r} names parameter {parameter!r}, which "
                f"element {element!r} of the beamline does not have (parameters: "
                f"{params})"
            )
        allowed = PARAMETER_UNITS.get(parameter)
        if allowed is not None and unit not in allowed:
            raise FormatError(
                f"settings.units: {name!r} must be in {allowed[0]!r}; found {unit!r}"
            )


def check_setting_limits(names: Sequence[str], settings: Tensor) -> None:
    """Refuse settings beyond :data:`PARAMETER_LIMITS` (one line naming the value).

    Args:
        names: Scanned ``"ELEMENT.parameter"`` names, one per column.
        settings: Settings ``(K, P)``.

    Raises:
        FormatError: naming the parameter, the value and the setting index.
    """
    for p, name in enumerate(names):
        limit = PARAMETER_LIMITS.get(name.partition(".")[2])
        if limit is None or settings.shape[0] == 0:
            continue
        column = settings[:, p].abs()
        if bool((column > limit).any()):
            k = int(torch.argmax(column))
            raise FormatError(
                f"settings: {name!r} = {float(settings[k, p]):g} at setting {k}; "
                f"expected |value| <= {limit:g} "
                f"{PARAMETER_UNITS[name.partition('.')[2]][0]} (a unit or typing "
                "error?)"
            )


def _check_setting_signs(
    names: Sequence[str], settings: Tensor, elements: dict[str, dict]
) -> None:
    """Refuse negative settings of parameters the element requires >= 0."""
    for p, name in enumerate(names):
        element, _, parameter = name.partition(".")
        cls = ELEMENT_TYPES[elements[element]["type"]]
        unit = dict(cls.nonnegative_params).get(parameter)
        if unit is None or settings.shape[0] == 0:
            continue
        column = settings[:, p]
        if bool((column < 0).any()):
            k = int(torch.argmin(column))
            raise FormatError(
                f"settings: {name!r} = {float(column[k]):g} at setting {k}; "
                f"expected >= 0 {unit} ({parameter} of {cls.__name__} {element!r})"
            )


#: Largest float32 number (images are stored and computed in float32).
FLOAT32_MAX = float(torch.finfo(torch.float32).max)
#: Smallest normal float32 number; below it float32 numbers are subnormal.
FLOAT32_TINY = float(torch.finfo(torch.float32).tiny)
#: Smallest image peak accepted: float32 resolves pixels down to its epsilon
#: (1.2e-7) times the peak, and those must stay normal numbers (subnormal ones
#: lose digits, and CPUs compute with them up to 40x slower).
MIN_IMAGE_PEAK = FLOAT32_TINY / float(torch.finfo(torch.float32).eps)


def _first(mask: Tensor) -> str:
    """``"setting k, shot s"`` of the first True of a ``(K, S, ...)`` mask."""
    k, s = (int(v) for v in torch.nonzero(mask)[0][:2])
    return f"setting {k}, shot {s}"


def _float32_images(images: Tensor) -> Tensor:
    """``images`` as float32, their values checked in their own dtype first.

    Refused (FormatError): float16 infinities (values beyond float16's largest,
    65504, when the images were stored), values or image sums beyond float32's
    largest (they would become inf), and images whose peak is below
    :data:`MIN_IMAGE_PEAK` (their pixels would be subnormal float32 numbers).
    Subnormal pixels of an image with a normal peak (below float32's
    resolution relative to it) are set to 0. Every other check is done on the
    float32 images by the dataset.
    """
    if images.ndim != 4 or images.numel() == 0 or not images.is_floating_point():
        return images.to(torch.float32)  # the shape and dtype checks name it
    if images.dtype == torch.float16 and bool(torch.isinf(images).any()):
        where = _first(torch.isinf(images))
        raise FormatError(
            f"images: float16 values of inf ({int(torch.isinf(images).sum())}, first "
            f"at {where}): float16 holds at most 65504, so these overflowed when the "
            "images were stored; store them as float32"
        )
    wide = images.to(torch.float64) if images.dtype != torch.float64 else images
    finite = torch.isfinite(wide)
    mag = torch.where(finite, wide.abs(), torch.zeros((), dtype=wide.dtype))
    big = mag > FLOAT32_MAX
    if bool(big.any()):
        raise FormatError(
            f"images: {int(big.sum())} value(s) beyond float32's largest number "
            f"{FLOAT32_MAX:.4g} (up to {float(mag[big].max()):.4g}, first at "
            f"{_first(big)}); "
            "images are computed in float32: scale them down (each image is "
            "normalised to unit sum, so a common factor changes nothing)"
        )
    total = mag.sum((-2, -1))
    if bool((total > FLOAT32_MAX).any()):
        over = total > FLOAT32_MAX
        raise FormatError(
            f"images: image of {_first(over)} sums to {float(total[over].max()):.4g}, "
            f"beyond float32's largest number {FLOAT32_MAX:.4g}; scale the images "
            "down (each is normalised to unit sum, so a common factor changes nothing)"
        )
    peak = mag.amax((-2, -1))
    faint = (peak > 0) & (peak < MIN_IMAGE_PEAK)
    if bool(faint.any()):
        raise FormatError(
            f"images: image of {_first(faint)} peaks at "
            f"{float(peak[faint].min()):.4g}, "
            f"below {MIN_IMAGE_PEAK:.3g} (float32 numbers below {FLOAT32_TINY:.3g} are "
            "subnormal: they lose digits and slow computation); scale the images up "
            "(each is normalised to unit sum, so a common factor changes nothing)"
        )
    out = images.to(torch.float32)
    return torch.where(out.abs() < FLOAT32_TINY, torch.zeros((), dtype=out.dtype), out)


def _validate(ds: QuadScanDataset) -> None:
    images, settings = ds.images, ds.settings
    if not images.is_floating_point():
        raise FormatError(
            f"images: expected a float tensor; found dtype {images.dtype}"
        )
    if images.ndim != 4:
        raise FormatError(
            f"images: expected 4 dimensions (K, S, H, W); found shape "
            f"{tuple(images.shape)}"
            + ("; add a shots axis with images[:, None]" if images.ndim == 3 else "")
        )
    if min(images.shape) < 1:
        raise FormatError(
            f"images: expected no empty axis; found {tuple(images.shape)}"
        )
    if min(images.shape[2:]) < MIN_PIXELS:
        raise FormatError(
            f"images: expected a screen of at least {MIN_PIXELS} x {MIN_PIXELS} "
            f"pixels (H, W); found {tuple(images.shape[2:])}"
        )
    if settings.ndim != 2:
        raise FormatError(
            f"settings: expected 2 dimensions (K, P); found shape "
            f"{tuple(settings.shape)}"
        )
    if settings.shape[0] != images.shape[0]:
        raise FormatError(
            f"settings: expected {images.shape[0]} rows (one per image setting K of "
            f"images {tuple(images.shape)}); found shape {tuple(settings.shape)}"
        )
    if settings.shape[1] < 1:
        raise FormatError("settings: expected at least one scanned parameter (P >= 1)")
    bad = ~torch.isfinite(images)
    if bool(bad.any()):
        k, s = (int(v) for v in torch.nonzero(bad)[0][:2])
        raise FormatError(
            f"images: expected finite values; found {int(bad.sum())} NaN/inf "
            f"values (first at setting {k}, shot {s})"
        )
    bad = ~torch.isfinite(settings)
    if bool(bad.any()):
        k = int(torch.nonzero(bad)[0][0])
        raise FormatError(
            f"settings: expected finite values; found NaN/inf at setting {k}"
        )
    empty = (images == 0).flatten(2).all(dim=-1)
    if bool(empty.any()):
        k, s = (int(v) for v in torch.nonzero(empty)[0])
        raise FormatError(
            f"images: image of setting {k} (shot {s}) is all zero; "
            f"{int(empty.sum())} all-zero image(s) in total"
        )
    # background-subtracted images may dip below 0 by their noise; a pixel more
    # negative than the image's brightest one is not noise (sign or offset error)
    low = images.amin(dim=(-2, -1))
    deep = low < -images.amax(dim=(-2, -1))
    if bool(deep.any()):
        k, s = (int(v) for v in torch.nonzero(deep)[0])
        raise FormatError(
            f"images: image of setting {k} (shot {s}) has a pixel of "
            f"{float(low[k, s]):g}, more negative than its brightest pixel is "
            f"bright ({float(images[k, s].max()):g}); background-subtracted images "
            "may dip below 0 by their noise, not by more than the signal "
            f"({int(deep.sum())} such image(s))"
        )
    sums = images.sum(dim=(-2, -1), dtype=torch.float64)
    if bool((sums <= 0).any()):
        k, s = (int(v) for v in torch.nonzero(sums <= 0)[0])
        raise FormatError(
            f"images: image of setting {k} (shot {s}) sums to {float(sums[k, s]):g}; "
            "expected a positive total intensity (over-subtracted background?)"
        )
    for axis, v in zip("xy", ds.pixel_size, strict=True):
        if not MIN_PIXEL_SIZE <= v <= MAX_PIXEL_SIZE:
            raise FormatError(
                f"screen.pixel_size: expected (x, y) > 0 and <= {MAX_PIXEL_SIZE:g} m, "
                f"at least {MIN_PIXEL_SIZE:g} m (sizes are in m: 20 um is 2e-05); "
                f"found {ds.pixel_size} (pixel_size_{axis} = {v:g})"
            )
    if not all(abs(v) <= MAX_CENTER for v in ds.center):
        raise FormatError(
            f"screen.center: expected |x|, |y| <= {MAX_CENTER:g} m; found {ds.center}"
        )
    res = ds.resolution_pixels
    if res is not None and not (
        isinstance(res, int | float)
        and not isinstance(res, bool)
        and math.isfinite(res)
        and 0 <= res <= MAX_RESOLUTION_PIXELS
    ):
        raise FormatError(
            "screen.resolution_pixels: expected a number in "
            f"[0, {MAX_RESOLUTION_PIXELS:g}] pixels; found {res!r}"
        )
    if ds.species not in SPECIES:
        raise FormatError(f"species: expected one of {SPECIES}; found {ds.species!r}")
    check_p0c(ds.p0c, ds.species)
    _check_p0c_max(ds.p0c, "p0c")
    elements = _validate_spec(ds.beamline_spec)
    _validate_settings_names(
        ds.setting_names, ds.setting_units, elements, int(settings.shape[1])
    )
    check_setting_limits(ds.setting_names, settings)
    _check_setting_signs(ds.setting_names, settings, elements)
    gt = ds.ground_truth
    if gt is not None:
        if gt.ndim != 2 or gt.shape[-1] != 6 or gt.shape[0] < 1:
            raise FormatError(
                f"ground_truth: expected shape (N, 6) with N >= 1; found "
                f"{tuple(gt.shape)}"
            )
        if not gt.is_floating_point():
            raise FormatError(
                f"ground_truth: expected a float tensor; found dtype {gt.dtype}"
            )
        if not bool(torch.isfinite(gt).all()):
            raise FormatError(
                "ground_truth: expected finite coordinates; found NaN/inf"
            )
    if not isinstance(ds.metadata, dict):
        raise FormatError(f"metadata: expected a dict; found {type(ds.metadata)}")
    _check_preprocessing(ds.metadata, "metadata")


# ---------------------------------------------------------------------- reading
def _as_str(value: Any, where: str) -> str:
    """An HDF5 text attribute as ``str`` (UTF-8 bytes accepted)."""
    if isinstance(value, np.ndarray) and value.shape == ():
        value = value.item()
    if isinstance(value, bytes | np.bytes_):
        try:
            return bytes(value).decode("utf-8")
        except UnicodeDecodeError as err:
            raise FormatError(
                f"{where}: expected UTF-8 text; found bytes that are not UTF-8 "
                f"({err.reason} at byte {err.start})"
            ) from err
    if isinstance(value, str):
        return str(value)
    raise FormatError(
        f"{where}: expected a text attribute; found {type(value).__name__} {value!r}"
    )


def _attr(obj: h5py.HLObject, key: str, where: str) -> Any:
    if key not in obj.attrs:
        raise FormatError(
            f"{where}: missing attribute {key!r} (found: {sorted(obj.attrs)})"
        )
    try:
        return obj.attrs[key]
    except (OSError, TypeError, ValueError) as err:
        raise FormatError(f"{where}.{key}: unreadable attribute ({err})") from err


def _text_attr(obj: h5py.HLObject, key: str, where: str) -> str:
    return _as_str(_attr(obj, key, where), f"{where}.{key}")


def _json_attr(obj: h5py.HLObject, key: str, where: str) -> Any:
    raw = _text_attr(obj, key, where)
    try:
        return json.loads(raw)
    except json.JSONDecodeError as err:
        raise FormatError(
            f"{where}.{key}: invalid JSON ({err.msg} at char {err.pos}); "
            f"found {raw[:80]!r}"
        ) from err


def _member(group: h5py.Group, key: str, where: str) -> h5py.HLObject | None:
    """``group[key]``, None if absent; a link that cannot be followed (an
    external link to a missing file, a dangling soft link) is a FormatError."""
    if key not in group:
        # "in" is False for a dangling soft or external link: tell it apart
        if group.get(key, getlink=True) is None:
            return None
    try:
        return group[key]
    except (KeyError, OSError) as err:
        link = group.get(key, getlink=True)
        target = ""
        if isinstance(link, h5py.ExternalLink):
            target = f" (external link to {link.filename}:{link.path})"
        elif isinstance(link, h5py.SoftLink):
            target = f" (soft link to {link.path})"
        raise FormatError(
            f"{where}{key}: cannot be opened{target}: {err}; store the data in the "
            "file or make the link's target readable"
        ) from err


def _dataset(group: h5py.Group, key: str, where: str) -> h5py.Dataset:
    obj = _member(group, key, where)
    if not isinstance(obj, h5py.Dataset):
        raise FormatError(f"{where}{key}: missing dataset (found: {sorted(group)})")
    return obj


def _float_attr(obj: h5py.HLObject, key: str, where: str) -> float:
    value = _attr(obj, key, where)
    array = np.asarray(value)
    if array.dtype.kind not in "iuf" or array.size != 1:
        raise FormatError(
            f"{where}.{key}: expected a number; found {type(value).__name__} {value!r}"
        )
    out = float(array.item())
    if not math.isfinite(out):
        raise FormatError(f"{where}.{key}: expected a finite number; found {out}")
    return out


def _read_version(h5: h5py.File) -> int:
    """The checked ``format`` and integer ``format_version`` of an open file."""
    fmt = _text_attr(h5, "format", "/")
    if fmt != FORMAT_NAME:
        raise FormatError(f"/.format: expected {FORMAT_NAME!r}; found {fmt!r}")
    raw = _attr(h5, "format_version", "/")
    array = np.asarray(raw)
    if array.dtype.kind not in "iuf" or array.size != 1:
        raise FormatError(
            f"/.format_version: expected an integer; found {type(raw).__name__} {raw!r}"
        )
    value = array.item()
    number = float(value)
    if not number.is_integer():
        raise FormatError(
            f"/.format_version: expected an integer (1 or 2); found {value!r}"
        )
    version = int(number)
    if version not in READ_VERSIONS:
        raise FormatError(
            f"/.format_version: this reader reads versions "
            f"{', '.join(map(str, READ_VERSIONS))}; found {version}"
        )
    return version


def _string_list(value: Any, where: str) -> list[str]:
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise FormatError(f"{where}: expected a JSON list of strings; found {value!r}")
    return value


@dataclass
class _Root:
    """Beam-level fields of a quad-scan file (shared by all of its scans)."""

    p0c: float
    species: str
    ground_truth: Tensor | None
    metadata: dict[str, Any]


def _read_root(h5: h5py.File) -> _Root:
    p0c = _float_attr(h5, "p0c", "/")
    species = _text_attr(h5, "species", "/")
    if species not in SPECIES:
        raise FormatError(f"/.species: expected one of {SPECIES}; found {species!r}")
    # before the ground truth, whose conversion from cheetah coordinates needs it
    if not p0c > 0:
        raise FormatError(f"/.p0c: expected a finite value > 0 [eV]; found {p0c:g}")
    check_p0c(p0c, species, "/.p0c")
    _check_p0c_max(p0c, "/.p0c")
    metadata: dict[str, Any] = {}
    if "metadata" in h5.attrs:
        metadata = _json_attr(h5, "metadata", "/")
        if not isinstance(metadata, dict):
            raise FormatError(
                f"/.metadata: expected a JSON object; found {type(metadata).__name__}"
            )
        _check_preprocessing(metadata, "/.metadata")
    if "description" in h5.attrs:
        metadata["description"] = _text_attr(h5, "description", "/")
    ground_truth = None
    truth = _member(h5, "ground_truth", "/")
    if truth is not None:
        particles = (
            _member(truth, "particles", "/ground_truth/")
            if isinstance(truth, h5py.Group)
            else None
        )
        if particles is None:
            raise FormatError("/ground_truth: missing dataset 'particles'")
        ground_truth = _read_ground_truth(particles, p0c, species)
    return _Root(p0c, species, ground_truth, metadata)


def _read_ground_truth(data: h5py.Dataset, p0c: float, species: str) -> Tensor:
    where = "/ground_truth/particles"
    coords = _json_attr(data, "coordinates", where)
    try:
        values = torch.from_numpy(np.asarray(data[()], dtype=np.float64))
    except (TypeError, ValueError) as err:
        raise FormatError(f"{where}: expected float numbers ({err})") from err
    if values.ndim != 2 or values.shape[-1] != 6:
        raise FormatError(
            f"{where}: expected shape (N, 6); found {tuple(values.shape)}"
        )
    if not isinstance(coords, list):
        coords = [coords]
    if tuple(coords) == BMAD_COORDINATES:
        return values
    if tuple(coords) == CHEETAH_COORDINATES:
        return cheetah_to_bmad(values, p0c, Species.from_name(species))
    raise FormatError(
        f"{where}.coordinates: expected {list(BMAD_COORDINATES)} (Bmad) or "
        f"{list(CHEETAH_COORDINATES)} (cheetah); found {coords}"
    )


def _read_array(group: h5py.Group, key: str, where: str, dtype: Any) -> Tensor:
    data = _dataset(group, key, where)
    if data.dtype.kind not in "iuf":
        raise FormatError(
            f"{where}{key}: expected real numbers (integer or float); found dtype "
            f"{data.dtype}"
        )
    if dtype is None:  # the stored numbers, for checks before a cast
        kind, size = data.dtype.kind, data.dtype.itemsize
        dtype = data.dtype if kind == "f" and size in (2, 4, 8) else np.float64
        dtype = np.dtype(dtype).newbyteorder("=")
    try:
        return torch.from_numpy(np.asarray(data[()], dtype=dtype))
    except (TypeError, ValueError) as err:
        raise FormatError(
            f"{where}{key}: expected real numbers; found dtype {data.dtype} ({err})"
        ) from err


def _read_scan(group: h5py.Group, where: str, root: _Root) -> QuadScanDataset:
    """One scan (beamline, images, settings, screen) from ``group``.

    ``where`` is the group's path with a trailing slash (``"/"`` for version 1,
    ``"/scans/NAME/"`` for version 2); errors name the field by that path.
    """
    spec = _json_attr(group, "beamline", where.rstrip("/") or "/")
    images = _read_array(group, "images", where, None)  # checked, then float32
    settings = _read_array(group, "settings", where, np.float64)
    settings_ds = _dataset(group, "settings", where)
    names = _string_list(
        _json_attr(settings_ds, "names", f"{where}settings"),
        f"{where}settings.names",
    )
    units = _string_list(
        _json_attr(settings_ds, "units", f"{where}settings"),
        f"{where}settings.units",
    )
    screen = _member(group, "screen", where)
    if not isinstance(screen, h5py.Group):
        raise FormatError(f"{where}screen: missing group (found: {sorted(group)})")
    pixel_size = tuple(
        _float_attr(screen, f"pixel_size_{a}", f"{where}screen") for a in "xy"
    )
    center = tuple(_float_attr(screen, f"center_{a}", f"{where}screen") for a in "xy")
    resolution = (
        _float_attr(screen, "resolution_pixels", f"{where}screen")
        if "resolution_pixels" in screen.attrs
        else None
    )
    try:
        return QuadScanDataset(
            images=images,
            settings=settings,
            setting_names=names,
            setting_units=units,
            p0c=root.p0c,
            species=root.species,
            beamline_spec=spec,
            pixel_size=pixel_size,  # type: ignore[arg-type]
            center=center,  # type: ignore[arg-type]
            ground_truth=root.ground_truth,
            metadata=root.metadata,
            resolution_pixels=resolution,
        )
    except FormatError as err:
        # container messages name the field ("settings.names: ..."); add the path
        raise FormatError(f"{where}{err}") from err


def open_quad_scan(path: str | os.PathLike) -> h5py.File:
    """Open a quad-scan file for reading, with clear errors.

    Raises:
        FileNotFoundError: if ``path`` does not exist.
        FormatError: if it is not a readable HDF5 file.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"quad-scan file not found: {path}")
    if path.is_dir():
        raise FormatError(f"{path}: is a directory, not a quad-scan file")
    try:
        return h5py.File(path, "r")
    except OSError as err:
        condition = os_condition(err)  # locked, no permission: not the file's fault
        if condition is not None:
            raise FormatError(f"{path}: cannot open it: {condition}") from err
        raise FormatError(f"{path}: not a readable HDF5 file ({err})") from err


def read_quad_scan(path: str | os.PathLike) -> QuadScanDataset:
    """Read a quad-scan HDF5 file holding one scan (version 1, or 2 with one scan).

    For files with several scans use :func:`diffaccel.data.read_scans`.

    Args:
        path: File to read.

    Returns:
        The validated dataset. A ground truth stored in cheetah coordinates
        (x, px, y, py, tau, delta) is converted to Bmad coordinates. The root
        attributes ``description`` and ``metadata`` (JSON) go to ``metadata``.

    Raises:
        FileNotFoundError: if ``path`` does not exist.
        FormatError: naming the file and the attribute or dataset that is
            missing or invalid, or a version-2 file with several scans.
    """
    _, scans, _ = read_file_scans(path, one=True)
    return next(iter(scans.values()))


def read_file_scans(
    path: str | os.PathLike, *, one: bool = False, single_name: str = ""
) -> tuple[int, dict[str, QuadScanDataset], dict]:
    """The scans of a quad-scan file of any version (the readers' common part).

    Args:
        path: File to read.
        one: Refuse a version-2 file with more than one scan.
        single_name: Name given to the one scan of a version-1 file.

    Returns:
        ``(format_version, {name: scan} in file order, root metadata)``.

    Raises:
        FileNotFoundError: if ``path`` does not exist.
        FormatError: ``"PATH: field: problem"``.
    """
    path = Path(path)
    with open_quad_scan(path) as h5:
        try:
            version = _read_version(h5)
            _refuse_other_version_fields(h5, version)
            root = _read_root(h5)
            if version == 1:
                scan = _read_scan(h5, "/", root)
                _warn_repeated_settings(scan, path, "/")
                return version, {single_name: scan}, root.metadata
            names = scan_names(h5)
            if one and len(names) != 1:
                raise FormatError(
                    f"/scans: holds {len(names)} scans ({names}); read the file "
                    "with diffaccel.data.read_scans"
                )
            scans = {
                name: _read_scan(h5["scans"][name], f"/scans/{name}/", root)
                for name in names
            }
            for name, scan in scans.items():
                _warn_repeated_settings(scan, path, f"/scans/{name}/")
            return version, scans, root.metadata
        except FormatError as err:
            raise FormatError(f"{path}: {err}") from err


def _warn_repeated_settings(ds: QuadScanDataset, path: Path, where: str) -> None:
    """Warn when settings rows repeat (shots of one setting belong on axis S).

    Repeated rows can be legitimate (a setting revisited later in the scan, e.g.
    to see hysteresis), so this warns instead of refusing.
    """
    _, inverse, counts = torch.unique(
        ds.settings, dim=0, return_inverse=True, return_counts=True
    )
    if bool((counts == 1).all()):
        return
    groups = [
        torch.nonzero(inverse == g).flatten().tolist()
        for g in torch.nonzero(counts > 1).flatten().tolist()
    ]
    warnings.warn(
        f"{path}: {where}settings: rows {groups} hold the same setting "
        f"({ds.setting_names}); several shots of one setting belong on the shots "
        "axis S of images (K, S, H, W), unless the setting was revisited on purpose",
        stacklevel=4,
    )


#: Root fields of one format version that the other version does not have.
_V1_ONLY = ("images", "settings", "screen")


def _refuse_other_version_fields(h5: h5py.File, version: int) -> None:
    """Refuse root fields of the other format version (they would be ignored).

    Raises:
        FormatError: naming the field, e.g. a version-2 file with ``/images``.
    """
    if version == 1:
        if "scans" in h5:
            raise FormatError(
                "/scans: a format_version 1 file holds its scan at the root; "
                "/scans is version 2 (set format_version 2 or remove it)"
            )
        return
    for key in _V1_ONLY:
        if key in h5:
            raise FormatError(
                f"/{key}: a format_version 2 file keeps {key} under "
                f"/scans/<name>/; this root-level {key} would be ignored"
            )
    if "beamline" in h5.attrs:
        raise FormatError(
            "/.beamline: a format_version 2 file keeps the beamline in "
            "/scans/<name>.beamline; this root attribute would be ignored"
        )


def scan_names(h5: h5py.File) -> list[str]:
    """Names of the scans of an open version-2 file, in file order.

    Raises:
        FormatError: if ``/scans`` is missing, empty or holds a non-group.
    """
    if "scans" not in h5 or not isinstance(h5["scans"], h5py.Group):
        raise FormatError(f"/scans: missing group (found: {sorted(h5)})")
    scans = h5["scans"]
    names = list(scans)
    if not names:
        raise FormatError("/scans: expected at least one scan group; found none")
    for name in names:
        if not isinstance(scans[name], h5py.Group):
            raise FormatError(f"/scans/{name}: expected a group; found a dataset")
    return names


# ---------------------------------------------------------------------- writing
def _json_dumps(value: Any, field_name: str) -> str:
    try:
        return json.dumps(value)
    except (TypeError, ValueError) as err:
        raise FormatError(f"{field_name}: not JSON-serialisable ({err})") from err


def write_root(h5: h5py.File, dataset: QuadScanDataset, version: int) -> None:
    """Root attributes and ground truth of ``dataset`` into an open file."""
    metadata = dict(dataset.metadata)
    description = metadata.pop("description", None)
    h5.attrs["format"] = FORMAT_NAME
    h5.attrs["format_version"] = np.int64(version)
    h5.attrs[H5_ATTRIBUTE] = h5_mark()  # what --force may replace
    h5.attrs["p0c"] = np.float64(dataset.p0c)
    h5.attrs["species"] = dataset.species
    h5.attrs["metadata"] = _json_dumps(metadata, "metadata")
    if description is not None:
        h5.attrs["description"] = str(description)
    if dataset.ground_truth is not None:
        gt = h5.create_group("ground_truth").create_dataset(
            "particles",
            data=dataset.ground_truth.detach().cpu().double().numpy(),
        )
        gt.attrs["coordinates"] = json.dumps(list(BMAD_COORDINATES))
        gt.attrs["convention"] = BMAD_CONVENTION


def write_scan(group: h5py.Group, dataset: QuadScanDataset) -> None:
    """Beamline, images, settings and screen of one scan into ``group``."""
    group.attrs["beamline"] = _json_dumps(dataset.beamline_spec, "beamline")
    group.create_dataset(
        "images",
        data=dataset.images.detach().cpu().numpy().astype(np.float32),
        compression="gzip",
        compression_opts=4,
        shuffle=True,
    )
    settings = group.create_dataset(
        "settings", data=dataset.settings.detach().cpu().numpy()
    )
    settings.attrs["names"] = json.dumps(dataset.setting_names)
    settings.attrs["units"] = json.dumps(dataset.setting_units)
    screen = group.create_group("screen")
    screen.attrs["pixel_size_x"] = np.float64(dataset.pixel_size[0])
    screen.attrs["pixel_size_y"] = np.float64(dataset.pixel_size[1])
    screen.attrs["center_x"] = np.float64(dataset.center[0])
    screen.attrs["center_y"] = np.float64(dataset.center[1])
    if dataset.resolution_pixels is not None:
        screen.attrs["resolution_pixels"] = np.float64(dataset.resolution_pixels)


def write_quad_scan(
    dataset: QuadScanDataset, path: str | os.PathLike, overwrite: bool = False
) -> Path:
    """Write a dataset as a quad-scan HDF5 file (format version 1), atomically.

    The file is written to a temporary file in the same directory and moved into
    place with ``os.replace``, so readers never see a half-written file. The
    ground truth is stored in Bmad coordinates; ``metadata`` (minus
    ``description``, which becomes its own attribute) is stored as JSON.
    Several scans: :func:`diffaccel.data.write_scans` (version 2).

    Args:
        dataset: The dataset; it is validated again before writing.
        path: Destination file.
        overwrite: Replace an existing file at ``path``.

    Returns:
        The path written.

    Raises:
        FileExistsError: if ``path`` exists and ``overwrite`` is false.
        FormatError: if the dataset is invalid or its metadata/beamline are not
            JSON-serialisable.
    """
    if not isinstance(dataset, QuadScanDataset):
        raise TypeError(f"dataset: expected a QuadScanDataset; got {type(dataset)}")
    _validate(dataset)
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(
            f"{path} exists; pass overwrite=True (CLI: --force) to replace it"
        )
    _json_dumps(dataset.beamline_spec, "beamline")
    _json_dumps(dataset.metadata, "metadata")
    path.parent.mkdir(parents=True, exist_ok=True)

    def _write(tmp: Path) -> None:
        with h5py.File(tmp, "w") as h5:
            write_root(h5, dataset, 1)
            write_scan(h5, dataset)

    return atomic_write(path, _write)
