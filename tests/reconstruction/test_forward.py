from __future__ import annotations

import math

import pytest
import torch

from diffaccel.dynamics import Beamline
from diffaccel.dynamics.images import blur_variance, gaussian_blur
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


def test_transfer_map_of_drift_setting() -> None:
    r = _model().transfer_maps(torch.tensor([[0.0]]))[0]
    # k1 = 0: a 1.1 m drift, composed analytically: round-off only
    assert r.shape == (7, 7)
    assert r[0, 1].item() == pytest.approx(1.1, rel=1e-14)
    assert r[2, 3].item() == pytest.approx(1.1, rel=1e-14)
    assert r[0, 0].item() == 1.0
    assert r[:6, 6].abs().max().item() == 0.0  # aligned: no orbit offset


def test_linear_maps_reproduce_tracking_for_pz_zero(gaussian_beam) -> None:
    fwd = _model(blur=0.0)
    x = gaussian_beam.float()
    exact = fwd.images(x, K1)
    lin = fwd.images_linear(x, fwd.linear_maps(K1, monochromatic=True))
    # only the px^2 ~ 1e-6 terms of the exact drift differ: float32 level
    assert (exact - lin).abs().max() < 1e-5


def _centroid(images: torch.Tensor, fwd: ScreenForwardModel) -> torch.Tensor:
    xs, ys = fwd.screen.pixel_centers(dtype=torch.float64)
    img = images.double() / images.double().sum((-2, -1), keepdim=True)
    return torch.stack([(img.sum(-2) * xs).sum(-1), (img.sum(-1) * ys).sum(-1)], -1)


@pytest.mark.parametrize("scanned", [False, True], ids=["fixed-dx", "scanned-Q1.dx"])
def test_quad_offset_moves_linear_and_tracked_images_alike(
    scanned: bool, gaussian_beam
) -> None:
    # a 2 mm horizontal quadrupole offset: the linear path must shift the images
    # exactly as tracking does (it used to drop dx and train on centred images)
    k1 = torch.tensor([-10.0, 0.0, 7.0], dtype=torch.float64)
    if scanned:
        fwd = ScreenForwardModel(
            Beamline.from_spec(SPEC), ["Q1.k1", "Q1.dx"], 43e6, blur_pixels=0.0
        )
        sets = torch.stack([k1, torch.full_like(k1, 2e-3)], -1)
    else:
        spec = [{**SPEC[0], "dx": 2e-3}, *SPEC[1:]]
        fwd = ScreenForwardModel(
            Beamline.from_spec(spec), ["Q1.k1"], 43e6, blur_pixels=0.0
        )
        sets = k1[:, None]
    x = gaussian_beam.float()
    maps = fwd.linear_maps(sets, monochromatic=True)
    assert maps is not None
    exact = fwd.images(x, sets)
    lin = fwd.images_linear(x, maps)
    # same particles in both paths: equal up to the drift's px^2 terms (float32)
    assert (exact - lin).abs().max() < 1e-5
    aligned = _model(blur=0.0).images(x, k1[:, None])
    shift = _centroid(exact, fwd) - _centroid(aligned, fwd)
    # the shift is the map's orbit offset (the beam's own centroid cancels; CIC
    # keeps first moments exactly): at k1 = -10 1/m^2 the defocusing quad pushes
    # the beam, 2 mm off its axis, to about -2.0 mm; at k1 = 0 nothing moves
    torch.testing.assert_close(shift[:, 0], maps[:, 0, 6], rtol=0, atol=2e-6)
    assert shift[0, 0].item() < -1.5e-3
    assert abs(shift[1, 0].item()) < 2e-6
    assert shift[:, 1].abs().max().item() < 2e-6


def test_linear_maps_refused_where_not_exact() -> None:
    spec = [
        SPEC[0],
        {
            "type": "TransverseDeflectingCavity",
            "name": "T",
            "length": 0.1,
            "voltage": 0.0,
            "frequency": 1.3e9,
            "tilt": 1.5707963267948966,
        },
        *SPEC[1:],
    ]
    fwd = ScreenForwardModel(Beamline.from_spec(spec), ["Q1.k1", "T.voltage"], 43e6)
    off = torch.tensor([[1.0, 0.0], [2.0, 0.0]], dtype=torch.float64)
    on = torch.tensor([[1.0, 0.0], [2.0, 4e6]], dtype=torch.float64)
    assert fwd.linear_maps(off, monochromatic=True) is not None
    assert fwd.linear_maps(on, monochromatic=True) is None  # sin(k z): track
    assert fwd.linear_maps(off, monochromatic=False) is None  # chromatic: track


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
    xs, _ = fwd.screen.pixel_centers(dtype=torch.float64)
    px = img.sum(0) / img.sum()
    var = (px * xs**2).sum() - (px * xs).sum() ** 2
    beam = fwd.track_to_screen(gaussian_beam, K1[1:2])[0, :, 0].var()
    # 2 px blur = 4e-6 m^2; tolerance: discretisation of a 2-pixel Gaussian
    assert (var - beam).item() == pytest.approx(4e-6, rel=0.05)


def _added_variance_px2(fwd: ScreenForwardModel, beam: torch.Tensor, img=None) -> float:
    """Image x variance minus the tracked beam's [pixels^2] at k1 = 0."""
    if img is None:
        img = fwd.images(beam, K1[1:2])[0]
    xs, _ = fwd.screen.pixel_centers(dtype=torch.float64)
    px = img.double().sum(0) / img.double().sum()
    var = (px * xs**2).sum() - (px * xs).sum() ** 2
    x = fwd.track_to_screen(beam, K1[1:2])[0, :, 0]
    return float(var - x.var(correction=0)) / fwd.screen.pixel_size[0] ** 2


@pytest.mark.parametrize("blur", [0.5, 0.7, 1.0])
def test_sub_pixel_blur_adds_its_variance(gaussian_beam, blur: float) -> None:
    # blur_pixels is the total point-spread rms below one pixel too: the
    # Gaussian after cloud-in-cell is sized by the variance its sampled kernel
    # has (a nominal 0.29 pixel adds 0.004 pixel^2 instead of 0.083)
    added = _added_variance_px2(_model(blur), gaussian_beam)
    assert added == pytest.approx(blur**2, rel=0.02)


@pytest.mark.parametrize(
    ("blur", "smoothing"),
    [(1.0, 0.3), (1.0, 0.58), (math.sqrt(1 / 12), 0.6), (math.sqrt(1 / 12), 1.0)],
)
def test_smoothing_adds_the_same_variance_as_to_measured_images(
    gaussian_beam, blur: float, smoothing: float
) -> None:
    # the image term smooths the measured images with gaussian_blur and the
    # simulated ones through image_smoothing: both must gain the same variance,
    # or the fit moves the beam by the difference where its spot is smallest
    # (0.09 against 0.002 pixel^2 for a nominal 0.3-pixel smoothing)
    smoothed = ScreenForwardModel(
        Beamline.from_spec(SPEC),
        ["Q1.k1"],
        43e6,
        blur_pixels=blur,
        image_smoothing=torch.full((1, 2), smoothing),
    )
    added = _added_variance_px2(smoothed, gaussian_beam)
    # a measured image with a point spread of rms `blur` gains this much
    measured = blur**2 + float(blur_variance(smoothing))
    assert added == pytest.approx(measured, abs=2e-3)
    if blur**2 > 1 / 6:  # the model's own point spread, then the same smoothing
        plain = _model(blur)
        img = plain.images(gaussian_beam, K1[1:2])
        again = gaussian_blur(img, smoothing * 1e-3, plain.screen.pixel_size)[0]
        assert _added_variance_px2(plain, gaussian_beam, again) == pytest.approx(
            added, abs=2e-3
        )


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


def _awa6d_forwards() -> tuple[list[ScreenForwardModel], list[torch.Tensor]]:
    from diffaccel.data.synthetic import AWA6D_BEAMLINES

    forwards, settings = [], []
    for spec in AWA6D_BEAMLINES.values():
        spec = [dict(e) for e in spec]
        spec[-1].update(shape=[24, 24], pixel_size=[8e-4, 8e-4])
        forwards.append(
            ScreenForwardModel(
                Beamline.from_spec(spec),
                ["SCAN_QUAD.k1", "SCAN_TDC.voltage"],
                43.36e6,
                blur_pixels=0.8,
            )
        )
        k1 = torch.tensor([-6.0, -6.0, 0.0, 6.0, 6.0], dtype=torch.float64)
        volts = torch.tensor([0.0, 4e6, 0.0, 0.0, 4e6], dtype=torch.float64)
        settings.append(torch.stack([k1, volts], -1))
    return forwards, settings


@pytest.mark.parametrize("rows", [None, ([0, 1, 2, 3, 4], [1, 4]), ([0, 2], [0, 3, 4])])
def test_shared_upstream_gives_each_scans_images(gaussian_beam, rows) -> None:
    from diffaccel.reconstruction.forward import SharedUpstream

    forwards, settings = _awa6d_forwards()
    if rows is not None:
        settings = [s[r] for s, r in zip(settings, rows, strict=True)]
    x = gaussian_beam[:2000] * 0.3
    g = torch.Generator().manual_seed(0)
    x[:, 4:] = torch.randn(2000, 2, generator=g, dtype=x.dtype) * 1e-3  # z, pz
    x = x.float().requires_grad_(True)
    shared = SharedUpstream.build(forwards, settings)
    # quadrupole and drift tracked once per distinct k1, cavity and drift once
    # per distinct (k1, voltage) row
    every = torch.cat(settings)
    (first, quad), (index, cavity) = shared.stages
    assert first is None and [e.name for e in quad] == ["SCAN_QUAD", "D1"]
    assert [e.name for e in cavity] == ["SCAN_TDC", "D2"]
    assert quad["SCAN_QUAD"].k1.shape == (len(every[:, 0].unique()),)
    assert cavity["SCAN_TDC"].voltage.shape == (len(every.unique(dim=0)),)
    assert index is not None and len(index) == len(every.unique(dim=0))
    images = shared(x)
    (sum(i.square().sum() for i in images)).backward()
    grad = x.grad.clone()
    x.grad = None
    plain = [f.images(x, s) for f, s in zip(forwards, settings, strict=True)]
    (sum(i.square().sum() for i in plain)).backward()
    for a, b in zip(images, plain, strict=True):
        assert a.shape == b.shape
        assert torch.equal(a, b)  # the same arithmetic, only shared
    # float32 gradients summed in another order
    assert torch.allclose(grad, x.grad, rtol=1e-5, atol=1e-6 * x.grad.abs().max())


def test_shared_upstream_none_when_nothing_is_shared() -> None:
    from diffaccel.reconstruction.forward import SharedUpstream

    forwards, settings = _awa6d_forwards()
    assert SharedUpstream.build(forwards[:1], settings[:1]) is None
    # every upstream row distinct across the scans: nothing to save
    assert SharedUpstream.build(forwards, [settings[0][:2], settings[1][2:]]) is None
    other = ScreenForwardModel(Beamline.from_spec(SPEC), ["Q1.k1"], 43.36e6)
    assert SharedUpstream.build([forwards[0], other], [settings[0], K1]) is None


def test_pixel_kernel_sum_sq_limits() -> None:
    # bare cloud-in-cell: (integral of the hat squared)^2 = (2/3)^2 per particle
    assert _model(blur=0.2).pixel_kernel_sum_sq() == pytest.approx(4 / 9, abs=1e-3)
    # a wide Gaussian point spread of rms b pixels: 1 / (4 pi b^2)
    wide = _model(blur=3.0).pixel_kernel_sum_sq()
    assert wide == pytest.approx(1 / (4 * math.pi * 9.0), rel=2e-3)


@pytest.mark.parametrize("blur", [0.5, 1.0, 2.0])
def test_pixel_kernel_sum_sq_is_the_image_noise(blur: float) -> None:
    # images of N i.i.d. particles: sum_p Var(s_p) = (kappa - sum_p s_p^2) / N
    fwd = _model(blur=blur)
    g = torch.Generator().manual_seed(1)
    n, repeats = 500, 400
    sig = torch.tensor([3e-3, 0, 2e-3, 0, 0, 0], dtype=torch.float64)  # 3, 2 px
    x = torch.randn(repeats * n, 6, generator=g, dtype=torch.float64) * sig
    imgs = torch.cat([fwd.images(b, K1[1:2]) for b in x.split(n)])  # (R, H, W)
    s = imgs.mean(0)
    noise = imgs.var(0).sum() * n + s.square().sum()
    # relative standard error of the variance estimate ~ sqrt(2 / R) / few px
    assert float(noise) == pytest.approx(fwd.pixel_kernel_sum_sq(), rel=0.03)
