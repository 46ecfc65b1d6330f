"""Beamlines to and from cheetah ``Segment``s and the lattice files cheetah reads.

cheetah-accelerator (GPL-3.0) is an optional dependency (``pip install
diffaccel[cheetah]``), imported only inside these functions. Lattice files are
read by cheetah's own parsers and converters (Bmad, elegant, LatticeJSON), and
Ocelot cells (Python objects) by cheetah's Ocelot converter;
where a converter loses information this module maps the element itself from
cheetah's parsed attributes (see :func:`elements_from_lattice`).

Element correspondence (cheetah 0.8.4 -> diffaccel):

=============================  ===========================================
``Drift``                      ``Drift``
``Quadrupole``                 ``Quadrupole`` (misalignment -> ``dx, dy``)
``Dipole``, ``RBend``          ``Dipole`` (no ``k1``; linear fringe kept)
``TransverseDeflectingCavity`` ``TransverseDeflectingCavity`` (phase x 2 pi)
``Solenoid``                   ``Solenoid`` (``ks = 2 k``)
``Sextupole``                  ``Sextupole``
``Cavity``                     ``RFCavity`` (only with zero reference gain)
``Screen``                     ``Screen`` (resolution, pixel size, binning)
``CustomTransferMap``          ``LinearMap`` (needs ``p0c``)
``Marker``, ``BPM``            zero-length ``Drift`` (or ``Screen``, see
                               ``screens``)
=============================  ===========================================

Anything else (correctors, apertures, undulators, space charge, a dipole with
``k1``, ...) is refused with one error naming every such
element, unless ``approximate`` is ``"drift"`` (a drift of the same length) or
``"linear"`` (cheetah's first-order map of the element at ``p0c``).
"""

from __future__ import annotations

import contextlib
import math
import re
import warnings
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from diffaccel.dynamics.coordinates import bmad_to_cheetah, p0c_to_energy
from diffaccel.dynamics.elements.dipole import Dipole
from diffaccel.dynamics.elements.drift import Drift
from diffaccel.dynamics.elements.element import Element
from diffaccel.dynamics.elements.linear_map import LinearMap
from diffaccel.dynamics.elements.quadrupole import Quadrupole
from diffaccel.dynamics.elements.rf_cavity import RFCavity
from diffaccel.dynamics.elements.screen import Screen
from diffaccel.dynamics.elements.sextupole import Sextupole
from diffaccel.dynamics.elements.solenoid import Solenoid
from diffaccel.dynamics.elements.transverse_deflecting_cavity import (
    TransverseDeflectingCavity,
)
from diffaccel.dynamics.species import ELECTRON, Species

__all__ = [
    "APPROXIMATIONS",
    "LATTICE_FORMATS",
    "LatticeConversionWarning",
    "LatticeImportError",
    "elements_from_cheetah",
    "elements_from_lattice",
    "elements_from_ocelot",
    "elements_to_cheetah",
    "lattice_format",
]

#: Values of ``approximate``: a drift of the same length, or the linear map.
APPROXIMATIONS = ("drift", "linear")

#: Lattice formats by file suffix (``format`` overrides the suffix).
LATTICE_FORMATS = {
    ".bmad": "bmad",
    ".lat": "bmad",
    ".lte": "elegant",
    ".ele": "elegant",
    ".json": "latticejson",
}

F64 = torch.float64
_METADATA_KEY = "diffaccel"


class LatticeImportError(ValueError):
    """A lattice or segment that cannot be converted (one-line message)."""


class LatticeConversionWarning(UserWarning):
    """Information a conversion changed, approximated or could not keep."""


def _require_cheetah() -> Any:
    try:
        import cheetah
    except ImportError as err:  # pragma: no cover - the test extra has cheetah
        raise ImportError(
            "Lattice import and cheetah conversion need cheetah-accelerator: "
            "pip install diffaccel[cheetah]"
        ) from err
    return cheetah


def _f(value: Any) -> float:
    """A scalar cheetah attribute as a Python float."""
    t = torch.as_tensor(value)
    if t.numel() != 1:
        raise LatticeImportError(
            "batched cheetah attributes (vectorised segments) are not supported; "
            f"got shape {tuple(t.shape)}"
        )
    return float(t.detach().reshape(()).item())


def _misalignment(element: Any) -> tuple[float, float]:
    m = getattr(element, "misalignment", None)
    if m is None:
        return 0.0, 0.0
    m = torch.as_tensor(m).detach().reshape(-1)
    return float(m[0]), float(m[1])


def _coordinate_jacobian(p0c: float, species: Species) -> Tensor:
    """``d(cheetah coordinates) / d(Bmad coordinates)`` at the reference, 6x6."""
    return torch.autograd.functional.jacobian(
        lambda u: bmad_to_cheetah(u.unsqueeze(0), p0c, species)[0],
        torch.zeros(6, dtype=F64),
    )


def _cheetah_map_to_bmad(r: Tensor, p0c: float, species: Species) -> Tensor:
    """A cheetah affine 7x7 map (tau, delta) as a Bmad (z, pz) affine map."""
    j = torch.eye(7, dtype=F64)
    j[:6, :6] = _coordinate_jacobian(p0c, species)
    return torch.linalg.inv(j) @ r.to(F64) @ j


def _bmad_map_to_cheetah(r: Tensor, p0c: float, species: Species) -> Tensor:
    j = torch.eye(7, dtype=F64)
    j[:6, :6] = _coordinate_jacobian(p0c, species)
    return j @ r.to(F64) @ torch.linalg.inv(j)


def _cheetah_species(species: Species) -> Any:
    cheetah = _require_cheetah()
    names = {(-1, "electron"), (1, "positron"), (1, "proton")}
    for charge, name in names:
        s = cheetah.Species(name)
        if charge == species.charge and math.isclose(
            float(s.mass_eV), species.mass_ev, rel_tol=1e-6
        ):
            return s
    raise LatticeImportError(
        f"no cheetah species for charge {species.charge} e, mass {species.mass_ev} eV"
    )


# ---- cheetah -> diffaccel ---------------------------------------------------------


def _why_unsupported(element: Any, cheetah: Any) -> str | None:
    """Why ``element`` has no exact diffaccel counterpart (None if it has one)."""
    kind = type(element).__name__
    if isinstance(element, cheetah.Dipole):
        if _f(element.k1) != 0:
            return "combined-function dipole (k1 != 0)"
        return None
    if isinstance(element, cheetah.TransverseDeflectingCavity):
        if _misalignment(element) != (0.0, 0.0):
            return "misaligned deflecting cavity"
        if int(element.num_steps) != 1:
            return f"deflecting cavity with num_steps = {element.num_steps}"
        return None
    if isinstance(element, cheetah.Cavity):
        gain = _f(element.voltage) * math.cos(math.radians(_f(element.phase)))
        if abs(gain) > 1e-9 * max(abs(_f(element.voltage)), 1.0):
            return (
                f"accelerating cavity changes the reference energy by {gain:.6g} eV "
                "(diffaccel's RFCavity keeps the reference momentum)"
            )
        return None
    known = (
        cheetah.Drift,
        cheetah.Quadrupole,
        cheetah.Solenoid,
        cheetah.Sextupole,
        cheetah.Screen,
        cheetah.Marker,
        cheetah.BPM,
        cheetah.CustomTransferMap,
    )
    if isinstance(element, known):
        return None
    return f"no diffaccel element for cheetah {kind}"


def _convert(
    element: Any,
    name: str,
    cheetah: Any,
    p0c: float | None,
    species: Species,
    screens: set[str],
) -> Element:
    """The exact diffaccel counterpart of a supported cheetah element."""
    if isinstance(element, cheetah.Dipole):  # (RBend is a Dipole)
        # a face's fringe integral acts only with a gap (else it is dropped)
        at = element.fringe_at
        entrance = at in ("entrance", "both") and _f(element.gap) != 0
        exit_ = at in ("exit", "both") and _f(element.gap_exit) != 0
        return Dipole(
            name,
            _f(element.length),
            _f(element.angle),
            e1=_f(element.dipole_e1),
            e2=_f(element.dipole_e2),
            tilt=_f(element.tilt),
            hgap=_f(element.gap) / 2 if entrance else 0.0,
            hgapx=_f(element.gap_exit) / 2 if exit_ else 0.0,
            fint=_f(element.fringe_integral) if entrance else 0.0,
            fintx=_f(element.fringe_integral_exit) if exit_ else 0.0,
        )
    if isinstance(element, cheetah.TransverseDeflectingCavity):
        return TransverseDeflectingCavity(
            name,
            _f(element.length),
            _f(element.voltage),
            _f(element.frequency),
            2 * math.pi * _f(element.phase),
            tilt=_f(element.tilt),
        )
    if isinstance(element, cheetah.Cavity):
        if _f(element.voltage) != 0:
            warnings.warn(
                f"{name}: cheetah's Cavity adds transverse (Rosenzweig-Serafini) "
                "focusing that diffaccel's RFCavity (Bmad rfcavity, no transverse "
                "fields) does not have",
                LatticeConversionWarning,
                stacklevel=4,
            )
        return RFCavity(
            name,
            _f(element.length),
            _f(element.voltage) * -float(species.charge) / abs(species.charge),
            _f(element.frequency),
            math.radians(_f(element.phase)) + math.pi / 2,
        )
    if isinstance(element, cheetah.Quadrupole):
        dx, dy = _misalignment(element)
        return Quadrupole(
            name, _f(element.length), _f(element.k1), _f(element.tilt), dx, dy
        )
    if isinstance(element, cheetah.Solenoid):
        dx, dy = _misalignment(element)
        return Solenoid(name, _f(element.length), 2 * _f(element.k), dx, dy)
    if isinstance(element, cheetah.Sextupole):
        dx, dy = _misalignment(element)
        return Sextupole(
            name, _f(element.length), _f(element.k2), _f(element.tilt), dx, dy
        )
    if isinstance(element, cheetah.Screen):
        if element.metadata.get(_METADATA_KEY) == "screen without geometry":
            return Screen(name)
        binning = int(element.binning)
        w, h = (int(n) // binning for n in element.resolution)
        psx, psy = (float(v) * binning for v in element.pixel_size.reshape(-1))
        return Screen(name, (h, w), (psx, psy), _misalignment(element))
    if isinstance(element, cheetah.CustomTransferMap):
        if p0c is None:
            raise LatticeImportError(
                f"{name}: a CustomTransferMap needs p0c (its map is in cheetah's "
                "tau, delta coordinates about a reference energy)"
            )
        r = _cheetah_map_to_bmad(element.predefined_transfer_map, p0c, species)
        return LinearMap(name, r, _f(element.length))
    if isinstance(element, cheetah.Marker | cheetah.BPM):
        return Screen(name) if name in screens else Drift(name, 0.0)
    return Drift(name, _f(element.length))


def _approximation(
    element: Any,
    name: str,
    how: str,
    reason: str,
    p0c: float | None,
    species: Species,
) -> Element:
    length = _f(getattr(element, "length", 0.0))
    if how == "drift":
        warnings.warn(
            f"{name} ({type(element).__name__}): {reason}; replaced by a drift of "
            f"{length:g} m",
            LatticeConversionWarning,
            stacklevel=4,
        )
        return Drift(name, length)
    if p0c is None:
        raise LatticeImportError(
            f"{name}: approximate='linear' needs p0c (the reference momentum [eV] "
            "of the element's linear map)"
        )
    energy = p0c_to_energy(torch.tensor(p0c, dtype=F64), species)
    r = element.first_order_transfer_map(energy, _cheetah_species(species))
    warnings.warn(
        f"{name} ({type(element).__name__}): {reason}; replaced by its linear map "
        f"at p0c = {p0c:.6g} eV",
        LatticeConversionWarning,
        stacklevel=4,
    )
    return LinearMap(name, _cheetah_map_to_bmad(r, p0c, species), max(length, 0.0))


def _unique_names(names: Sequence[str]) -> list[str]:
    """``names`` with repeats suffixed ``_2``, ``_3``, ... (first kept as is)."""
    seen: dict[str, int] = {}
    taken = set(names)
    out = []
    for n in names:
        count = seen.get(n, 0) + 1
        seen[n] = count
        if count == 1:
            out.append(n)
            continue
        new = f"{n}_{count}"
        while new in taken:
            count += 1
            new = f"{n}_{count}"
        taken.add(new)
        out.append(new)
    return out


def _flat(segment: Any, cheetah: Any) -> list[Any]:
    if isinstance(segment, cheetah.Segment):
        return list(segment.flattened().elements)
    return [segment]


def _select(names: list[str], start: str | None, end: str | None) -> slice:
    """Index range from the first ``start`` to the first ``end`` after it."""
    i0, i1 = 0, len(names)
    upper = [n.upper() for n in names]

    def exact(name: str | None) -> str | None:
        # names as given, else case-insensitively (Bmad and elegant ignore case)
        if name is None or name in names or name.upper() not in upper:
            return name
        return names[upper.index(name.upper())]

    start, end = exact(start), exact(end)
    if start is not None:
        if start not in names:
            raise LatticeImportError(
                f"--start {start!r}: no such element; elements are {_few(names)}"
            )
        i0 = names.index(start)
    if end is not None:
        if end not in names[i0:]:
            where = "after the start " if start is not None else ""
            raise LatticeImportError(
                f"--end {end!r}: no such element {where}; elements are {_few(names)}"
            )
        i1 = names.index(end, i0) + 1
    return slice(i0, i1)


def _case(name: str, names: Sequence[str]) -> str:
    """``name`` as spelled in ``names`` if it matches one case-insensitively."""
    if name in names:
        return name
    for n in names:
        if n.upper() == name.upper():
            return n
    return name


def _few(names: Sequence[str], n: int = 12) -> str:
    shown = ", ".join(names[:n])
    return shown + (f", ... ({len(names)} in all)" if len(names) > n else "")


def elements_from_cheetah(
    segment: Any,
    *,
    start: str | None = None,
    end: str | None = None,
    approximate: str | None = None,
    p0c: float | None = None,
    species: Species = ELECTRON,
    screens: Sequence[str] = (),
) -> list[Element]:
    """The elements of a cheetah ``Segment`` (``Beamline.from_cheetah``).

    Args:
        segment: A cheetah ``Segment`` (nested segments are flattened) or
            element, with scalar (not vectorised) attributes.
        start: First element to keep (its first occurrence), or None.
        end: Last element to keep (first occurrence from ``start``), or None.
        approximate: None (refuse elements without a diffaccel counterpart),
            ``"drift"`` or ``"linear"`` (see the module docs).
        p0c: Reference momentum [eV]; needed for ``CustomTransferMap`` and
            ``approximate="linear"`` only.
        species: Tracked species (for coordinate conversion of linear maps).
        screens: Names of markers or monitors to make geometry-less Screens.

    Returns:
        The elements in beam order; repeated names get ``_2``, ``_3``, ....

    Raises:
        LatticeImportError: naming every unsupported element (and offering
            ``approximate``), or a bad ``start`` / ``end``.
    """
    cheetah = _require_cheetah()
    if approximate not in (None, *APPROXIMATIONS):
        raise LatticeImportError(
            f"approximate must be one of {APPROXIMATIONS} or None; got {approximate!r}"
        )
    elements = _flat(segment, cheetah)
    names = _unique_names([str(e.name) for e in elements])
    keep = _select(names, start, end)
    elements, names = elements[keep], names[keep]
    missing = set(screens) - set(names)
    if missing:
        raise LatticeImportError(f"screens: no element(s) {sorted(missing)}")
    reasons = [_why_unsupported(e, cheetah) for e in elements]
    bad = [(n, r) for n, r in zip(names, reasons, strict=True) if r is not None]
    if bad and approximate is None:
        listed = "; ".join(f"{n}: {r}" for n, r in bad)
        raise LatticeImportError(
            f"{len(bad)} element(s) without a diffaccel counterpart: {listed}. "
            "Use approximate='drift' (a drift of the same length) or "
            "approximate='linear' (the element's linear map, needs p0c); "
            "CLI: --approximate drift|linear"
        )
    out = []
    for e, n, r in zip(elements, names, reasons, strict=True):
        if r is None:
            out.append(_convert(e, n, cheetah, p0c, species, set(screens)))
        else:
            out.append(_approximation(e, n, approximate, r, p0c, species))  # type: ignore[arg-type]
    _check_unique(out)
    return out


#: Ocelot element classes cheetah's converter maps to an element of the same
#: kind (any other class it turns into a drift, and ``TDCavity`` into an
#: accelerating cavity: :func:`elements_from_ocelot` refuses those unless asked
#: to approximate).
_OCELOT_KNOWN = (
    "Drift",
    "Quadrupole",
    "Sextupole",
    "Solenoid",
    "Hcor",
    "Vcor",
    "Bend",
    "SBend",
    "RBend",
    "Cavity",
    "TWCavity",
    "Monitor",
    "Marker",
    "Undulator",
    "Aperture",
)


def elements_from_ocelot(cell: Sequence[Any], **kwargs: Any) -> list[Element]:
    """The elements of an Ocelot cell through cheetah's Ocelot converter.

    Ocelot lattices are Python: import the lattice module yourself and pass
    its cell (a list of Ocelot elements). Each element is converted by
    cheetah (``cheetah.converters.ocelot``; an ``ocelot.Monitor`` whose id
    contains ``"BSC"`` becomes a screen), then mapped as
    :func:`elements_from_cheetah` maps a ``Segment``, with the same keywords
    (``start``, ``end``, ``approximate``, ``p0c``, ``species``, ``screens``).
    Needs ``diffaccel[cheetah]`` and ``diffaccel[ocelot]``.

    ``ocelot.TDCavity`` is refused like an unknown class: cheetah 0.8.4's
    converter makes it an accelerating cavity, which a deflector is not.

    Raises:
        LatticeImportError: naming every element of a class cheetah's
            converter does not map faithfully (it would make each a drift, or
            a deflector an accelerating cavity) unless ``approximate`` is
            ``"drift"``, and whatever :func:`elements_from_cheetah` refuses.
    """
    cheetah = _require_cheetah()
    try:
        import ocelot
    except ImportError:
        raise ImportError(
            "reading an Ocelot cell needs ocelot: pip install 'diffaccel[ocelot]'"
        ) from None
    from cheetah.converters import ocelot as convert

    known = tuple(getattr(ocelot, name) for name in _OCELOT_KNOWN)
    cell = list(cell)
    unknown = [e for e in cell if not isinstance(e, known)]
    approximate = kwargs.get("approximate")
    if unknown and approximate is None:
        listed = "; ".join(f"{e.id}: ocelot.{type(e).__name__}" for e in unknown)
        raise LatticeImportError(
            f"{len(unknown)} element(s) cheetah's Ocelot converter does not map: "
            f"{listed}. Use approximate='drift' (a drift of the same length); "
            "CLI: --approximate drift"
        )
    if unknown and approximate != "drift":
        raise LatticeImportError(
            f"elements cheetah's Ocelot converter does not map can only become "
            f"drifts (approximate='drift'); got approximate={approximate!r}"
        )
    converted = []
    for e in cell:
        if not isinstance(e, known):
            converted.append(
                cheetah.Drift(torch.tensor(float(e.l), dtype=F64), name=e.id)
            )
            warnings.warn(
                f"{e.id} (ocelot.{type(e).__name__}): a drift of the same length "
                f"({float(e.l):g} m)",
                LatticeConversionWarning,
                stacklevel=2,
            )
            continue
        converted.append(convert.convert_element(e, sanitize_name=False, dtype=F64))
    return elements_from_cheetah(cheetah.Segment(converted), **kwargs)


# ---- diffaccel -> cheetah ---------------------------------------------------------


def elements_to_cheetah(
    beamline: Iterable[Element],
    p0c: float | None = None,
    species: Species = ELECTRON,
) -> Any:
    """A cheetah ``Segment`` of these elements (``Beamline.to_cheetah``), float64.

    Drifts, quadrupoles and dipoles use cheetah's ``"drift_kick_drift"``
    tracking (the exact maps diffaccel tracks); sextupoles cheetah's
    second-order map; solenoids cheetah's linear map (its only one). Scan
    settings must already be applied and every attribute be a scalar.

    Args:
        beamline: The beamline.
        p0c: Reference momentum [eV]; needed for a ``LinearMap`` only.
        species: Tracked species (for ``LinearMap`` coordinates).

    Raises:
        LatticeImportError: for an ``RFCavity`` whose reference particle gains
            energy (cheetah's ``Cavity`` would change the reference energy), a
            misaligned deflecting cavity, or a ``LinearMap`` without ``p0c``.
    """
    cheetah = _require_cheetah()
    kw = {"dtype": F64}

    def t(v: Tensor | float) -> Tensor:
        v = torch.as_tensor(v, dtype=F64).detach()
        if v.numel() != 1:
            raise LatticeImportError(
                f"batched attribute of shape {tuple(v.shape)}; apply one setting "
                "(with_params) before converting to cheetah"
            )
        return v.reshape(())

    out = []
    for e in beamline:
        name = e.name
        # every element: its own name, kept as is, in float64
        common = {"name": name, "sanitize_name": False, **kw}
        if isinstance(e, Screen):
            if e.shape is None:
                out.append(
                    cheetah.Screen(
                        metadata={_METADATA_KEY: "screen without geometry"},
                        **common,
                    )
                )
            else:
                h, w = e.shape
                out.append(
                    cheetah.Screen(
                        resolution=(w, h),
                        pixel_size=torch.tensor(e.pixel_size, dtype=F64),
                        misalignment=torch.tensor(e.center, dtype=F64),
                        method="cloud-in-cell",
                        **common,
                    )
                )
        elif isinstance(e, Drift):
            out.append(
                cheetah.Drift(
                    t(e.length),
                    tracking_method="drift_kick_drift",
                    **common,
                )
            )
        elif isinstance(e, Quadrupole):
            out.append(
                cheetah.Quadrupole(
                    t(e.length),
                    t(e.k1),
                    misalignment=torch.stack([t(e.dx), t(e.dy)]),
                    tilt=t(e.tilt),
                    tracking_method="drift_kick_drift",
                    **common,
                )
            )
        elif isinstance(e, Dipole):
            out.append(
                cheetah.Dipole(
                    t(e.length),
                    t(e.angle),
                    dipole_e1=t(e.e1),
                    dipole_e2=t(e.e2),
                    tilt=t(e.tilt),
                    gap=2 * t(e.hgap),
                    gap_exit=2 * t(e.hgapx),
                    fringe_integral=t(e.fint),
                    fringe_integral_exit=t(e.fintx),
                    tracking_method="drift_kick_drift",
                    **common,
                )
            )
        elif isinstance(e, TransverseDeflectingCavity):
            out.append(
                cheetah.TransverseDeflectingCavity(
                    t(e.length),
                    t(e.voltage),
                    t(e.phase) / (2 * math.pi),
                    t(e.frequency),
                    tilt=t(e.tilt),
                    **common,
                )
            )
        elif isinstance(e, Solenoid):
            out.append(
                cheetah.Solenoid(
                    t(e.length),
                    t(e.ks) / 2,
                    misalignment=torch.stack([t(e.dx), t(e.dy)]),
                    **common,
                )
            )
        elif isinstance(e, Sextupole):
            out.append(
                cheetah.Sextupole(
                    t(e.length),
                    t(e.k2),
                    misalignment=torch.stack([t(e.dx), t(e.dy)]),
                    tilt=t(e.tilt),
                    **common,
                )
            )
        elif isinstance(e, RFCavity):
            v, phase = float(t(e.voltage)), float(t(e.phase))
            if abs(v * math.sin(phase)) > 1e-9 * max(abs(v), 1.0):
                raise LatticeImportError(
                    f"{name}: the reference particle gains {v * math.sin(phase):.6g} "
                    "eV; cheetah's Cavity would change the reference energy "
                    "(diffaccel's RFCavity keeps it)"
                )
            out.append(
                cheetah.Cavity(
                    t(e.length),
                    torch.tensor(v * -float(species.charge), dtype=F64),
                    torch.tensor(math.degrees(phase - math.pi / 2), dtype=F64),
                    t(e.frequency),
                    **common,
                )
            )
        elif isinstance(e, LinearMap):
            if p0c is None:
                raise LatticeImportError(
                    f"{name}: converting a LinearMap needs p0c (cheetah's maps are "
                    "in tau, delta about a reference energy)"
                )
            r = _bmad_map_to_cheetah(e.transfer_map(p0c).detach(), p0c, species)
            out.append(
                cheetah.CustomTransferMap(
                    r,
                    length=t(e.length),
                    **common,
                )
            )
        else:
            raise LatticeImportError(
                f"{name}: no cheetah element for {type(e).__name__}"
            )
    return cheetah.Segment(out, name="diffaccel", sanitize_name=False)


# ---- lattice files ----------------------------------------------------------------


def lattice_format(path: str | Path, fmt: str | None = None) -> str:
    """``"bmad"``, ``"elegant"`` or ``"latticejson"`` for ``path``.

    Raises:
        LatticeImportError: for an unknown suffix (and no ``fmt``).
    """
    if fmt is not None:
        if fmt not in set(LATTICE_FORMATS.values()):
            raise LatticeImportError(
                f"format must be one of {sorted(set(LATTICE_FORMATS.values()))}; "
                f"got {fmt!r}"
            )
        return fmt
    suffix = Path(path).suffix.lower()
    if suffix not in LATTICE_FORMATS:
        raise LatticeImportError(
            f"{path}: unknown lattice suffix {suffix!r}; known: "
            f"{', '.join(f'{k} ({v})' for k, v in LATTICE_FORMATS.items())}"
        )
    return LATTICE_FORMATS[suffix]


@contextlib.contextmanager
def _cheetah_warnings(path: Path, handled: dict[str, set[str]]) -> Iterator[None]:
    """Re-issue cheetah's converter warnings as ours, except for the handled ones.

    ``handled`` maps an element type to the attributes this module reads itself.
    """
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        yield
    pattern = re.compile(
        r"Property (\S+) with value .* for element type (\S+) is currently not"
    )
    for w in caught:
        text = str(w.message)
        m = pattern.match(text)
        if m and m.group(1) in handled.get(m.group(2), set()):
            continue
        if "sanitize" in text or "valid Python variable" in text:
            continue
        if re.match(r"Could not evaluate expression '\".*\"'", text):
            continue  # a quoted string value (e.g. a WATCH file name)
        if issubclass(w.category, LatticeConversionWarning):
            warnings.warn(w.message, w.category, stacklevel=4)
            continue
        warnings.warn(
            f"{path.name}: cheetah's converter: {text}",
            LatticeConversionWarning,
            stacklevel=4,
        )


def _parse(path: Path) -> dict:
    from cheetah.converters.utils.fortran_namelist import (
        merge_delimiter_continued_lines,
        parse_lines,
        read_clean_lines,
    )

    lines = read_clean_lines(path)
    lines = merge_delimiter_continued_lines(lines, "&", remove_delimiter=True)
    lines = merge_delimiter_continued_lines(lines, ",", remove_delimiter=False)
    lines = merge_delimiter_continued_lines(lines, "{", remove_delimiter=False)
    return parse_lines(lines)


def _walk(name: str, context: dict) -> list[tuple[str, dict]]:
    """Element names and parsed attributes of a line, flattened in beam order."""
    reverse = name.startswith("-")
    key = name.removeprefix("-")
    if key not in context:
        raise LatticeImportError(f"line or element {key!r} is not defined")
    parsed = context[key]
    if isinstance(parsed, list):
        out = [item for sub in parsed for item in _walk(sub, context)]
        return out[::-1] if reverse else out
    if isinstance(parsed, dict) and "element_type" in parsed:
        return [(key, parsed)]
    raise LatticeImportError(f"{key!r} is neither a line nor an element")


# element types cheetah's converters know (others it turns into drifts)
_BMAD_KNOWN = {
    "marker",
    "monitor",
    "instrument",
    "pipe",
    "drift",
    "hkicker",
    "vkicker",
    "sbend",
    "quadrupole",
    "sextupole",
    "lcavity",
    "rcollimator",
    "ecollimator",
    "wiggler",
    "patch",
}
_ELEGANT_KNOWN = {
    "hkick",
    "hkic",
    "vkick",
    "vkic",
    "kick",
    "kicker",
    "mark",
    "marker",
    "drift",
    "drif",
    "csrdrift",
    "csrdrif",
    "lscdrift",
    "lscdrif",
    "ecol",
    "rcol",
    "quad",
    "quadrupole",
    "kquad",
    "sext",
    "sextupole",
    "moni",
    "ematrix",
    "rfca",
    "rfcw",
    "sben",
    "csbend",
    "rben",
    "csrcsben",
    "csrcsbend",
    "wiggler",
    "charge",
    "wake",
}


class _Unsupported:
    """Stand-in for an element no converter maps (refused or approximated)."""

    def __init__(self, name: str, kind: str, length: float) -> None:
        self.name = name
        self.kind = kind
        self.length = torch.tensor(length, dtype=F64)


def _own_bmad(name: str, p: dict, species: Species) -> Element | None:
    """Bmad elements mapped here on top of cheetah's converter (None: cheetah's)."""
    kind = p["element_type"]
    if kind == "crab_cavity":  # absent from cheetah's Bmad converter
        # Bmad: px += V sin(2 pi phi0 + k z / beta) / p0c for the reference species
        return TransverseDeflectingCavity(
            name,
            float(p.get("l", 0.0)),
            float(p.get("voltage", 0.0)) * -1.0 / species.charge,
            float(p.get("rf_frequency", 0.0)),
            2 * math.pi * float(p.get("phi0", 0.0)),
            tilt=float(p.get("tilt", 0.0)),
        )
    if kind == "rfcavity":  # absent from cheetah's Bmad converter
        return RFCavity(
            name,
            float(p.get("l", 0.0)),
            float(p.get("voltage", 0.0)),
            float(p.get("rf_frequency", 0.0)),
            2 * math.pi * float(p.get("phi0", 0.0)),
        )
    if kind == "solenoid":  # cheetah reads ks as its k (= ks / 2)
        return Solenoid(name, float(p.get("l", 0.0)), float(p.get("ks", 0.0)))
    return None


def _own_elegant(name: str, p: dict) -> Element | None:
    """elegant elements mapped here on top of cheetah's converter."""
    kind = p["element_type"]
    if kind == "rfdf":  # cheetah drops FREQUENCY and TILT, phase units
        return TransverseDeflectingCavity(
            name,
            float(p.get("l", 0.0)),
            float(p.get("voltage", 0.0)),
            float(p.get("frequency", 2.856e9)),
            math.radians(float(p.get("phase", 0.0)) - 90.0),
            tilt=float(p.get("tilt", 0.0)),
        )
    if kind == "sole":  # cheetah reads KS as 0
        return Solenoid(name, float(p.get("l", 0.0)), float(p.get("ks", 0.0)))
    if kind == "watch":
        return Screen(name)
    return None


_HANDLED = {
    "rfdf": {"frequency", "tilt", "voltage", "phase"},
    "sole": {"ks"},
    "watch": {"filename", "mode", "label"},
    "lcavity": {"cavity_type"},  # (Bmad's default, set here for cheetah)
}


def elements_from_lattice(
    path: str | Path,
    start: str | None = None,
    end: str | None = None,
    *,
    line: str | None = None,
    fmt: str | None = None,
    approximate: str | None = None,
    p0c: float | None = None,
    species: Species = ELECTRON,
    screens: Sequence[str] = (),
) -> list[Element]:
    """Elements of a Bmad, elegant or LatticeJSON lattice (``Beamline.from_lattice``).

    Read through cheetah's converters.

    Parsing is cheetah's (``cheetah.converters``); each element is converted by
    cheetah and then by :func:`elements_from_cheetah`, except where cheetah
    0.8.4's converter loses information; those elements are mapped here from
    cheetah's parsed attributes:

    - Bmad ``crab_cavity`` (cheetah has none): ``TransverseDeflectingCavity``
      with ``phase = 2 pi phi0``, ``voltage``, ``rf_frequency``, ``tilt``;
    - Bmad ``rfcavity`` (cheetah has none): ``RFCavity`` (same convention);
    - Bmad ``solenoid``: ``ks`` as given (cheetah takes it for its ``k = ks/2``);
    - elegant ``RFDF``: ``FREQUENCY`` and ``TILT`` are kept (cheetah drops
      them), ``PHASE`` [deg] minus 90 is the phase in rad (``PHASE = 90`` is
      the zero crossing, as in cheetah's converter);
    - elegant ``SOLE``: ``KS`` kept as Bmad's ``ks`` (cheetah reads 0);
    - elegant ``WATCH``: a ``Screen`` without geometry.

    Elements that neither cheetah nor this module maps (cheetah would put in a
    drift) count as unsupported, as do those :func:`elements_from_cheetah`
    refuses. Any attribute cheetah ignores is reported as a
    :class:`LatticeConversionWarning` naming the file.

    Args:
        path: Lattice file.
        start: First element to keep (first occurrence), or None.
        end: Last element to keep (first occurrence from ``start``), or None.
        line: elegant line to use (default: the file's ``USE``, else the last
            line defined); Bmad uses the file's ``use``.
        fmt: ``"bmad"``, ``"elegant"`` or ``"latticejson"`` (default: by suffix,
            see :data:`LATTICE_FORMATS`).
        approximate: As in :func:`elements_from_cheetah`.
        p0c: Reference momentum [eV] (for ``approximate="linear"``, ``EMATRIX``).
        species: Tracked species.
        screens: Names of markers or monitors to make geometry-less Screens.

    Raises:
        LatticeImportError: unreadable file, unknown line or element, elements
            without counterpart (all named in one line).
    """
    cheetah = _require_cheetah()
    path = Path(path)
    if not path.is_file():
        raise LatticeImportError(f"{path}: no such lattice file")
    fmt = lattice_format(path, fmt)
    if fmt == "latticejson":
        try:
            with _cheetah_warnings(path, {}):
                segment = cheetah.Segment.from_lattice_json(str(path), dtype=F64)
        except (KeyError, ValueError, TypeError, OSError) as err:
            raise LatticeImportError(
                f"{path}: not a cheetah LatticeJSON file ({type(err).__name__}: {err})"
            ) from None
        return elements_from_cheetah(
            segment,
            start=start,
            end=end,
            approximate=approximate,
            p0c=p0c,
            species=species,
            screens=screens,
        )
    from cheetah.converters import bmad as bmad_converter
    from cheetah.converters import elegant as elegant_converter

    try:
        with _cheetah_warnings(path, {}):
            context = _parse(path)
    except LatticeImportError:
        raise
    except Exception as err:  # cheetah's parser raises many kinds
        raise LatticeImportError(
            f"{path}: cheetah's {fmt} parser failed ({type(err).__name__}: {err})"
        ) from None
    root = line or context.get("__use__")
    if root is None:
        lines = [k for k, v in context.items() if isinstance(v, list)]
        if not lines:
            raise LatticeImportError(f"{path}: defines no beam line")
        root = lines[-1]
    root = str(root)
    if root not in context and root.lower() in context:
        root = root.lower()
    flat = _walk(root, context)

    converter = bmad_converter if fmt == "bmad" else elegant_converter
    known = _BMAD_KNOWN if fmt == "bmad" else _ELEGANT_KNOWN
    items: list[Any] = []
    own: dict[int, Element] = {}
    with _cheetah_warnings(path, _HANDLED):
        for i, (name, parsed) in enumerate(flat):
            upper = name.upper()  # Bmad and elegant names are case-insensitive
            mine = (
                _own_bmad(upper, parsed, species)
                if fmt == "bmad"
                else _own_elegant(upper, parsed)
            )
            if mine is not None:
                own[i] = mine
                items.append(None)
                continue
            kind = parsed["element_type"]
            if kind not in known:
                items.append(_Unsupported(upper, kind, float(parsed.get("l", 0.0))))
                continue
            if fmt == "bmad" and kind == "sbend":
                parsed.setdefault("e1", 0.0)  # cheetah needs it
            if fmt == "bmad" and kind == "lcavity":
                parsed.setdefault("cavity_type", "traveling_wave")  # Bmad's default
            try:
                converted = converter.convert_element(
                    name, context, sanitize_name=False, dtype=F64
                )
            except Exception as err:
                raise LatticeImportError(
                    f"{path}: element {upper!r} ({kind}): cheetah's converter failed "
                    f"({type(err).__name__}: {err})"
                ) from None
            items.append(converted)
    return _assemble(
        flat, items, own, start, end, approximate, p0c, species, screens, cheetah
    )


def _assemble(
    flat: list[tuple[str, dict]],
    items: list[Any],
    own: dict[int, Element],
    start: str | None,
    end: str | None,
    approximate: str | None,
    p0c: float | None,
    species: Species,
    screens: Sequence[str],
    cheetah: Any,
) -> list[Element]:
    """Convert, name uniquely, select ``start..end`` and check support."""
    if approximate not in (None, *APPROXIMATIONS):
        raise LatticeImportError(
            f"approximate must be one of {APPROXIMATIONS} or None; got {approximate!r}"
        )
    # cheetah may return a Segment for one element (e.g. collimators): expand
    entries: list[tuple[str, Any, Element | None]] = []
    for i, ((name, _), item) in enumerate(zip(flat, items, strict=True)):
        name = name.upper()
        if i in own:
            entries.append((name, None, own[i]))
        elif isinstance(item, cheetah.Segment):
            entries.extend((str(e.name).upper(), e, None) for e in _flat(item, cheetah))
        else:
            entries.append((name, item, None))
    names = _unique_names([n for n, _, _ in entries])
    keep = _select(names, start, end)
    entries, names = entries[keep], names[keep]
    screens = [_case(n, names) for n in screens]
    missing = set(screens) - set(names)
    if missing:
        raise LatticeImportError(f"screens: no element(s) {sorted(missing)}")
    reasons: list[str | None] = []
    for _, item, mine in entries:
        if mine is not None:
            reasons.append(None)
        elif isinstance(item, _Unsupported):
            reasons.append(f"{item.kind} is not converted by cheetah or diffaccel")
        else:
            reasons.append(_why_unsupported(item, cheetah))
    bad = [(n, r) for n, r in zip(names, reasons, strict=True) if r is not None]
    if bad and approximate is None:
        listed = "; ".join(f"{n}: {r}" for n, r in bad)
        raise LatticeImportError(
            f"{len(bad)} element(s) without a diffaccel counterpart: {listed}. "
            "Use approximate='drift' (a drift of the same length) or "
            "approximate='linear' (the element's linear map, needs p0c); "
            "CLI: --approximate drift|linear"
        )
    out: list[Element] = []
    for (_, item, mine), n, r in zip(entries, names, reasons, strict=True):
        if mine is not None:
            out.append(_renamed(mine, n))
        elif r is None:
            out.append(_convert(item, n, cheetah, p0c, species, set(screens)))
        elif isinstance(item, _Unsupported):
            no_map = "; no linear map is known" if approximate == "linear" else ""
            warnings.warn(
                f"{n} ({item.kind}): {r}{no_map}; replaced by a drift of "
                f"{float(item.length):g} m",
                LatticeConversionWarning,
                stacklevel=3,
            )
            out.append(Drift(n, float(item.length)))
        else:
            out.append(_approximation(item, n, approximate, r, p0c, species))  # type: ignore[arg-type]
    _check_unique(out)
    return out


def _check_unique(elements: Sequence[Element]) -> None:
    names = [e.name for e in elements]
    if len(set(names)) != len(names):  # (cannot happen: names are made unique)
        raise LatticeImportError(f"repeated element names in {names}")


def _renamed(element: Element, name: str) -> Element:
    if element.name == name:
        return element
    if isinstance(element, Screen):
        return Screen(name, element.shape, element.pixel_size, element.center)
    return type(element)(name=name, **element.params(), **element._config())
