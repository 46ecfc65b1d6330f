"""The element interface: an ``nn.Module`` that maps particles to particles."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar

import torch
from torch import Tensor, nn

from diffaccel.dynamics._validate import (
    as_p0c,
    broadcast_shapes,
    check_finite,
    check_nonnegative,
    check_particles,
    compute_dtype,
)
from diffaccel.dynamics.elements._kernels import (
    is_zero,
    stack_columns,
    to_element_frame,
    to_lab_frame,
)
from diffaccel.dynamics.species import ELECTRON, Species

__all__ = ["Coords", "Element", "bcast"]

#: The six coordinate columns ``(x, px, y, py, z, pz)``, each broadcastable to
#: ``(*K, N)``.
#: ``z`` may be None where nothing downstream needs it (:attr:`Element.reads_z`).
Coords = tuple[Tensor, Tensor, Tensor, Tensor, Tensor | None, Tensor]


def bcast(value: Tensor, like: Tensor) -> Tensor:
    """An attribute shaped ``(*K,)`` cast to ``like`` and shaped ``(*K, 1)``.

    The trailing singleton lines the attribute up with the particle axis ``N`` of
    coordinates shaped ``(*K, N)``, so that ordinary broadcasting applies.
    """
    return value.to(dtype=like.dtype, device=like.device).unsqueeze(-1)


class Element(nn.Module):
    """A beamline element: tracks Bmad coordinates ``(x, px, y, py, z, pz)``.

    Subclasses must implement :meth:`track` or :meth:`track_columns`;
    :meth:`transfer_map` (the affine first-order map about the reference orbit)
    and :meth:`linear_map_is_exact` are optional.

    Affine maps are ``(*K, 7, 7)`` matrices ``A`` acting on ``(u, 1)``: the
    linear part ``A[..., :6, :6]`` (the Jacobian) and the offset
    ``A[..., :6, 6]`` (where the reference particle ends up, e.g. after a
    misaligned quadrupole); the last row is ``(0, ..., 0, 1)``. Maps compose by
    matrix products, ``A_beamline = A_n @ ... @ A_1``. Numeric attributes listed in
    ``param_names`` are tensors: buffers, or ``nn.Parameter`` if passed as one.

    Broadcasting rule: an attribute of shape ``(*K,)`` acts on particles shaped
    ``(*K, N, 6)``; particles shaped ``(N, 6)`` are broadcast to ``(*K, N, 6)``.
    Scalars (shape ``()``) act on every batch. Elements are never changed in place
    by tracking; :meth:`with_params` returns a new element.

    Args:
        name: Element name, unique inside a ``Beamline``.
        **params: Numeric attributes by name (see :meth:`_set_param`); those in
            ``nonnegative_params`` must be >= 0.

    Shapes:
        ``track``: ``(*K, N, 6) -> (*K, N, 6)``; ``transfer_map``: ``(*K, 7, 7)``.
    """

    #: Names of the numeric attributes, in spec order.
    param_names: ClassVar[tuple[str, ...]] = ()
    #: Parameters left out of :meth:`to_spec` while they are a scalar zero.
    optional_params: ClassVar[tuple[str, ...]] = ()
    #: ``(name, unit)`` of parameters that must be >= 0 (checked on construction).
    nonnegative_params: ClassVar[tuple[tuple[str, str], ...]] = ()
    #: Whether the map depends on ``z`` (an RF cavity's does). An element that
    #: does not may be given ``z = None`` by :meth:`track_columns` when nothing
    #: downstream needs ``z`` (screen images); it must then return ``None``
    #: there. True by default, so elements defined elsewhere always get ``z``.
    reads_z: ClassVar[bool] = True

    def __init__(self, name: str, **params: Tensor | float) -> None:
        super().__init__()
        if not isinstance(name, str) or not name:
            raise ValueError(f"Element name must be a non-empty string; got {name!r}.")
        self.name = name
        for key, value in params.items():
            self._set_param(key, value)
        for key, unit in self.nonnegative_params:
            check_nonnegative(f"{key} [{unit}]", getattr(self, key), self.owner)

    @property
    def owner(self) -> str:
        """``"<Type> '<name>'"``, the prefix of this element's error messages."""
        return f"{type(self).__name__} {self.name!r}"

    def _set_param(self, key: str, value: Tensor | float) -> None:
        """Store ``value`` as parameter (if ``nn.Parameter``) or buffer ``key``."""
        if isinstance(value, nn.Parameter):
            self.register_parameter(key, value)
        else:
            # Python numbers are kept in float64 so that float64 tracking is exact;
            # tracking casts attributes to the dtype of the particles.
            t = (
                value
                if isinstance(value, Tensor) and value.is_floating_point()
                else torch.as_tensor(value, dtype=torch.float64)
            )
            self.register_buffer(key, t)
        check_finite(key, getattr(self, key), self.owner)

    def params(self) -> dict[str, Tensor]:
        """The numeric attributes by name (the tensors themselves, not copies)."""
        return {k: getattr(self, k) for k in self.param_names}

    def _config(self) -> dict[str, Any]:
        """Non-numeric constructor arguments besides ``name`` (for copies)."""
        return {}

    def with_params(self, **values: Tensor | float) -> Element:
        """A new element with some numeric attributes replaced; ``self`` unchanged.

        Args:
            **values: New values by attribute name, e.g. ``k1=torch.tensor(2.0)``.

        Raises:
            ValueError: if a name is not one of ``param_names``.
        """
        unknown = sorted(set(values) - set(self.param_names))
        if unknown:
            raise ValueError(
                f"{type(self).__name__} has no parameter(s) {unknown}; "
                f"known parameters are {list(self.param_names)}."
            )
        kwargs = {**self.params(), **values}
        return type(self)(name=self.name, **kwargs, **self._config())

    @property
    def batch_shape(self) -> torch.Size:
        """Broadcast shape ``K`` of all numeric attributes."""
        return broadcast_shapes(*(p.shape for p in self.params().values()))

    def track(
        self, particles: Tensor, p0c: Tensor | float, species: Species = ELECTRON
    ) -> Tensor:
        """Track particles through the element.

        Args:
            particles: Bmad coordinates, shape ``(*K, N, 6)`` or ``(N, 6)``.
            p0c: Reference momentum times c [eV], shape ``()`` or ``(*K,)``.
            species: Tracked species (default electron).

        Returns:
            Coordinates at the exit, shape ``(*K, N, 6)``.

        The default validates the particles and runs :meth:`track_columns` when
        a subclass implements it (the built-in elements; see each class's
        docstring for its map).
        """
        if type(self).track_columns is Element.track_columns:
            raise NotImplementedError(
                f"{type(self).__name__} does not implement track."
            )
        check_particles(particles)
        particles = particles.to(compute_dtype(particles))  # float16: p0c overflows
        p0c = as_p0c(p0c, particles)
        coords = self.track_columns(tuple(particles.unbind(-1)), p0c, species)
        return stack_columns(coords)

    def track_columns(self, coords: Coords, p0c: Tensor, species: Species) -> Coords:
        """Unchecked tracking of coordinate columns (used by ``Beamline``).

        The columns ``(x, px, y, py, z, pz)`` are each broadcastable to
        ``(*K, N)`` and need not share a shape (a coordinate an element leaves
        alone is not expanded). ``p0c`` must already be a tensor of the
        particles' dtype. Inputs are not validated here. ``z`` is None when
        the caller does not need it and the element does not read it
        (:attr:`reads_z` False): then it is not computed. The default stacks the
        columns and calls :meth:`track`; built-in elements override it.
        """
        particles = torch.stack(torch.broadcast_tensors(*coords), dim=-1)
        out = self.track(particles, p0c, species)
        return tuple(out.unbind(-1))  # type: ignore[return-value]

    def _in_element_frame(
        self, coords: Coords, body: Callable[[Coords], Coords]
    ) -> Coords:
        """Apply ``body`` to the columns in the element's own frame.

        The frame is set by the attributes ``dx``, ``dy`` (offsets [m]) and
        ``tilt`` (roll [rad]) an element has (absent ones count as 0): lab ->
        element frame, ``body``, element -> lab frame. Without offsets and roll
        ``body`` sees the lab columns unchanged.
        """
        names = [n for n in ("dx", "dy", "tilt") if n in self.param_names]
        if all(is_zero(getattr(self, n)) for n in names):
            return body(coords)
        x, px, y, py, z, pz = coords
        zero = x.new_zeros(())
        frame = tuple(
            bcast(getattr(self, n), x) if n in names else zero
            for n in ("dx", "dy", "tilt")
        )
        x, px, y, py = to_element_frame(x, px, y, py, *frame)
        x, px, y, py, z, pz = body((x, px, y, py, z, pz))
        x, px, y, py = to_lab_frame(x, px, y, py, *frame)
        return x, px, y, py, z, pz

    def _map_params(self, p0c: Tensor | float, *names: str) -> tuple[Tensor, ...]:
        """The named attributes and ``p0c`` (last), broadcast to ``(*K,)``.

        All in the dtype and device of ``length`` (float64 for Python numbers);
        ``p0c`` is checked to be finite and > 0 eV.
        """
        p0c = as_p0c(p0c, self.length)
        return torch.broadcast_tensors(*(getattr(self, n).to(p0c) for n in names), p0c)

    def transfer_map(self, p0c: Tensor | float, species: Species = ELECTRON) -> Tensor:
        """Affine first-order map about the reference orbit, ``(*K, 7, 7)``.

        ``u_out ~ A[..., :6, :6] @ u_in + A[..., :6, 6]`` (see the class docs).
        """
        raise NotImplementedError(
            f"{type(self).__name__} does not implement transfer_map."
        )

    def linear_map_is_exact(self, monochromatic: bool) -> bool:
        """Whether :meth:`transfer_map` reproduces :meth:`track` for such beams.

        True means: for particles with ``pz = 0`` (``monochromatic``) or any
        ``pz`` (not ``monochromatic``), ``track`` gives the affine map's
        ``x, px, y, py, pz`` up to the paraxial terms of drifts (relative
        ``(px^2 + py^2) / 2``, ~1e-8 for typical beams) and ``z`` up to its
        second-order path-length terms. Callers that need images (the fast
        linear path) must track when this is False. The default is False.
        """
        return False

    def to_spec(self) -> dict[str, Any]:
        """A JSON-serialisable dict ``{"type", "name", <params>}`` for this element."""
        spec: dict[str, Any] = {"type": type(self).__name__, "name": self.name}
        for k, v in self.params().items():
            v = v.detach().cpu()
            if k in self.optional_params and v.dim() == 0 and v.item() == 0.0:
                continue
            spec[k] = v.item() if v.dim() == 0 else v.tolist()
        return spec

    def extra_repr(self) -> str:
        parts = [f"name={self.name!r}"]
        for k, v in self.params().items():
            parts.append(
                f"{k}={v.item():g}" if v.dim() == 0 else f"{k}{tuple(v.shape)}"
            )
        return ", ".join(parts)
