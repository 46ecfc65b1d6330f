from __future__ import annotations

from pathlib import Path

import pytest
import torch

from diffaccel.reconstruction import ReconstructionConfig, load, reconstruct

FAST = {"n_particles": 1024, "steps": 12, "snapshots": 3}


@pytest.fixture(scope="module")
def result(small_scan):
    return reconstruct(
        small_scan, ReconstructionConfig(**FAST), train_indices=[0, 2, 4]
    )


def test_sample_shapes(result) -> None:
    assert result.sample(100).shape == (100, 6)
    assert result.sample(10, per_snapshot=True).shape == (3, 10, 6)
    assert torch.equal(result.sample(50, seed=3), result.sample(50, seed=3))


def test_predict_images_uses_the_settings_passed(result, small_scan) -> None:
    s = small_scan.settings
    a = result.predict_images(s[:1], n_particles=2000)
    b = result.predict_images(s[-1:], n_particles=2000)
    a2 = result.predict_images(s[:1], n_particles=2000)
    assert torch.equal(a, a2)
    assert (a - b).abs().sum() > 0.2
    assert a.shape == (1, 32, 32)
    assert a.sum().item() == pytest.approx(1.0, abs=1e-5)


def test_predict_images_fraction_on_screen_leaves_the_images(
    result, small_scan
) -> None:
    # the scan's settings and one (k1 = 200) that throws the beam off the screen
    s = torch.cat([small_scan.settings, torch.tensor([[200.0]])])
    plain = result.predict_images(s, n_particles=2000)
    images, fraction = result.predict_images(s, n_particles=2000, return_on_screen=True)
    assert torch.equal(images, plain)  # the same numbers, bit for bit
    assert fraction.shape == (7,)
    mean, std = result.predict_images(s, n_particles=2000, return_std=True, n_draws=2)
    mean2, std2, fraction2 = result.predict_images(
        s, n_particles=2000, return_std=True, n_draws=2, return_on_screen=True
    )
    assert torch.equal(mean, mean2) and torch.equal(std, std2)
    torch.testing.assert_close(fraction2, fraction)
    per, per_fraction = result.predict_images(
        s, n_particles=2000, per_snapshot=True, return_on_screen=True
    )
    assert per.shape == (3, 7, 32, 32) and per_fraction.shape == (3, 7)
    torch.testing.assert_close(per_fraction.mean(0), fraction)
    # the particles of the same sample that land inside the screen's pixel area
    fwd = result.forward
    scr = fwd.screen
    (h, w), (psx, psy), (cx, cy) = scr.shape, scr.pixel_size, scr.center
    at = torch.stack(
        [fwd.track_to_screen(b, s) for b in result.sample(2000, per_snapshot=True)]
    )
    inside = ((at[..., 0] - cx).abs() < w * psx / 2) & (
        (at[..., 2] - cy).abs() < h * psy / 2
    )
    counted = inside.double().mean(-1).mean(0)
    # the image sums also lose what the blur spreads past the edges: close
    torch.testing.assert_close(fraction.double(), counted, rtol=0, atol=0.03)
    assert fraction[:-1].min() > 0.95 and fraction[-1] < 0.5


def test_predict_rejects_bad_settings(result) -> None:
    with pytest.raises(ValueError, match="shape"):
        result.predict_images(torch.zeros(2, 3))
    with pytest.raises(ValueError, match="NaN"):
        result.predict_images(torch.tensor([[float("nan")]]))


def test_moments_report_mean_and_spread(result) -> None:
    m = result.moments(n=2000)
    assert len(m["rms"]["mean"]) == 6
    assert all(s >= 0 for s in m["rms"]["std"])
    assert m["emit_x"]["mean"] > 0
    assert result.unconstrained_coordinates() == []  # 4D: x, px, y, py all seen


def test_image_spread_variance_equals_torch_var() -> None:
    from diffaccel.reconstruction.ensemble import _var0

    x = torch.rand(5, 3, 8, 7, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(_var0(x), x.var(0), rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(_var0(x[:2]), x[:2].var(0), rtol=1e-5, atol=1e-7)


def test_save_load_round_trip(result, tmp_path: Path) -> None:
    result.save(tmp_path)
    back = load(tmp_path)
    assert torch.equal(back.sample(100, seed=1), result.sample(100, seed=1))
    assert back.config == result.config
    with pytest.raises(FileExistsError):
        result.save(tmp_path)


#: The config of a result folder as written by earlier versions: settings that
#: are fixed now (quasi_random ... sampling_offset), runtime choices that are
#: arguments now, and the settings of the stages that moved members after
#: training (with the prior term under its earlier name).
OLD_CONFIG = {
    "dims": 4,
    "n_particles": 1024,
    "width": 48,
    "depth": 2,
    "steps": 12,
    "snapshots": 3,
    "lr_max": 0.01,
    "lr_min": 0.0001,
    "penalty_start": 10.0,
    "penalty_end": 30000.0,
    "image_loss": "kl",
    "quasi_random": True,
    "blur_pixels": None,
    "entropy_radius": 4.0,
    "loss_smoothing": 1.0,
    "sampling_offset": 0.25,
    "burn_in": 1,
    "longitudinal_scale": [0.001, 0.001],
    "prior_factor": 3.0,
    "unseen_prior": "pair",
    "hold_unseen": 1000.0,
    "place_unseen": True,
    "refit_steps": 60,
    "probe_unseen": 0.05,
    "polish_moments": True,
    "seed": 2,
    "checkpoint_every": 100,
    "report_every": 10,
    "cuda_graph": True,
}


def test_a_result_folder_of_an_earlier_version_loads(
    small_scan, tmp_path: Path
) -> None:
    # the earlier version's generator: 2 x 48, as its config says
    result = reconstruct(
        small_scan,
        ReconstructionConfig(**FAST, width=48, depth=2),
        train_indices=[0, 2, 4],
    )
    result.save(tmp_path)
    payload = torch.load(tmp_path / "ensemble.pt", weights_only=True)
    payload["config"] = OLD_CONFIG
    torch.save(payload, tmp_path / "ensemble.pt")
    back = load(tmp_path)
    assert back.config == ReconstructionConfig(
        dims=4,
        n_particles=1024,
        width=48,
        depth=2,
        steps=12,
        snapshots=3,
        burn_in=1,
        penalty_end=3e4,
        loss_smoothing=1.0,
        seed=2,
        unseen_weight=1000.0,
        moment_weight=0.0,  # trained without the moment term
    )
    assert torch.equal(back.sample(100, seed=1), result.sample(100, seed=1))


def test_load_errors(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        load(tmp_path)
    (tmp_path / "ensemble.pt").write_bytes(b"junk")
    with pytest.raises(ValueError, match="cannot read"):
        load(tmp_path)


def _own_noise(result, images: torch.Tensor, n_member: int) -> torch.Tensor:
    from diffaccel.reconstruction.metrics import prediction_noise_l1

    kappa = result.forward.pixel_kernel_sum_sq()
    return prediction_noise_l1(images, kappa, n_member * result.n_snapshots)


def test_predictions_add_particles_until_their_own_noise_meets_the_target(
    result, small_scan
) -> None:
    s = small_scan.settings
    plain = result.predict_images(s, n_particles=500)
    # a target the pilot already meets: the same images, bit for bit
    same, used = result.predict_images(
        s, n_particles=500, noise_l1=1.0, return_particles=True
    )
    assert used == 500 and torch.equal(same, plain)
    pilot_noise = float(_own_noise(result, plain, 500).mean())
    target = pilot_noise / 3
    a, used = result.predict_images(
        s, n_particles=500, noise_l1=target, return_particles=True
    )
    b = result.predict_images(s, n_particles=500, noise_l1=target, seed=1)
    # noise goes as 1 / sqrt(N): about 9x the particles for a third of the noise
    assert 8 * 500 <= used <= 10 * 500
    own = float(_own_noise(result, a, used).mean())
    assert own == pytest.approx(target, rel=0.1)
    # the formula is the scatter that two independent predictions show
    scatter = float((a - b).abs().sum((-2, -1)).mean()) / 2**0.5
    assert scatter == pytest.approx(own, rel=0.25)
    assert a.sum((-2, -1)).sub(1).abs().max() < 1e-5
    capped = result.predict_images(
        s, n_particles=500, noise_l1=target, max_particles=1000, return_particles=True
    )[1]
    assert capped == 1000


def test_predictions_against_measured_images_target_a_third_of_their_error(
    result, small_scan
) -> None:
    s = small_scan.settings
    sharp = result.predict_images(s, n_particles=200_000)
    # images the beam reproduces: the error is the pilot's own noise, so the
    # target falls to ~0 and the predictions take all the particles allowed
    used = result.predict_images(
        s,
        n_particles=500,
        noise_l1=1.0,
        measured=sharp,
        max_particles=4000,
        return_particles=True,
    )[1]
    assert used == 4000
    # images far from the beam's: an error far above the pilot's noise
    wrong = torch.roll(sharp, shifts=(11, 11), dims=(-2, -1))
    used = result.predict_images(
        s, n_particles=2000, noise_l1=1e-3, measured=wrong, return_particles=True
    )[1]
    assert used == 2000
    # empty measured images fall back to noise_l1
    used = result.predict_images(
        s,
        n_particles=500,
        noise_l1=1.0,
        measured=torch.zeros_like(sharp),
        return_particles=True,
    )[1]
    assert used == 500


@pytest.mark.parametrize("bad", [0.0, -0.1, float("nan"), "0.02"])
def test_a_bad_noise_target_is_refused(result, small_scan, bad) -> None:
    with pytest.raises(ValueError, match="noise_l1"):
        result.predict_images(small_scan.settings, n_particles=500, noise_l1=bad)
