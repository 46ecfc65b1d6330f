"""Number boundaries of the public APIs: dtypes refused or computed wider."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from diffaccel.data import FormatError, make_synthetic_quad_scan
from diffaccel.dynamics import (
    Beamline,
    bmad_to_openpmd,
    emittance,
    emittance_4d,
    normalized_emittance,
    rms_sizes,
)
from diffaccel.hysteresis import PreisachModel, fit_preisach
from diffaccel.hysteresis.mesh import PreisachMesh
from diffaccel.reconstruction import (
    ScreenForwardModel,
    beam_moments,
    image_errors,
)


@pytest.fixture(scope="module")
def scan():
    return make_synthetic_quad_scan(
        "gaussian", n_particles=500, n_settings=3, screen_shape=(8, 8)
    )


def _beam(dtype: torch.dtype) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    sig = torch.tensor([1e-3, 1e-4, 1e-3, 1e-4, 1e-3, 1e-3], dtype=torch.float64)
    return (torch.randn(50_000, 6, generator=g, dtype=torch.float64) * sig).to(dtype)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_particles_give_float32_moments(dtype) -> None:
    half = _beam(dtype)
    wide = half.double()  # the same numbers
    eps = emittance(half, "x")
    assert eps.dtype == torch.float32
    # float16 results were +19 % (emittance) and 0 (4D emittance)
    assert float(eps) == pytest.approx(float(emittance(wide, "x")), rel=1e-5)
    assert float(emittance_4d(half)) == pytest.approx(
        float(emittance_4d(wide)), rel=1e-5
    )
    assert rms_sizes(half).dtype == torch.float32
    assert float(normalized_emittance(half, 43e6)) > 0
    cols = bmad_to_openpmd(half, 43e6)  # 43e6 eV/c is beyond float16
    assert bool(torch.isfinite(cols["pz"]).all())


@pytest.mark.parametrize(
    "bad, what",
    [
        (torch.tensor([0.0, 1.0j, 0.5]), "complex"),
        (torch.tensor([False, True, False]), "booleans"),
        (np.array([0.0, 1.0j, 0.5]), "complex"),
        ([True, False, True], "booleans"),
    ],
)
def test_preisach_api_refuses_complex_and_boolean_inputs(bad, what) -> None:
    model = PreisachModel(PreisachMesh.triangular(n=6), input_range=(0.0, 1.0))
    with pytest.raises(ValueError, match=rf"{what} .*not cast"):
        model(bad)
    with pytest.raises(ValueError, match="not cast"):
        model.predict(torch.tensor([0.2, 0.3]), history=bad)
    u = torch.linspace(0, 1, 12)
    with pytest.raises(ValueError, match="not cast"):
        fit_preisach(model, u, torch.zeros(12, dtype=torch.complex128) + u, steps=1)


def test_reconstruction_api_refuses_complex_and_boolean_inputs(scan) -> None:
    fwd = ScreenForwardModel.from_dataset(scan)
    with pytest.raises(ValueError, match=r"settings must be real.*complex"):
        fwd.check_settings(torch.tensor([[1.0 + 1j]]))
    with pytest.raises(ValueError, match=r"settings must be real.*booleans"):
        fwd.check_settings(torch.tensor([[True]]))
    img = scan.mean_images()
    with pytest.raises(ValueError, match="predicted images must be real"):
        image_errors(img.to(torch.complex64), img)
    with pytest.raises(ValueError, match=r"particles must be real.*booleans"):
        beam_moments(torch.ones(10, 6, dtype=torch.bool))


@pytest.mark.parametrize(
    "scale, dtype, message",
    [
        (1e40, torch.float64, "beyond float32's largest"),
        (1e-33, torch.float64, "subnormal"),
        (1e7, torch.float16, "float16 holds at most 65504"),
    ],
)
def test_images_are_checked_before_the_float32_cast(scan, scale, dtype, message):
    images = (scan.images.double() * scale).to(dtype)
    with pytest.raises(FormatError, match=message):
        dataclasses.replace(scan, images=images)


def test_float16_and_float64_images_within_float32_are_kept(scan) -> None:
    for dtype in (torch.float16, torch.float64):
        ds = dataclasses.replace(scan, images=scan.images.to(dtype))
        assert ds.images.dtype == torch.float32
        torch.testing.assert_close(
            ds.images, scan.images.to(dtype).float(), rtol=0, atol=0
        )
    # a pixel far below float32's resolution of its image's peak becomes 0
    images = scan.images.double().clone()
    images[0, 0, 0, 0] = 1e-42
    ds = dataclasses.replace(scan, images=images)
    assert float(ds.images[0, 0, 0, 0]) == 0.0


def test_half_precision_particles_are_tracked_in_float32() -> None:
    spec = [
        {
            "type": "TransverseDeflectingCavity",
            "name": "T",
            "length": 0.2,
            "voltage": 4e6,
            "frequency": 1.3e9,
            "phase": 0.0,
            "tilt": 0.0,
        },
        {"type": "Drift", "name": "D", "length": 1.0},
        {"type": "Screen", "name": "S"},
    ]
    line = Beamline.from_spec(spec)
    half = _beam(torch.float16)[:2000]
    out = line.track(half, p0c=43e6)
    assert out.dtype == torch.float32
    # the same numbers tracked in float64 (float16 p0c was inf)
    ref = line.track(half.double(), p0c=43e6)
    torch.testing.assert_close(out.double(), ref, rtol=1e-5, atol=1e-9)
