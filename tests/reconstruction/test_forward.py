from __future__ import annotations

import pytest
import torch

from diffaccel.dynamics import Beamline
from diffaccel.reconstruction import ScreenForwardModel

SPEC = [
    {"type": "Quadrupole", "name": "Q1", "length": 0.1, "k1": 0.0},
    {"type": "Drift", "name": "D1", "length": 1.0},
    {"type": "Screen", "name": "S", "shape": [32, 32], "pixel_size": [1e-3, 1e-3]},
]
K1 = torch.tensor([[-10.0], [0.0], [7.0]], dtype=torch.float64)


def _model(blur: float = 1.0) -> ScreenForwardModel:
    return ScreenForwardModel(
        Beamline.from_spec(SPEC), ["Q1.k1"], 43e6, blur_pixels=blur
    )


def test_transfer_matrix_of_drift_setting() -> None:
    r = _model().transfer_matrices(torch.tensor([[0.0]]))[0]
    # k1 = 0: a 1.1 m drift; central differences of a linear map: round-off only
    assert r[0, 1].item() == pytest.approx(1.1, rel=1e-6)
    assert r[2, 3].item() == pytest.approx(1.1, rel=1e-6)
    assert r[0, 0].item() == pytest.approx(1.0, rel=1e-6)


def test_linear_maps_reproduce_tracking_for_pz_zero(gaussian_beam) -> None:
    fwd = _model(blur=0.0)
    x = gaussian_beam.float()
    exact = fwd.images(x, K1)
    lin = fwd.images_linear(x, fwd.transfer_matrices(K1))
    # only the px^2 ~ 1e-6 terms of the exact drift differ: float32 level
    assert (exact - lin).abs().max() < 1e-5


def test_images_sum_to_fraction_on_screen(gaussian_beam) -> None:
    fwd = _model(blur=0.0)
    x = gaussian_beam.float().clone()
    x[:1000, 0] += 0.1  # 25 % of the particles 10 cm off axis (screen: +-16 mm)
    img = fwd.images(x, K1)
    assert img.sum((-2, -1)).tolist() == pytest.approx([0.75] * 3, abs=1e-5)


def test_predictions_follow_the_settings(gaussian_beam) -> None:
    fwd = _model()
    x = gaussian_beam.float()
    a = fwd.images(x, K1[:1])
    b = fwd.images(x, K1[2:])
    again = fwd.images(x, K1[:1])
    assert torch.equal(a, again)  # no state carried between calls
    assert (a - b).abs().sum() > 0.1


def test_blur_adds_the_point_spread_variance(gaussian_beam) -> None:
    # variance of the image = beam variance + blur^2 (CIC's 1/6 px^2 included)
    x = gaussian_beam.float()
    fwd = _model(blur=2.0)
    img = fwd.images(x, K1[1:2])[0].double()
    xs, _ = fwd.pixel_axes()
    px = img.sum(0) / img.sum()
    var = (px * xs**2).sum() - (px * xs).sum() ** 2
    beam = fwd.track_to_screen(gaussian_beam, K1[1:2])[0, :, 0].var()
    # 2 px blur = 4e-6 m^2; tolerance: discretisation of a 2-pixel Gaussian
    assert (var - beam).item() == pytest.approx(4e-6, rel=0.05)


@pytest.mark.parametrize(
    ("names", "match"),
    [(["Q9.k1"], "no element 'Q9'"), (["Q1.k7"], "no parameter 'k7'")],
    ids=["unknown-element", "unknown-parameter"],
)
def test_unknown_setting_names(names: list[str], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        ScreenForwardModel(Beamline.from_spec(SPEC), names, 43e6)


def test_bad_settings_and_p0c() -> None:
    fwd = _model()
    with pytest.raises(ValueError, match="shape"):
        fwd.check_settings(torch.zeros(3, 2))
    with pytest.raises(ValueError, match="NaN"):
        fwd.check_settings(torch.tensor([[float("nan")]]))
    with pytest.raises(ValueError, match="p0c"):
        ScreenForwardModel(Beamline.from_spec(SPEC), ["Q1.k1"], -1.0)


def test_spec_round_trip() -> None:
    fwd = _model(blur=1.5)
    back = ScreenForwardModel.from_spec(fwd.to_spec())
    assert back.to_spec() == fwd.to_spec()
