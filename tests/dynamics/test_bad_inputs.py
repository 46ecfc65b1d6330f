"""Bad inputs to the dynamics API: clear errors instead of raw tracebacks."""

from __future__ import annotations

import pytest
import torch

from diffaccel.dynamics import (
    Beamline,
    emittance,
    emittance_6d,
    finite_checks,
    gaussian_blur,
    kde_image,
)

SPEC = [
    {"type": "Quadrupole", "name": "Q1", "length": 0.1, "k1": 0.0},
    {"type": "Drift", "name": "D1", "length": 1.0},
    {"type": "Screen", "name": "SCREEN"},
]


@pytest.mark.parametrize(
    ("value", "got"),
    [("1.0", "str"), (None, "NoneType"), (True, "bool"), ([1.0, "a"], "list")],
)
def test_spec_values_must_be_real_numbers(value: object, got: str) -> None:
    spec = [dict(SPEC[0]), {"type": "Drift", "name": "D1", "length": value}]
    with pytest.raises(
        ValueError, match=rf"\(Drift 'D1'\): length must be a real .*{got}"
    ):
        Beamline.from_spec(spec)


def test_spec_lists_of_numbers_still_batch() -> None:
    line = Beamline.from_spec([{"type": "Drift", "name": "D1", "length": [0.5, 1.0]}])
    assert line["D1"].length.shape == (2,)


@pytest.mark.parametrize("frequency", [0.0, -1e9])
def test_spec_tdc_needs_positive_frequency(frequency: float) -> None:
    spec = [{"type": "TransverseDeflectingCavity", "name": "T", "frequency": frequency}]
    with pytest.raises(ValueError, match=r"'T'\): frequency must be > 0 Hz"):
        Beamline.from_spec(spec)


def test_track_batch_shapes_must_broadcast() -> None:
    line = Beamline.from_spec(SPEC)
    k1 = torch.zeros(3, 1)
    with pytest.raises(ValueError, match=r"particles \(4, 100, 6\).*settings \(3, 1\)"):
        line.track(torch.zeros(4, 100, 6), 43e6, settings=k1, names=["Q1.k1"])
    with pytest.raises(ValueError, match="broadcastable batch shapes"):
        line.screen_images(torch.zeros(4, 100, 6), 43e6, settings=k1, names=["Q1.k1"])


@pytest.mark.parametrize("p0c", ["43e6", None, True, 1j])
def test_track_p0c_must_be_real(p0c: object) -> None:
    with pytest.raises(ValueError, match=r"p0c .* must be a real number"):
        Beamline.from_spec(SPEC).track(torch.zeros(10, 6), p0c)  # type: ignore[arg-type]


def test_track_refuses_zero_momentum_only_with_checks() -> None:
    beam = torch.zeros(10, 6)
    beam[3, 5] = -1.0
    line = Beamline.from_spec(SPEC)
    with pytest.raises(ValueError, match=r"1 particle\(s\) with pz <= -1"):
        line.track(beam, 43e6)
    with finite_checks(False):  # no device read: not checked
        line.track(beam, 43e6)


def test_image_shapes() -> None:
    x = torch.zeros(100)
    with pytest.raises(ValueError, match=r"must broadcast .* \(50,\), \(100,\)"):
        kde_image(x[:50], x, (16, 16), 1e-3)
    with pytest.raises(ValueError, match=r"no particles \(N = 0"):
        kde_image(x[:0], x[:0], (16, 16), 1e-3)
    with pytest.raises(ValueError, match=r"image must be a tensor shaped .*\(16,\)"):
        gaussian_blur(torch.rand(16), 1.0, 1e-3)


@pytest.mark.parametrize("n", [0, 1])
def test_emittance_needs_two_particles(n: int) -> None:
    with pytest.raises(ValueError, match="need at least 2 particle"):
        emittance(torch.zeros(n, 6))
    with pytest.raises(ValueError, match="need at least 2 particle"):
        emittance_6d(torch.zeros(n, 6))
