"""Preisach mesh: geometry, areas, validation."""

from __future__ import annotations

import pytest
import torch

from diffaccel.hysteresis import PreisachMesh


@pytest.mark.parametrize(
    ("n", "refine", "band", "expected"),
    [
        (1, 0, 1, 1),
        (10, 0, 1, 55),
        (44, 0, 1, 990),
        (200, 0, 1, 20100),
        (6, 2, 2, None),
    ],
    ids=["n1", "n10", "n44", "n200", "refined"],
)
def test_triangular_covers_half_square(n, refine, band, expected) -> None:
    mesh = PreisachMesh.triangular(n, refine=refine, band=band)
    if expected is not None:
        assert len(mesh) == expected
    # areas tile the half square exactly (float64 round-off of the sum)
    assert abs(float(mesh.area.sum()) - 0.5) < 1e-12
    assert (mesh.beta <= mesh.alpha).all()
    assert (mesh.beta >= 0).all() and (mesh.alpha <= 1).all()
    assert (mesh.area > 0).all()


def test_refinement_is_finer_near_diagonal() -> None:
    coarse = PreisachMesh.triangular(6)
    fine = PreisachMesh.triangular(6, refine=2, band=2)
    near = lambda m: ((m.alpha - m.beta) < 2 / 6).sum()  # noqa: E731
    far = lambda m: ((m.alpha - m.beta) > 2 / 6).sum()  # noqa: E731
    assert near(fine) > 4 * near(coarse)
    assert far(fine) == far(coarse)


def test_user_points_get_equal_areas() -> None:
    mesh = PreisachMesh.from_points(torch.tensor([0.5, 0.9]), torch.tensor([0.1, 0.2]))
    assert torch.equal(mesh.area, torch.tensor([0.25, 0.25]))


@pytest.mark.parametrize(
    ("alpha", "beta", "area", "match"),
    [
        ([0.5, 0.6], [0.1], None, "equal shape"),
        ([0.2], [0.5], None, "beta <= alpha"),
        ([1.5], [0.5], None, r"range \[0, 1\]"),
        ([float("nan")], [0.1], None, "NaN"),
        ([0.5], [0.1], [0.0], "positive"),
        ([], [], None, "at least one"),
    ],
    ids=["shape", "beta-above-alpha", "outside", "nan", "zero-area", "empty"],
)
def test_bad_points_raise(alpha, beta, area, match) -> None:
    area_t = None if area is None else torch.tensor(area)
    with pytest.raises(ValueError, match=match):
        PreisachMesh(torch.tensor(alpha), torch.tensor(beta), area_t)


def test_bad_triangular_arguments_raise() -> None:
    with pytest.raises(ValueError, match="n >= 1"):
        PreisachMesh.triangular(0)
    with pytest.raises(ValueError, match="refine >= 0"):
        PreisachMesh.triangular(4, refine=-1)


def test_to_changes_dtype() -> None:
    mesh = PreisachMesh.triangular(4).to(dtype=torch.float32)
    assert mesh.alpha.dtype == torch.float32 and mesh.area.dtype == torch.float32


@pytest.mark.parametrize(
    ("n", "refine", "band"),
    [(1, 0, 1), (9, 0, 1), (6, 2, 2)],
    ids=["n1", "n9", "refined"],
)
def test_mirror_index_maps_to_mirror_points(n: int, refine: int, band: int) -> None:
    mesh = PreisachMesh.triangular(n, refine=refine, band=band)
    mirror = mesh.mirror_index()
    assert torch.equal(mirror[mirror], torch.arange(len(mesh)))
    # (alpha, beta) -> (1 - beta, 1 - alpha), to float64 round-off
    torch.testing.assert_close(mesh.alpha[mirror], 1 - mesh.beta, rtol=0, atol=1e-12)
    torch.testing.assert_close(mesh.beta[mirror], 1 - mesh.alpha, rtol=0, atol=1e-12)
    torch.testing.assert_close(mesh.area[mirror], mesh.area, rtol=1e-12, atol=0)


def test_mirror_index_rejects_asymmetric_mesh() -> None:
    mesh = PreisachMesh.from_points([0.5, 0.9], [0.1, 0.2])
    with pytest.raises(ValueError, match="no mirror image"):
        mesh.mirror_index()
