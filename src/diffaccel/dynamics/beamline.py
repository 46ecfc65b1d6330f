"""An ordered list of elements, built from the quad-scan dataset's JSON spec."""

from __future__ import annotations

import numbers
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from diffaccel.dynamics._validate import (
    as_p0c,
    broadcast_shapes,
    check_particles,
    compute_dtype,
    finite_checks_enabled,
)
from diffaccel.dynamics.cheetah_interop import (
    elements_from_cheetah,
    elements_from_lattice,
    elements_from_ocelot,
    elements_to_cheetah,
)
from diffaccel.dynamics.elements._kernels import stack_columns
from diffaccel.dynamics.elements.dipole import Dipole
from diffaccel.dynamics.elements.drift import Drift
from diffaccel.dynamics.elements.element import Coords, Element
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

__all__ = ["ELEMENT_TYPES", "Beamline"]

#: Element classes by the ``"type"`` string used in specs.
ELEMENT_TYPES: dict[str, type[Element]] = {
    cls.__name__: cls
    for cls in (
        Drift,
        Quadrupole,
        Dipole,
        TransverseDeflectingCavity,
        Screen,
        LinearMap,
        Solenoid,
        Sextupole,
        RFCavity,
    )
}
_SCREEN_KEYS = ("shape", "pixel_size", "center")


def _spec_value(value: Any, owner: str, key: str) -> Tensor:
    """A spec parameter as a float64 tensor: a real number or nested list of them.

    Raises:
        ValueError: naming the element and parameter for a bool, string, None,
            complex number or anything else that is not real numbers.
    """

    def bad(v: Any) -> bool:
        if isinstance(v, list | tuple):
            return any(bad(u) for u in v)
        return isinstance(v, bool) or not isinstance(v, numbers.Real)

    if isinstance(value, Tensor):
        ok = not value.is_complex() and value.dtype != torch.bool
    elif isinstance(value, np.ndarray):
        ok = value.dtype.kind in "iuf"
    else:
        ok = not bad(value)
    if not ok:
        got = getattr(value, "dtype", type(value).__name__)
        raise ValueError(
            f"{owner}: {key} must be a real number (or a list of them); got "
            f"{got} {value!r}."
        )
    try:
        return torch.as_tensor(value, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError) as err:
        raise ValueError(f"{owner}: {key}: not a rectangular array ({err}).") from err


def _last_z_reader(elements: Sequence[Element]) -> int:
    """Index of the last element whose map reads ``z`` (-1 if none does)."""
    return max((i for i, e in enumerate(elements) if e.reads_z), default=-1)


def _without_z(coords: Coords) -> Coords:
    """The columns with ``z`` left out (None: no element after reads it)."""
    return (*coords[:4], None, coords[5])  # type: ignore[return-value]


class Beamline(nn.Module):
    """An ordered sequence of uniquely named elements.

    Tracking never changes the beamline: scan settings are applied to copies of
    the elements (see :meth:`track`).

    Args:
        elements: The elements in beam order; names must be unique.

    Shapes:
        ``track``: particles ``(N, 6)`` or ``(*K, N, 6)`` and settings ``(*K, P)``
        -> ``(*K, N, 6)``, in the particles' dtype; half-precision particles
        (float16, bfloat16) are tracked in float32 and returned as float32.

    Example:
        >>> spec = [
        ...     {"type": "Quadrupole", "name": "Q1", "length": 0.1, "k1": 0.0},
        ...     {"type": "Drift", "name": "D1", "length": 1.0},
        ...     {"type": "Screen", "name": "SCREEN"},
        ... ]
        >>> bl = Beamline.from_spec(spec)
        >>> k1 = torch.linspace(-25.0, 15.0, 20).unsqueeze(-1)
        >>> p = torch.zeros(100, 6)
        >>> bl.track(p, p0c=43.36e6, settings=k1, names=["Q1.k1"]).shape
        torch.Size([20, 100, 6])
    """

    def __init__(self, elements: Sequence[Element]) -> None:
        super().__init__()
        names = [e.name for e in elements]
        for e in elements:
            if not isinstance(e, Element):
                raise TypeError(f"Beamline takes Elements; got {type(e).__name__}.")
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"Element names must be unique; repeated: {dup}.")
        self.elements = nn.ModuleList(elements)

    @classmethod
    def from_spec(cls, spec: Sequence[Mapping[str, Any]]) -> Beamline:
        """Build from a list of element dicts (the quad-scan ``beamline`` JSON).

        Each dict has ``"type"`` (one of :data:`ELEMENT_TYPES`), ``"name"`` and
        numeric parameters (e.g. ``"length"`` [m], ``"k1"`` [1/m^2]); a Screen
        may carry ``"shape"``, ``"pixel_size"`` and ``"center"``.

        Raises:
            ValueError: for an unknown type or parameter (the known ones are
                listed), a missing name or a bad value.
        """
        if isinstance(spec, str | bytes) or not isinstance(spec, Sequence):
            raise ValueError(
                "spec must be a list of element dicts (decode the JSON first)."
            )
        elements = []
        for pos, entry in enumerate(spec):
            if not isinstance(entry, Mapping):
                raise ValueError(f"spec[{pos}] must be a dict; got {entry!r}.")
            entry = dict(entry)
            kind = entry.pop("type", None)
            if kind not in ELEMENT_TYPES:
                raise ValueError(
                    f"spec[{pos}]: unknown element type {kind!r}; known types are "
                    f"{sorted(ELEMENT_TYPES)}."
                )
            name = entry.pop("name", None)
            if not isinstance(name, str) or not name:
                raise ValueError(f"spec[{pos}] ({kind}) needs a non-empty 'name'.")
            elem_cls = ELEMENT_TYPES[kind]
            config = tuple(getattr(elem_cls, "config_names", ()))
            known = list(elem_cls.param_names) + list(config)
            if elem_cls is Screen:
                known += list(_SCREEN_KEYS)
            unknown = sorted(set(entry) - set(known))
            if unknown:
                raise ValueError(
                    f"spec[{pos}] ({kind} {name!r}): unknown parameter(s) {unknown}; "
                    f"known parameters are {known}."
                )
            if elem_cls is Screen:
                elements.append(Screen(name, **entry))
                continue
            owner = f"spec[{pos}] ({kind} {name!r})"
            values: dict[str, Any] = {
                k: v if k in config else _spec_value(v, owner, k)
                for k, v in entry.items()
            }
            if elem_cls is LinearMap:
                if "matrix" not in values:
                    raise ValueError(
                        f"spec[{pos}] (LinearMap {name!r}) needs 'matrix'."
                    )
                elements.append(LinearMap(name, **values))
            else:
                if elem_cls is TransverseDeflectingCavity and not bool(
                    (values.get("frequency", torch.zeros(())) > 0).all()
                ):
                    got = repr(entry["frequency"]) if "frequency" in entry else "none"
                    raise ValueError(
                        f"{owner}: frequency must be > 0 Hz (an RF cavity); got {got}."
                    )
                elements.append(elem_cls(name, **values))
        return cls(elements)

    @classmethod
    def from_cheetah(cls, segment: Any, **kwargs: Any) -> Beamline:
        """Build from a cheetah ``Segment`` (needs ``diffaccel[cheetah]``).

        See :func:`diffaccel.dynamics.cheetah_interop.elements_from_cheetah`
        for the element correspondence and the keyword arguments (``start``,
        ``end``, ``approximate``, ``p0c``, ``species``, ``screens``).
        """
        return cls(elements_from_cheetah(segment, **kwargs))

    @classmethod
    def from_ocelot(cls, cell: Any, **kwargs: Any) -> Beamline:
        """Build from an Ocelot cell (a list of Ocelot elements) through
        cheetah's Ocelot converter (needs ``diffaccel[cheetah]`` and
        ``diffaccel[ocelot]``).

        See :func:`diffaccel.dynamics.cheetah_interop.elements_from_ocelot`
        (same keywords as :meth:`from_cheetah`).
        """
        return cls(elements_from_ocelot(cell, **kwargs))

    def to_cheetah(self, **kwargs: Any) -> Any:
        """This beamline as a cheetah ``Segment`` (needs ``diffaccel[cheetah]``).

        See :func:`diffaccel.dynamics.cheetah_interop.elements_to_cheetah`
        (keywords ``p0c``, ``species``).
        """
        return elements_to_cheetah(self, **kwargs)

    @classmethod
    def from_lattice(
        cls,
        path: Any,
        start: str | None = None,
        end: str | None = None,
        **kwargs: Any,
    ) -> Beamline:
        """Read a Bmad, elegant or LatticeJSON file through cheetah's converters.

        ``start`` / ``end`` name the first and last element kept. See
        :func:`diffaccel.dynamics.cheetah_interop.elements_from_lattice` for
        what is mapped, what is refused and the keyword arguments (``line``,
        ``fmt``, ``approximate``, ``p0c``, ``species``, ``screens``).
        """
        return cls(elements_from_lattice(path, start, end, **kwargs))

    def to_spec(self) -> list[dict[str, Any]]:
        """The JSON-serialisable element list (inverse of :meth:`from_spec`)."""
        return [e.to_spec() for e in self.elements]

    @property
    def element_names(self) -> list[str]:
        """Element names in beam order."""
        return [e.name for e in self.elements]

    def __getitem__(self, name: str) -> Element:
        for e in self.elements:
            if e.name == name:
                return e
        raise KeyError(f"No element named {name!r}; elements are {self.element_names}.")

    def __iter__(self) -> Iterator[Element]:
        return iter(self.elements)

    def __len__(self) -> int:
        return len(self.elements)

    @property
    def length(self) -> Tensor:
        """Total length [m] (broadcast over batched lengths)."""
        total = torch.zeros((), dtype=torch.float64)
        for e in self.elements:
            total = total + e.length.to(total.dtype)
        return total

    def with_screen(
        self,
        name: str,
        shape: Sequence[int],
        pixel_size: Sequence[float] | float,
        center: Sequence[float] = (0.0, 0.0),
    ) -> Beamline:
        """A new beamline whose screen ``name`` has the given geometry."""
        if not isinstance(self[name], Screen):
            raise ValueError(f"Element {name!r} is a {type(self[name]).__name__}.")
        return Beamline(
            [
                Screen(name, shape, pixel_size, center) if e.name == name else e
                for e in self.elements
            ]
        )

    def with_params(self, values: Mapping[str, Tensor | float]) -> Beamline:
        """A new beamline with ``{"Q1.k1": value, ...}`` applied; ``self`` unchanged."""
        per_element: dict[str, dict[str, Tensor | float]] = {}
        for key, value in values.items():
            elem, attr = self._split_name(key)
            per_element.setdefault(elem, {})[attr] = value
        return Beamline(
            [
                e.with_params(**per_element[e.name]) if e.name in per_element else e
                for e in self.elements
            ]
        )

    def _split_name(self, key: str) -> tuple[str, str]:
        if not isinstance(key, str) or key.count(".") < 1:
            raise ValueError(
                f"Setting name {key!r} must look like 'ELEMENT.parameter', "
                "e.g. 'Q1.k1'."
            )
        elem, attr = key.rsplit(".", 1)
        if elem not in self.element_names:
            raise ValueError(
                f"Setting {key!r}: no element {elem!r}; elements are "
                f"{self.element_names}."
            )
        known = self[elem].param_names
        if attr not in known:
            raise ValueError(
                f"Setting {key!r}: {type(self[elem]).__name__} {elem!r} has no "
                f"parameter {attr!r}; known parameters are {list(known)}."
            )
        return elem, attr

    def _scanned(
        self,
        settings: Tensor | None,
        names: Sequence[str] | None,
        particles: Tensor | None = None,
    ) -> Beamline:
        if settings is None and names is None:
            return self
        if settings is None or names is None:
            raise ValueError("Give both settings and names, or neither.")
        settings = torch.as_tensor(settings)
        if isinstance(names, str):
            raise ValueError(
                f"names must be a list of strings; got the string {names!r}."
            )
        if settings.dim() < 1 or settings.shape[-1] != len(names):
            raise ValueError(
                f"settings must be shaped (*K, P) with P = len(names) = {len(names)}; "
                f"got {tuple(settings.shape)}."
            )
        if finite_checks_enabled() and not bool(torch.isfinite(settings).all()):
            raise ValueError("settings contain NaN or infinite values.")
        if len(set(names)) != len(names):
            raise ValueError(f"names must be unique; got {list(names)}.")
        if particles is not None:
            try:
                broadcast_shapes(particles.shape[:-2], settings.shape[:-1])
            except RuntimeError:
                raise ValueError(
                    f"particles {tuple(particles.shape)} (*K, N, 6) and settings "
                    f"{tuple(settings.shape)} (*K, P) must have broadcastable batch "
                    f"shapes K; got {tuple(particles.shape[:-2])} and "
                    f"{tuple(settings.shape[:-1])}."
                ) from None
        return self.with_params({n: settings[..., p] for p, n in enumerate(names)})

    def track(
        self,
        particles: Tensor,
        p0c: Tensor | float,
        settings: Tensor | None = None,
        names: Sequence[str] | None = None,
        species: Species = ELECTRON,
    ) -> Tensor:
        """Track particles through the whole beamline.

        Args:
            particles: Bmad coordinates at the entrance, ``(N, 6)`` or ``(*K, N, 6)``.
            p0c: Reference momentum times c [eV], scalar or ``(*K,)``.
            settings: Optional scan values ``(*K, P)``; column ``p`` sets the
                element parameter ``names[p]``.
            names: ``P`` names like ``"Q1.k1"`` (element name, dot, parameter).
            species: Tracked species (default electron).

        Returns:
            Coordinates at the end, ``(*K, N, 6)``.
        """
        return self._run(particles, p0c, settings, names, species)[0]

    def track_screens(
        self,
        particles: Tensor,
        p0c: Tensor | float,
        settings: Tensor | None = None,
        names: Sequence[str] | None = None,
        species: Species = ELECTRON,
    ) -> dict[str, Tensor]:
        """Particles at every screen, ``{name: (*K, N, 6)}``.

        Arguments as in :meth:`track`.
        """
        return self._run(particles, p0c, settings, names, species)[1]

    def screen_images(
        self,
        particles: Tensor,
        p0c: Tensor | float,
        settings: Tensor | None = None,
        names: Sequence[str] | None = None,
        species: Species = ELECTRON,
        method: str = "cic",
        bandwidth: Sequence[float] | float | None = None,
        blur_sigma: Sequence[float] | float | None = None,
        weights: Tensor | None = None,
    ) -> dict[str, Tensor]:
        """Images at every screen, ``{name: (*K, H, W)}``, in one pass.

        Equal to ``screen.image(track_screens(...)[name], ...)`` for each screen,
        but renders straight from the tracked ``x, y`` columns: the ``(*K, N, 6)``
        particles at the screens are never assembled, which saves memory traffic
        in scans (and, in the backward pass, the gradients of unused coordinates).
        Tracking arguments as in :meth:`track`; image arguments as in
        :meth:`Screen.image`. Every screen needs a geometry.
        """
        check_particles(particles)
        particles = particles.to(compute_dtype(particles))  # float16: p0c overflows
        p0c = as_p0c(p0c, particles)
        line = self._scanned(settings, names, particles)
        return line.images_of_columns(
            tuple(particles.unbind(-1)),  # type: ignore[arg-type]
            p0c,
            species,
            method=method,
            bandwidth=bandwidth,
            blur_sigma=blur_sigma,
            weights=weights,
        )

    def images_of_columns(
        self,
        coords: Coords,
        p0c: Tensor,
        species: Species = ELECTRON,
        *,
        method: str = "cic",
        bandwidth: Sequence[float] | float | None = None,
        blur_sigma: Sequence[float] | float | None = None,
        weights: Tensor | None = None,
    ) -> dict[str, Tensor]:
        """Unchecked :meth:`screen_images` of coordinate columns.

        As :meth:`Element.track_columns`: ``coords`` are the six columns, each
        broadcastable to ``(*K, N)``; ``p0c`` a tensor of their dtype; scan
        settings already applied (:meth:`with_params`). Nothing is validated
        (the positions at each screen still are, by the imaging). Only what the
        images need is computed: nothing after the last screen, ``z`` only up
        to the last element that reads it (:attr:`Element.reads_z`), and a
        :class:`LinearMap` followed only by screens gives ``x`` and ``y``.
        ``coords[4]`` may be None when no element reads ``z``.
        """
        images: dict[str, Tensor] = {}
        elements = list(self.elements)
        last = max(
            (i for i, e in enumerate(elements) if isinstance(e, Screen)), default=-1
        )
        z_until = _last_z_reader(elements[: last + 1])
        for i, e in enumerate(elements[: last + 1]):
            if i > z_until:
                coords = _without_z(coords)
            if isinstance(e, Screen):
                images[e.name] = e.image_xy(
                    coords[0], coords[2], method, bandwidth, blur_sigma, weights
                )
            elif isinstance(e, LinearMap) and all(
                isinstance(f, Screen) for f in elements[i + 1 : last + 1]
            ):
                x, y = e.track_xy(coords)
                coords = (x, None, y, None, None, None)  # type: ignore[assignment]
            else:
                coords = e.track_columns(coords, p0c, species)
        return images

    def track_columns(
        self,
        coords: Coords,
        p0c: Tensor,
        species: Species = ELECTRON,
        *,
        need_z: bool = True,
    ) -> Coords:
        """Unchecked tracking of coordinate columns through every element.

        As :meth:`Element.track_columns` (columns broadcastable to ``(*K, N)``,
        ``p0c`` a tensor of their dtype, settings already applied, nothing
        validated). With ``need_z`` False the returned ``z`` is None and is not
        computed after the last element that reads it.
        """
        elements = list(self.elements)
        z_until = len(elements) if need_z else _last_z_reader(elements)
        for i, e in enumerate(elements):
            if i > z_until:
                coords = _without_z(coords)
            coords = e.track_columns(coords, p0c, species)
        return coords if need_z else _without_z(coords)

    def _run(
        self,
        particles: Tensor,
        p0c: Tensor | float,
        settings: Tensor | None,
        names: Sequence[str] | None,
        species: Species,
    ) -> tuple[Tensor, dict[str, Tensor]]:
        check_particles(particles)
        particles = particles.to(compute_dtype(particles))  # float16: p0c overflows
        p0c = as_p0c(p0c, particles)
        line = self._scanned(settings, names, particles)
        screens: dict[str, Tensor] = {}
        coords = tuple(particles.unbind(-1))
        for e in line.elements:
            coords = e.track_columns(coords, p0c, species)
            if isinstance(e, Screen):
                screens[e.name] = stack_columns(coords)
        return stack_columns(coords), screens

    def transfer_map(self, p0c: Tensor | float, species: Species = ELECTRON) -> Tensor:
        """Product of the elements' affine maps, shape ``(*K, 7, 7)``.

        ``A_n @ ... @ A_1`` (see :class:`Element` for the affine layout): the
        first-order map of the whole line about the reference orbit, offsets of
        misaligned elements included.
        """
        r = None
        for e in self.elements:
            if isinstance(e, Screen):
                continue
            m = e.transfer_map(p0c, species)
            r = m if r is None else m.to(r) @ r
        if r is None:
            return torch.eye(7, dtype=torch.float64)
        return r

    def linear_map_is_exact(self, monochromatic: bool) -> bool:
        """Whether :meth:`transfer_map` / :meth:`linearized` reproduce tracking.

        True when every element's :meth:`Element.linear_map_is_exact` is (for
        beams with ``pz = 0`` if ``monochromatic``); apply scan settings first.
        A cavity that is switched on, a bending dipole, or any element with
        length and a beam with energy spread make it False: then track.
        """
        return all(e.linear_map_is_exact(monochromatic) for e in self.elements)

    def linearized(self, p0c: Tensor | float, species: Species = ELECTRON) -> Beamline:
        """The linear fidelity of this beamline as a new ``Beamline``.

        Each run of elements between screens becomes one :class:`LinearMap` (the
        product of their ``transfer_map``); screens are kept, so
        ``track_screens`` works unchanged. Apply scan settings first, e.g.
        ``bl.with_params({"Q1.k1": k1}).linearized(p0c)``; the result's affine
        maps then carry the batch shape ``(*K, 7, 7)``. The result reproduces
        tracking only where :meth:`linear_map_is_exact` says so. A run of one
        element keeps its name; a longer run is named ``"FIRST..LAST"``.
        """
        out: list[Element] = []
        run: list[Element] = []

        def flush() -> None:
            if not run:
                return
            r = run[0].transfer_map(p0c, species)
            length = run[0].length.to(r)
            for e in run[1:]:
                r = e.transfer_map(p0c, species).to(r) @ r
                length = length + e.length.to(r)
            name = run[0].name if len(run) == 1 else f"{run[0].name}..{run[-1].name}"
            out.append(LinearMap(name, r, length))
            run.clear()

        for e in self.elements:
            if isinstance(e, Screen):
                flush()
                out.append(e)
            else:
                run.append(e)
        flush()
        return Beamline(out)

    def extra_repr(self) -> str:
        return f"elements={self.element_names}"
