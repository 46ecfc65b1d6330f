"""Screen geometry: the one pixel-centre helper against the analytic centres."""

from __future__ import annotations

import pytest
import torch

from diffaccel.dynamics import Screen

F64 = torch.float64


def test_pixel_centers_are_the_analytic_centres() -> None:
    # non-square, off-centre, anisotropic: a swapped (x, y) order, H/W or
    # pixel size would change the numbers
    scr = Screen("S", shape=(3, 4), pixel_size=(1e-3, 2e-3), center=(5e-3, -1e-3))
    xs, ys = scr.pixel_centers(dtype=F64)
    # x_j = cx + (j - (W - 1) / 2) psx, y_i = cy + (i - (H - 1) / 2) psy
    assert xs.tolist() == pytest.approx([3.5e-3, 4.5e-3, 5.5e-3, 6.5e-3], abs=1e-15)
    assert ys.tolist() == pytest.approx([-3e-3, -1e-3, 1e-3], abs=1e-15)
    assert xs.dtype == ys.dtype == F64


def test_a_particle_at_a_pixel_centre_lights_that_pixel() -> None:
    scr = Screen("S", shape=(5, 7), pixel_size=(1e-3, 0.5e-3), center=(1e-3, 2e-3))
    xs, ys = scr.pixel_centers(dtype=F64)
    p = torch.zeros(1, 6, dtype=F64)
    p[0, 0], p[0, 2] = xs[5], ys[1]
    img = scr.image(p, method="cic")
    assert img[1, 5].item() == pytest.approx(1.0)
    assert img.sum().item() == pytest.approx(1.0)


def test_pixel_centers_without_geometry_is_one_line_error() -> None:
    with pytest.raises(ValueError, match="no geometry"):
        Screen("S").pixel_centers()
