"""Diagnostic screen: a zero-length marker that renders images on request."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from diffaccel.dynamics._validate import check_particles, compute_dtype
from diffaccel.dynamics.elements.element import Coords, Element
from diffaccel.dynamics.images import _geometry, cic_image, kde_image, pixel_centers
from diffaccel.dynamics.species import ELECTRON, Species

__all__ = ["Screen"]

_METHODS = ("cic", "kde")


class Screen(Element):
    """A zero-length screen: tracking passes particles unchanged; ``image`` renders.

    The screen keeps no state from tracking: record the particles at the screen
    with ``Beamline.track_screens`` and pass them to :meth:`image`.

    Args:
        name: Element name.
        shape: ``(H, W)`` pixels, or ``None`` until the calibration is known.
        pixel_size: ``(pixel_size_x, pixel_size_y)`` [m], or ``None``.
        center: ``(center_x, center_y)`` of the screen in the beam frame [m].

    Shapes:
        ``track``: identity; ``image``: ``(*K, N, 6) -> (*K, H, W)`` with
        ``image[..., i, j]`` at ``y = center_y + (i - (H - 1) / 2) * pixel_size_y``,
        ``x = center_x + (j - (W - 1) / 2) * pixel_size_x``.

    Example:
        >>> import torch
        >>> scr = Screen("SCREEN", shape=(64, 64), pixel_size=(1e-3, 1e-3))
        >>> scr.image(torch.zeros(2, 100, 6), method="cic").shape
        torch.Size([2, 64, 64])
    """

    param_names = ()
    reads_z = False

    def __init__(
        self,
        name: str,
        shape: Sequence[int] | None = None,
        pixel_size: Sequence[float] | float | None = None,
        center: Sequence[float] = (0.0, 0.0),
    ) -> None:
        super().__init__(name)
        if (shape is None) != (pixel_size is None):
            raise ValueError(
                f"Screen {name!r}: give both shape and pixel_size, or neither."
            )
        if shape is not None:
            h, w, psx, psy, cx, cy = _geometry(shape, pixel_size, center)
            self.shape: tuple[int, int] | None = (h, w)
            self.pixel_size: tuple[float, float] | None = (psx, psy)
            self.center: tuple[float, float] = (cx, cy)
        else:
            self.shape = None
            self.pixel_size = None
            _, _, _, _, cx, cy = _geometry((1, 1), 1.0, center)
            self.center = (cx, cy)
        self._set_param("length", 0.0)

    def _config(self) -> dict[str, Any]:
        return {
            "shape": self.shape,
            "pixel_size": self.pixel_size,
            "center": self.center,
        }

    def track(
        self, particles: Tensor, p0c: Tensor | float, species: Species = ELECTRON
    ) -> Tensor:
        """Return ``particles`` unchanged (a screen does not act on the beam)."""
        check_particles(particles, check_finite=False)
        return particles

    def track_columns(self, coords: Coords, p0c: Tensor, species: Species) -> Coords:
        """Return the columns unchanged."""
        return coords

    def linear_map_is_exact(self, monochromatic: bool) -> bool:
        """Always: a screen does not act on the beam."""
        return True

    def pixel_centers(
        self,
        *,
        dtype: torch.dtype | None = None,
        device: torch.device | str | None = None,
    ) -> tuple[Tensor, Tensor]:
        """Pixel-centre coordinates ``(xs, ys)`` [m], shapes ``(W,)`` and ``(H,)``.

        ``xs[j]`` is the x of image column ``j``, ``ys[i]`` the y of row ``i``
        (see the class docstring); the one place the project computes them.

        Raises:
            ValueError: if the screen has no geometry.

        Example:
            >>> Screen("S", shape=(3, 2), pixel_size=(1.0, 2.0)).pixel_centers()
            (tensor([-0.5000,  0.5000]), tensor([-2.,  0.,  2.]))
        """
        self._check_geometry()
        return pixel_centers(
            self.shape, self.pixel_size, self.center, dtype=dtype, device=device
        )

    def _check_geometry(self) -> None:
        if self.shape is None or self.pixel_size is None:
            raise ValueError(
                f"Screen {self.name!r} has no geometry; build it with shape and "
                "pixel_size, or use Beamline.with_screen(...)."
            )

    def image(
        self,
        particles: Tensor,
        method: str = "cic",
        bandwidth: Sequence[float] | float | None = None,
        blur_sigma: Sequence[float] | float | None = None,
        weights: Tensor | None = None,
    ) -> Tensor:
        """Image of particles at the screen, shape ``(*K, H, W)``.

        Pixel values are (sum of weights in the pixel) / (total weight), so the
        image sum is the fraction of the beam landing on the screen.

        Args:
            particles: Coordinates at the screen, shape ``(*K, N, 6)``.
            method: ``"cic"`` (bilinear cloud-in-cell, see
                :func:`~diffaccel.dynamics.images.cic_image`) or ``"kde"``
                (Gaussian KDE, see :func:`~diffaccel.dynamics.images.kde_image`).
            bandwidth: KDE kernel rms [m]; default one pixel. Only for ``"kde"``.
            blur_sigma: Gaussian blur rms [m] after CIC deposition. Only ``"cic"``.
            weights: Optional particle weights broadcastable to ``(*K, N)``.

        Raises:
            ValueError: if the screen has no geometry, ``method`` is unknown or
                an option does not belong to the method.
        """
        check_particles(particles, check_finite=False)  # x, y are checked below
        particles = particles.to(compute_dtype(particles))  # float16 counts saturate
        x, y = particles[..., 0:3:2].unbind(-1)
        return self.image_xy(x, y, method, bandwidth, blur_sigma, weights)

    def image_xy(
        self,
        x: Tensor,
        y: Tensor,
        method: str = "cic",
        bandwidth: Sequence[float] | float | None = None,
        blur_sigma: Sequence[float] | float | None = None,
        weights: Tensor | None = None,
    ) -> Tensor:
        """Image from positions ``x, y`` [m] shaped ``(*K, N)``; see :meth:`image`."""
        self._check_geometry()
        if method == "cic":
            if bandwidth is not None:
                raise ValueError("bandwidth applies to method='kde' only.")
            return cic_image(
                x, y, self.shape, self.pixel_size, self.center, weights, blur_sigma
            )
        if method == "kde":
            if blur_sigma is not None:
                raise ValueError("blur_sigma applies to method='cic' only.")
            return kde_image(
                x, y, self.shape, self.pixel_size, self.center, bandwidth, weights
            )
        raise ValueError(f"Unknown image method {method!r}; choose one of {_METHODS}.")

    def to_spec(self) -> dict[str, Any]:
        """Spec dict; includes the geometry when it is set."""
        spec: dict[str, Any] = {"type": "Screen", "name": self.name}
        if self.shape is not None:
            spec["shape"] = list(self.shape)
            spec["pixel_size"] = list(self.pixel_size)
            spec["center"] = list(self.center)
        return spec
