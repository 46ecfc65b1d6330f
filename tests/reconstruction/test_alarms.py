"""Fit-quality alarms: one test per pattern, and a good fit that stays quiet."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from diffaccel.data import MultiScanDataset, make_synthetic_quad_scan
from diffaccel.reconstruction import (
    ReconstructionConfig,
    ScreenForwardModel,
    evaluate,
    reconstruct,
)
from diffaccel.reconstruction.alarms import (
    EDGE_LEVEL,
    FLOOR_SHARE,
    MOMENT_MISS,
    MOMENT_MISS_RAW,
    OUTLIER_RATIO,
    ScanFit,
    fit_alarms,
    fit_signals,
    longitudinal_alarm,
    poor_fit_causes,
    prediction_alarms,
)

QUICK = {"n_particles": 1024, "steps": 120, "snapshots": 1}


def _beamline(drift: float, quad: float = 0.1) -> list[dict]:
    return [
        {"type": "Quadrupole", "name": "Q1", "length": quad, "k1": 0.0},
        {"type": "Drift", "name": "D1", "length": drift},
        {"type": "Screen", "name": "SCREEN"},
    ]


@pytest.fixture(scope="module")
def beam() -> torch.Tensor:
    g = torch.Generator().manual_seed(5)
    sig = torch.tensor([1.5e-3, 0.6e-3, 1.2e-3, 0.5e-3, 0.0, 0.0], dtype=torch.float64)
    return torch.randn(6000, 6, generator=g, dtype=torch.float64) * sig


def _scan(beam, drift: float, seed: int):
    return make_synthetic_quad_scan(
        particles=beam,
        beamline_spec=_beamline(drift),
        n_settings=8,
        k1_range=(-20.0 / drift, 12.0 / drift),
        screen_shape=(32, 32),
        pixel_size=(1.5e-3 * (0.8 + 0.4 * drift),) * 2,
        seed=seed,
    )


def _perfect_fit(scan, predicted=None, name="scan") -> ScanFit:
    """A fit whose predictions are ``predicted`` (default: the measured images)."""
    fwd = ScreenForwardModel.from_dataset(scan)
    xs, ys = fwd.screen.pixel_centers(dtype=torch.float64)
    meas = scan.mean_images()
    return ScanFit(
        name=name,
        measured=meas,
        predicted=meas.clone() if predicted is None else predicted,
        maps=fwd.transfer_maps(scan.settings),
        xs=xs,
        ys=ys,
    )


def _kinds(summary_or_alarms) -> set[str]:
    if isinstance(summary_or_alarms, dict):
        return {a["kind"] for a in summary_or_alarms["fit_alarms"]}
    return {a.kind for a in summary_or_alarms}


def test_a_good_two_scan_fit_is_quiet(beam) -> None:
    ds = MultiScanDataset({"a": _scan(beam, 1.0, 1), "b": _scan(beam, 1.5, 2)})
    result = reconstruct(ds, ReconstructionConfig(**QUICK), uncertainty=False)
    s = evaluate(result, ds, n_sample=4000)
    assert s["warnings"] == []
    q = s["fit_quality"]
    assert q["moment_residual"] < 0.05
    assert q["moment_residual_one_beam"] < 1.5 * q["moment_residual_per_scan"] + 0.01


def test_scans_that_disagree_are_warned(beam) -> None:
    # scan b's file says its quadrupole is twice as long as it was
    b = _scan(beam, 1.5, 2)
    wrong = dataclasses.replace(b, beamline_spec=_beamline(1.5, quad=0.2))
    ds = MultiScanDataset({"a": _scan(beam, 1.0, 1), "b": wrong})
    result = reconstruct(ds, ReconstructionConfig(**QUICK), uncertainty=False)
    s = evaluate(result, ds, n_sample=4000)
    assert "inconsistent_scans" in _kinds(s)
    (w,) = [w for w in s["warnings"] if "disagree" in w]
    assert "likely causes, most likely first: (1) one scan's beamline" in w
    q = s["fit_quality"]
    assert q["moment_residual_one_beam"] > 5 * q["moment_residual_per_scan"]


def test_copied_images_are_scans_that_disagree(beam) -> None:
    a, b = _scan(beam, 1.0, 1), _scan(beam, 1.5, 2)
    ds = MultiScanDataset(
        {"a": a, "b": dataclasses.replace(b, images=a.images.clone())}
    )
    fits = [
        _perfect_fit(scan, name=name)
        for name, scan in ds  # each scan reproduced exactly by some beam
    ]
    # the one beam that best fits both: the truth of scan a, seen through b
    truth = ScreenForwardModel.from_dataset(b).images(beam.float(), b.settings).detach()
    fits[1].predicted = truth / truth.sum((-2, -1), keepdim=True)
    alarms = fit_alarms(fit_signals(fits, torch.cov(beam.T), 4))
    assert "inconsistent_scans" in _kinds(alarms)


def test_a_screen_that_cuts_the_beam_is_warned(beam) -> None:
    scan = _scan(beam, 1.0, 1)
    band = dataclasses.replace(scan, images=scan.images[:, :, 15:17, :].clone())
    alarms = fit_alarms(fit_signals([_perfect_fit(band)], torch.cov(beam.T), 4))
    (edge,) = [a for a in alarms if a.kind == "screen_edge"]
    assert edge.value > 3 * EDGE_LEVEL
    assert "cut by the edge" in edge.message
    assert edge.causes[0].startswith("a screen region of interest too small")
    # the full screen: the beam well inside, quiet
    quiet = fit_alarms(fit_signals([_perfect_fit(scan)], torch.cov(beam.T), 4))
    assert quiet == []


def test_a_4d_result_through_a_cavity_is_warned(small_scan, small_awa6d) -> None:
    maps = {
        n: ScreenForwardModel.from_dataset(s).transfer_maps(s.settings)
        for n, s in small_awa6d
    }
    specs = {n: s.beamline_spec for n, s in small_awa6d}
    alarm = longitudinal_alarm(4, maps, specs)
    assert alarm is not None
    assert "TransverseDeflectingCavity" in alarm.message
    assert "--dims 6" in alarm.causes[0]
    assert longitudinal_alarm(6, maps, specs) is None
    quad = {
        "scan": ScreenForwardModel.from_dataset(small_scan).transfer_maps(
            small_scan.settings
        )
    }
    assert longitudinal_alarm(4, quad, {"scan": small_scan.beamline_spec}) is None
    # predict: a 4D result imaged through the cavity layout
    result = reconstruct(
        small_scan,
        ReconstructionConfig(n_particles=256, steps=2, snapshots=1),
        uncertainty=False,
    )
    (a,) = prediction_alarms(result, small_awa6d)
    assert a.kind == "longitudinal_4d" and "predicted through" in a.text()
    assert prediction_alarms(result, small_scan) == []


def test_second_moments_missed_are_warned(beam) -> None:
    scan = _scan(beam, 1.0, 1)
    wide = beam.clone()
    wide[:, :4] *= 1.6  # every size 60 % too large: a fit far from converged
    fwd = ScreenForwardModel.from_dataset(scan)
    pred = fwd.images(wide.float(), scan.settings).detach()
    pred = pred / pred.sum((-2, -1), keepdim=True)
    alarms = fit_alarms(fit_signals([_perfect_fit(scan, pred)], torch.cov(beam.T), 4))
    (miss,) = [a for a in alarms if a.kind == "moment_miss"]
    assert miss.value > MOMENT_MISS_RAW  # rms relative miss of the variances
    # a beam fits the measured moments (the truth): the training did not reach it
    assert miss.causes[0].startswith("training too short")


def test_an_image_that_stands_out_is_warned(beam) -> None:
    scan = _scan(beam, 1.0, 1)
    fit = _perfect_fit(scan)
    fit.predicted = fit.predicted.clone()
    fit.predicted[3] = fit.measured[7]  # setting 3 recorded at another setting
    alarms = fit_alarms(fit_signals([fit], torch.cov(beam.T), 4))
    (out,) = [a for a in alarms if a.kind == "outlier_setting"]
    assert "setting 3" in out.message
    assert out.causes[0].startswith("the image recorded at another setting")


def test_an_image_whose_moments_stand_out_is_named(beam) -> None:
    # every prediction noisy (relative L1 ~0.25 each), setting 3's image taken
    # of a beam 30 % wider in x: its L1 does not stand out, its moments do
    scan = _scan(beam, 1.0, 1)
    fit = _perfect_fit(scan)
    g = torch.Generator().manual_seed(0)
    noisy = fit.measured * (1 + 0.3 * torch.randn(fit.measured.shape, generator=g))
    fit.predicted = noisy.clamp_min(0)
    fit.predicted /= fit.predicted.sum((-2, -1), keepdim=True)
    wide = beam.clone()
    wide[:, :2] *= 1.3
    fwd = ScreenForwardModel.from_dataset(scan)
    img = fwd.images(wide.float(), scan.settings[3:4]).detach()[0].double()
    fit.measured = fit.measured.clone()
    fit.measured[3] = img / img.sum()
    signals = fit_signals([fit], torch.cov(beam.T), 4)
    assert signals["image_l1_worst_ratio"] < OUTLIER_RATIO
    assert signals["moment_left_worst"] > MOMENT_MISS
    assert signals["moment_left_worst_ratio"] > OUTLIER_RATIO
    (out,) = [a for a in fit_alarms(signals) if a.kind == "outlier_setting"]
    assert "setting 3 " in out.message and "setting 2 " not in out.message
    # without the wide image: no setting stands out
    fit.measured[3] = _perfect_fit(scan).measured[3]
    quiet = fit_alarms(fit_signals([fit], torch.cov(beam.T), 4))
    assert "outlier_setting" not in _kinds(quiet)


def test_images_on_a_floor_are_warned(beam) -> None:
    scan = _scan(beam, 1.0, 1)
    fit = _perfect_fit(scan)  # the fit reproduces what it is given
    g = torch.Generator().manual_seed(0)
    peak = fit.measured.amax((-2, -1), keepdim=True)
    noise = 0.05 * peak * torch.randn(fit.measured.shape, generator=g)
    # background-subtracted frames: zero-mean noise, signed; quiet
    fit.measured = fit.measured + noise
    signals = fit_signals([fit], torch.cov(beam.T), 4)
    assert abs(torch.tensor(signals["scans"]["scan"]["floor_share"]).median()) < 0.01
    assert "background" not in _kinds(fit_alarms(signals))
    # the same noise clipped at 0: a floor of its positive half
    fit.measured = fit.measured.clamp_min(0)
    (floor,) = [
        a for a in fit_alarms(fit_signals([fit], torch.cov(beam.T), 4))
        if a.kind == "background"
    ]  # fmt: skip
    assert floor.value > FLOOR_SHARE
    assert floor.causes[0].startswith("background or a pedestal not subtracted")
    # a beam cut by one edge raises that edge only: no floor
    band = dataclasses.replace(scan, images=scan.images[:, :, 15:17, :].clone())
    alarms = fit_alarms(fit_signals([_perfect_fit(band)], torch.cov(beam.T), 4))
    assert "background" not in _kinds(alarms)


def test_a_scan_that_stands_out_is_warned(beam) -> None:
    scans = [_scan(beam, d, i) for i, d in enumerate((1.0, 1.5, 2.0))]
    fits = [_perfect_fit(s, name=f"s{i}") for i, s in enumerate(scans)]
    # scan s2's images of another beam position (a wrong screen centre)
    fits[2].predicted = torch.roll(fits[2].measured, shifts=6, dims=-1)
    alarms = fit_alarms(fit_signals(fits, torch.cov(beam.T), 4))
    (out,) = [a for a in alarms if a.kind == "outlier_scan"]
    assert out.scans == ("s2",)
    assert "scan 's2'" in out.text()


def test_poor_fit_causes_follow_the_other_signals(beam) -> None:
    assert poor_fit_causes([])[0].startswith("settings in the wrong units")
    scan = _scan(beam, 1.0, 1)
    band = dataclasses.replace(scan, images=scan.images[:, :, 15:17, :].clone())
    alarms = fit_alarms(fit_signals([_perfect_fit(band)], torch.cov(beam.T), 4))
    causes = poor_fit_causes(alarms)
    assert causes[0].startswith("a screen region of interest too small")
    assert any(c.startswith("settings in the wrong units") for c in causes)
