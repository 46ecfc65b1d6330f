"""Observability, knob recommendation and sequential design (reconstruction.design)."""

from __future__ import annotations

import copy
import json

import pytest
import torch
from click.testing import CliRunner

from diffaccel.cli.main import main
from diffaccel.reconstruction import (
    ReconstructionConfig,
    ScreenForwardModel,
    evaluate,
    reconstruct,
)
from diffaccel.reconstruction import design as dz
from diffaccel.reconstruction import screen_moments as sm
from diffaccel.reconstruction.uncertainty import image_moments

SPEC = {
    "p0c": 43.36e6,
    "beam": {"rms": [1e-3, 1e-3, 1e-3, 1e-3, 1e-3, 1e-3]},
    "scans": {
        "quad": {
            "beamline": [
                {"type": "Quadrupole", "name": "Q1", "length": 0.1, "k1": 0.0},
                {"type": "Quadrupole", "name": "Q2", "length": 0.1, "k1": 0.0},
                {"type": "Drift", "name": "D1", "length": 1.0},
                {
                    "type": "Screen",
                    "name": "S",
                    "shape": [64, 64],
                    "pixel_size": [2e-4, 2e-4],
                    "center": [0.0, 0.0],
                },
            ],
            "knobs": {"Q1.k1": [-10, 10, 7]},
        }
    },
}


def _beam() -> torch.Tensor:
    rms = torch.tensor([1e-3, 1e-3, 1.2e-3, 0.8e-3, 1e-3, 2e-3], dtype=torch.float64)
    corr = torch.eye(6, dtype=torch.float64)
    corr[0, 1] = corr[1, 0] = -0.5
    corr[2, 3] = corr[3, 2] = 0.3
    corr[4, 5] = corr[5, 4] = 0.4
    return corr * rms[:, None] * rms[None, :]


def test_quad_scan_leaves_z_and_pz_unseen(small_scan):
    layouts = dz.layouts_from_dataset(small_scan)
    obs = dz.observability(layouts, dz.beam_from_images(small_scan))
    assert obs.not_seen == ["z", "pz"]
    left = obs.left_to_prior()
    for q in ("emit_z", "emit_6d", "rms_z", "rms_pz", "chirp"):
        assert q in left
    for q in ("emit_x", "emit_y", "rms_x", "rms_y", "beta_x", "alpha_y"):
        assert q in obs.determined()
    assert obs.quantities["emit_x"]["relative_std"] < 0.05
    assert "z and pz not seen at all" in obs.summary_line()


def test_design_matches_tracked_images(small_awa6d):
    """First-order design against tracked particles and their images (6D layout)."""
    cov = _beam()
    cov[5, 5] = (2e-4) ** 2  # a small energy spread: second order stays < 1 %
    cov[4, 5] = cov[5, 4] = 0.4 * 1e-3 * 2e-4
    g = torch.Generator().manual_seed(0)
    x = torch.randn(40_000, 6, generator=g, dtype=torch.float64)
    x = x @ torch.linalg.cholesky(cov).T
    theta = sm.theta_of(torch.cov(x.T))
    for _, scan in small_awa6d:
        fwd = ScreenForwardModel.from_dataset(scan, blur_pixels=0.0)
        pred = sm.moment_design([fwd.transfer_maps(scan.settings)]) @ theta
        pred = pred.reshape(-1, 3)
        at = fwd.track_to_screen(x, scan.settings)  # (K, N, 6)
        xs, ys = at[..., 0], at[..., 2]
        xx = xs.var(-1)
        yy = ys.var(-1)
        xy = ((xs - xs.mean(-1, keepdim=True)) * (ys - ys.mean(-1, keepdim=True))).mean(
            -1
        )
        assert torch.allclose(pred[:, 0], xx, rtol=0.01)
        assert torch.allclose(pred[:, 2], yy, rtol=0.01)
        assert ((pred[:, 1] - xy).abs() / (xx * yy).sqrt()).max() < 0.01


def test_awa6d_names_the_unseen_and_recommends_settings_that_see_them(small_awa6d):
    layouts = dz.layouts_from_dataset(small_awa6d)
    cov = torch.cov(small_awa6d.ground_truth.double().T)
    obs = dz.observability(layouts, cov)
    words = [u["words"] for u in obs.unseen]
    assert "px-pz together with pz-pz" in words
    assert "py-z together with z-z" in words
    assert "emit_z" in obs.left_to_prior()
    low = sorted(obs.longitudinal_singular_values)[:2]
    assert low[0] < 1e-3 and low[1] < 1e-2
    knobs = [
        dz.parse_knob("SCAN_TDC.voltage=-4e6:4e6"),
        dz.parse_knob("SCAN_DIPOLE.angle=-0.40:-0.28"),
    ]
    rec = dz.recommend(layouts, cov, knobs)
    assert rec["recommended"]
    per_scan: dict[str, int] = {}
    for r in rec["recommended"]:
        per_scan[r["scan"]] = per_scan.get(r["scan"], 0) + r["n_images"]
    assert max(per_scan.values()) <= dz.MAX_IMAGES_PER_SCAN
    last = rec["recommended"][-1]["expected_std"]
    assert last["emit_z"] < 0.25 * rec["baseline_std"]["emit_z"]
    _, lsv = dz.singular_values_with(layouts, cov, rec["recommended"])
    assert sorted(lsv)[0] > 1e-2  # both longitudinal directions now seen


def test_knob_errors_are_one_line(small_awa6d):
    layouts = dz.layouts_from_dataset(small_awa6d)
    cov = torch.cov(small_awa6d.ground_truth.double().T)
    for text in ("SCAN_TDC.voltage", "SCAN_TDC.voltage=4:-4", "voltage=1:2", "A.b=1:x"):
        with pytest.raises(ValueError, match="knob") as err:
            dz.parse_knob(text)
        assert "\n" not in str(err.value)
    cases = {
        "NOPE.k1=-1:1": "no element 'NOPE'",
        "SCAN_TDC.colour=0:1": "colour",
        "SCAN_TDC.voltage=3e7:5e7": "off the",
        "SCAN_TDC.voltage=4e6": "adds no setting",
    }
    for text, msg in cases.items():
        with pytest.raises(ValueError, match=msg) as err:
            dz.recommend(layouts, cov, [dz.parse_knob(text)])
        assert "\n" not in str(err.value)


def test_spec_errors_name_the_scan_and_field():
    """Planned scans that measure nothing are refused in one line, not traced back."""

    def spec_with(**scan):
        spec = copy.deepcopy(SPEC)
        spec["scans"]["quad"].update(scan)
        return spec

    off = copy.deepcopy(SPEC)
    off["scans"]["quad"]["beamline"][-1]["pixel_size"] = [1e-8, 1e-8]
    cases = {
        "no knobs": spec_with(knobs={}),
        "n must be a whole number >= 1": spec_with(knobs={"Q1.k1": [-1, 1, 0]}),
        "rows of 1 value": spec_with(names=["Q1.k1"], settings=[[1.0, 2.0]]),
        "settings: not rows of numbers": spec_with(names=["Q1.k1"], settings=[["a"]]),
        "misses the screen at every setting": off,
    }
    for msg, spec in cases.items():
        with pytest.raises(ValueError, match=msg) as err:
            dz.layouts_from_spec(spec)
        assert "scans.quad" in str(err.value) and "\n" not in str(err.value)
    one_knob = spec_with(names=["Q1.k1"], settings=[-1.0, 0.0, 1.0])
    one_knob["scans"]["quad"].pop("knobs")
    [layout], _ = dz.layouts_from_spec(one_knob)
    assert tuple(layout.settings.shape) == (3, 1)


def test_a_knob_that_moves_nothing_is_refused():
    layouts, cov = dz.layouts_from_spec(SPEC)
    with pytest.raises(ValueError, match="moves nothing"):
        dz.recommend(layouts, cov, [dz.parse_knob("Q2.tilt=0:1")])
    with pytest.raises(ValueError, match="moves nothing"):
        dz.recommend(layouts, cov, [dz.parse_knob("Q2.tilt=0.5")])
    rec = dz.recommend(
        layouts, cov, [dz.parse_knob("Q2.k1=-5:5")], targets=("emit_x", "emit_y")
    )
    assert rec["not_seen"] == ["z", "pz"]


def test_cli_design_spec_json_and_errors(tmp_path):
    spec = tmp_path / "line.json"
    spec.write_text(json.dumps(SPEC))
    run = CliRunner().invoke(
        main,
        ["design", str(spec), "--json", "--knob", "Q2.k1=-5:5", "--target", "emit_x"],
    )
    assert run.exit_code == 0, run.output
    out = json.loads(run.output)
    assert set(out) >= {"unseen", "recommended"}
    for r in out["recommended"]:
        assert set(r) >= {"scan", "names", "values", "expected_std"}
        assert r["names"] == ["Q1.k1", "Q2.k1"]
    for knob, msg in (
        ("Q2.tilt=0:1", "moves nothing"),
        ("Q9.k1=0:1", "no element"),
        ("Q2.k1", "expected ELEMENT.param=LOW:HIGH"),
    ):
        run = CliRunner().invoke(main, ["design", str(spec), "--knob", knob])
        assert run.exit_code != 0
        assert msg in run.output and "Traceback" not in run.output
        assert len(run.output.strip().splitlines()) == 1


def test_propose_quad_settings_beats_a_poor_choice():
    fwd = ScreenForwardModel.from_spec(
        {
            "beamline": SPEC["scans"]["quad"]["beamline"],
            "names": ["Q1.k1"],
            "p0c": 43.36e6,
            "species": "electron",
            "blur_pixels": 1.0,
        }
    )
    cov = _beam()

    def map_of(k):
        return fwd.transfer_maps(k[:, None])[:, :6, :6]

    k0 = torch.tensor([-10.0, 0.0, 10.0], dtype=torch.float64)
    m0 = map_of(k0)

    def moments(m):
        s = m @ cov @ m.transpose(-1, -2)
        return torch.stack([s[:, 0, 0], s[:, 2, 2]], -1)

    cand = torch.linspace(-10, 10, 41, dtype=torch.float64)
    best = dz.propose_quad_settings(
        map_of, m0, moments(m0), cand, n=2, relative_error=0.01
    )
    assert best.shape == (2,)

    def std_after(extra):
        m = torch.cat([m0, map_of(extra)])
        p = dz.quad_scan_posterior(m, moments(m), relative_error=0.01)
        return float((p["emit_std"] / p["emit"]).square().sum())

    poor = torch.tensor([-10.0, 10.0], dtype=torch.float64)
    assert std_after(best) < std_after(poor)
    post = dz.quad_scan_posterior(m0, moments(m0), relative_error=0.01)
    torch.testing.assert_close(
        post["emit"][0], torch.linalg.det(cov[:2, :2]).sqrt(), rtol=1e-9, atol=0
    )


def test_summary_stores_the_observability_line(small_scan):
    fast = {"n_particles": 512, "steps": 4, "snapshots": 1}
    result = reconstruct(
        small_scan, ReconstructionConfig(**fast), train_indices=[0, 2, 4]
    )
    s = evaluate(result, small_scan, n_sample=2000)
    line = s["observability"]
    assert line.startswith("observability: z and pz not seen at all")
    assert "\n" not in line


def test_design_matches_the_moments_of_tracked_images(small_awa6d):
    """The synthetic files' images (exact tracking, histograms) against the design."""
    theta = sm.theta_of(torch.cov(small_awa6d.ground_truth.double().T))
    for _, scan in small_awa6d:
        fwd = ScreenForwardModel.from_dataset(scan)
        pred = sm.moment_design([fwd.transfer_maps(scan.settings)]) @ theta
        pred = pred.reshape(-1, 3)
        xs, ys = scan.pixel_centers()
        m = image_moments(scan.mean_images().double(), xs, ys)
        px, py = scan.pixel_size  # histograms: a point spread of 1/12 pixel^2
        assert ((m[:, 2] - px**2 / 12) / pred[:, 0] - 1).abs().max() < 0.04
        assert ((m[:, 4] - py**2 / 12) / pred[:, 2] - 1).abs().max() < 0.04
        assert (
            (m[:, 3] - pred[:, 1]) / (pred[:, 0] * pred[:, 2]).sqrt()
        ).abs().max() < 0.02


def test_tail_variance_of_a_gaussian_and_heavier_tails():
    c = torch.tensor([0.5, 1.0, 2.0, 3.0, 4.0], dtype=torch.float64)
    normal = torch.distributions.Normal(0.0, 1.0)
    pdf = normal.log_prob(c).exp()
    exact = c * pdf + 1 - normal.cdf(c)  # int_c^inf x^2 phi(x) dx
    torch.testing.assert_close(dz.tail_variance(c), exact, rtol=1e-6, atol=1e-9)
    torch.testing.assert_close(dz.tail_variance(c, 2.5), exact, rtol=1e-6, atol=1e-9)
    assert float(dz.tail_variance(torch.tensor(1e-6))) == 0.5
    # a heavier tail hides more of the variance beyond the same edge
    t = dz.tail_variance(torch.tensor(3.0), torch.tensor([3.0, 4.0, 6.0]))
    assert bool((t.diff() > 0).all())
    # a Student t's tail integral is that of its own density (numerical check)
    x = torch.linspace(3.0, 3000.0, 2_000_001, dtype=torch.float64)
    nu = 4 + 6 / (4.0 - 3)
    st = torch.distributions.StudentT(nu, 0.0, ((nu - 2) / nu) ** 0.5)
    ref = torch.trapezoid(x**2 * st.log_prob(x).exp(), x)
    torch.testing.assert_close(
        dz.tail_variance(torch.tensor(3.0), 4.0), ref, rtol=1e-3, atol=0
    )


def test_image_kurtosis_of_gaussian_and_uniform_beams():
    from diffaccel.dynamics.images import cic_image

    g = torch.Generator().manual_seed(0)
    n, px = 200_000, 1e-4
    xs = (torch.arange(128, dtype=torch.float64) - 63.5) * px
    gauss = 15 * px * torch.randn(n, generator=g, dtype=torch.float64)
    flat = 40 * px * (2 * torch.rand(n, generator=g, dtype=torch.float64) - 1)
    blur = 0.9 * px
    img = cic_image(gauss[None], flat[None], (128, 128), px, (0.0, 0.0), None, blur)
    spread = (1.0 / 6.0 + 0.9**2) ** 0.5 * px
    k = dz.image_kurtosis(img, xs, xs, (spread, spread))[0]
    assert abs(float(k[0]) - 3.0) < 0.05
    assert abs(float(k[1]) - 1.8) < 0.05


def test_quad_scan_error_model_of_each_image():
    fwd = ScreenForwardModel.from_spec(
        {
            "beamline": SPEC["scans"]["quad"]["beamline"],
            "names": ["Q1.k1"],
            "p0c": 43.36e6,
            "species": "electron",
            "blur_pixels": 1.0,
        }
    )
    cov = _beam()

    def map_of(k):
        return fwd.transfer_maps(k[:, None])[:, :6, :6]

    def moments(m):
        s = m @ cov @ m.transpose(-1, -2)
        return torch.stack([s[:, 0, 0], s[:, 2, 2]], -1)

    k0 = torch.tensor([-10.0, 0.0, 10.0], dtype=torch.float64)
    m0 = map_of(k0)
    noise = 1 + 0.01 * torch.tensor([[1.0, -1.0], [-0.5, 0.5], [0.3, 0.2]])
    y = moments(m0) * noise
    plain = dz.quad_scan_posterior(m0, y, relative_error=0.01)
    # a Gaussian kurtosis and a far-off screen edge change nothing
    same = dz.quad_scan_posterior(
        m0,
        y,
        relative_error=0.01,
        kurtosis=torch.full((3, 2), 3.0),
        half_width=(1.0, 1.0),
    )
    torch.testing.assert_close(same["emit_std"], plain["emit_std"])
    # heavier tails: more shot noise, a larger std
    heavy = dz.quad_scan_posterior(
        m0, y, relative_error=0.01, kurtosis=torch.full((3, 2), 5.0)
    )
    ratio = heavy["emit_std"] / plain["emit_std"]
    torch.testing.assert_close(ratio, torch.full((2,), 2.0**0.5, dtype=ratio.dtype))
    # a screen that clips the larger spots: the fit expects the variance the
    # edges hide and recovers the beam
    truth = torch.stack(
        [torch.linalg.det(cov[p : p + 2, p : p + 2]).sqrt() for p in (0, 2)]
    )
    k5 = torch.linspace(-10, 10, 5, dtype=torch.float64)
    m5 = map_of(k5)
    y5 = moments(m5)
    half = 3.0 * float(y5.sqrt().amax())
    clipped = y5 * (1 - 2 * dz.tail_variance(half / y5.sqrt()))
    assert float((clipped / y5).amin()) < 0.9999
    naive = dz.quad_scan_posterior(m5, clipped, relative_error=0.01)["emit"]
    seen = dz.quad_scan_posterior(
        m5, clipped, relative_error=0.01, half_width=(half, half)
    )["emit"]
    assert float((seen / truth - 1).abs().amax()) < 1e-4
    assert float((naive / truth - 1).abs().amax()) > 10 * float(
        (seen / truth - 1).abs().amax()
    )
    # the proposal keeps the beam further inside a screen that clips large spots
    cand = torch.linspace(-10, 10, 41, dtype=torch.float64)
    rms = moments(map_of(cand)).sqrt()  # (C, 2)
    edge = float(4 * rms.amin(0).amax())  # some candidates reach past 4 rms
    assert bool((rms > edge / 3).any())
    free = dz.propose_quad_settings(map_of, m0, y, cand, n=2, relative_error=0.01)
    best = dz.propose_quad_settings(
        map_of, m0, y, cand, n=2, relative_error=0.01, half_width=(edge, edge)
    )
    largest = [float(moments(map_of(k)).sqrt().amax()) for k in (free, best)]
    assert largest[1] < largest[0], (free, best, largest)


def test_propose_quad_settings_from_a_fit_that_is_no_beam():
    fwd = ScreenForwardModel.from_spec(
        {
            "beamline": SPEC["scans"]["quad"]["beamline"],
            "names": ["Q1.k1"],
            "p0c": 43.36e6,
            "species": "electron",
            "blur_pixels": 1.0,
        }
    )
    cov = _beam()

    def map_of(k):
        return fwd.transfer_maps(k[:, None])[:, :6, :6]

    k0 = torch.tensor([-10.0, 0.0, 10.0], dtype=torch.float64)
    m0 = map_of(k0)
    s = m0 @ cov @ m0.transpose(-1, -2)
    y = torch.stack([s[:, 0, 0], s[:, 2, 2]], -1)
    # the middle spot measured too large: three settings fit no beam in x
    for factor in (2.0, 20.0):
        bad = y.clone()
        bad[1, 0] *= factor
        post = dz.quad_scan_posterior(m0, bad, relative_error=0.01)
        th = post["theta"][0]
        assert float(th[0] * th[2] - th[1] ** 2) < 0
        cand = torch.linspace(-10, 10, 41, dtype=torch.float64)
        for draws in (0, 8):
            best = dz.propose_quad_settings(
                map_of,
                m0,
                bad,
                cand,
                n=2,
                relative_error=0.01,
                measured=k0,
                min_separation=1.0,
                draws=draws,
            )
            assert bool(torch.isfinite(best).all())
            assert float((best[0] - best[1]).abs()) > 1.0, best
            assert float((best[:, None] - k0[None]).abs().amin()) > 1.0, best


def test_joint_proposals_keep_their_separation():
    fwd = ScreenForwardModel.from_spec(
        {
            "beamline": SPEC["scans"]["quad"]["beamline"],
            "names": ["Q1.k1"],
            "p0c": 43.36e6,
            "species": "electron",
            "blur_pixels": 1.0,
        }
    )
    cov = _beam()

    def map_of(k):
        return fwd.transfer_maps(k[:, None])[:, :6, :6]

    k0 = torch.tensor([-10.0, 0.0, 10.0], dtype=torch.float64)
    m0 = map_of(k0)
    s = m0 @ cov @ m0.transpose(-1, -2)
    y = torch.stack([s[:, 0, 0], s[:, 2, 2]], -1)
    cand = torch.linspace(-10, 10, 41, dtype=torch.float64)
    for joint in (True, False):
        best = dz.propose_quad_settings(
            map_of,
            m0,
            y,
            cand,
            n=4,
            relative_error=0.01,
            min_separation=2.0,
            joint=joint,
        )
        gaps = (best[:, None] - best[None, :]).abs() + 10 * torch.eye(4)
        assert float(gaps.amin()) > 2.0, (joint, best)
