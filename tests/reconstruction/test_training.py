from __future__ import annotations

import math
import pickle
from dataclasses import fields, replace
from pathlib import Path

import pytest
import torch

from diffaccel.reconstruction import (
    ReconstructionConfig,
    ScreenForwardModel,
    load_checkpoint,
    reconstruct,
)
from diffaccel.reconstruction.generator import FlatGenerator
from diffaccel.reconstruction.initial import fit_gaussian
from diffaccel.reconstruction.training import load_tensors, train_generator

FAST = {"n_particles": 1024, "steps": 24, "snapshots": 3}
#: Runtime choices of the resume tests: checkpoints every 5 steps.
RUN = {"checkpoint_every": 5}


class _Stop(Exception):
    pass


def test_training_lowers_the_image_mismatch(small_scan) -> None:
    cfg = ReconstructionConfig(**{**FAST, "steps": 30, "snapshots": 1})
    r = reconstruct(small_scan, cfg, train_indices=[0, 2, 4])
    h = r.history["image_loss"]
    assert sum(h[-5:]) / 5 < 0.7 * sum(h[:5]) / 5
    assert r.n_snapshots == 1
    assert len(h) == 30 and r.history["snapshot_steps"] == [30]


def test_snapshot_per_cycle_and_schedule(small_scan) -> None:
    r = reconstruct(small_scan, ReconstructionConfig(**FAST))
    assert r.history["snapshot_steps"] == [8, 16, 24]
    lr = r.history["lr"]
    assert lr[0] == pytest.approx(1e-2) and lr[8] == pytest.approx(1e-2)
    assert lr[7] < 1e-3  # end of a cycle
    assert not torch.equal(r.snapshots[0]["log_scale"], r.snapshots[-1]["log_scale"])


def test_same_seed_same_result(small_scan) -> None:
    a = reconstruct(small_scan, ReconstructionConfig(**{**FAST, "steps": 6}))
    b = reconstruct(small_scan, ReconstructionConfig(**{**FAST, "steps": 6}))
    for sa, sb in zip(a.snapshots, b.snapshots, strict=True):
        for k in sa:
            assert torch.equal(sa[k], sb[k]), k


@pytest.mark.parametrize("stop_at", [6, 10], ids=["mid-cycle", "after-snapshot"])
def test_resume_equals_uninterrupted_run(
    small_scan, tmp_path: Path, stop_at: int
) -> None:
    # losses are read (and the callback runs) at steps 3, 5, 6, 8, 9, 10...:
    # every 3 steps, at checkpoints (5, 10) and snapshots (8); stopping at 6
    # loses step 6, done after the checkpoint of step 5
    cfg = ReconstructionConfig(**FAST)
    run = {**RUN, "report_every": 3}
    ref = reconstruct(small_scan, cfg, **run)
    ck = tmp_path / "ck.pt"

    def stop(info) -> None:
        if info.step == stop_at:
            raise _Stop

    with pytest.raises(_Stop):
        reconstruct(small_scan, cfg, checkpoint=ck, callback=stop, **run)
    saved = load_checkpoint(ck)
    assert saved.step == 5 if stop_at == 6 else saved.step == 10
    res = reconstruct(small_scan, cfg, checkpoint=ck, resume=True, **run)
    assert len(res.snapshots) == len(ref.snapshots)
    for sa, sb in zip(res.snapshots, ref.snapshots, strict=True):
        for k in sa:
            assert torch.equal(sa[k], sb[k]), k
    # the parameters are bitwise equal; logged float64 losses may differ in the
    # last bit between calls (threaded reductions), hence 1e-12
    assert res.history["loss"] == pytest.approx(ref.history["loss"], rel=1e-12)


def test_resume_with_other_config_is_refused(small_scan, tmp_path: Path) -> None:
    ck = tmp_path / "ck.pt"
    reconstruct(small_scan, ReconstructionConfig(**{**FAST, "steps": 6}), checkpoint=ck)
    with pytest.raises(ValueError, match="different config"):
        reconstruct(
            small_scan,
            ReconstructionConfig(**{**FAST, "steps": 6, "seed": 1}),
            checkpoint=ck,
            resume=True,
        )


def test_resume_of_a_6d_checkpoint_without_the_quadratic_term_is_refused(
    small_awa6d, tmp_path: Path
) -> None:
    """A 6D run checkpointed by a generator without the quadratic term: its
    optimiser state is shorter than the parameters; a clear
    error, not a size mismatch from inside Adam."""
    ck = tmp_path / "ck.pt"
    cfg = ReconstructionConfig(
        dims=6,
        n_particles=512,
        steps=4,
        snapshots=1,
        burn_in=0,
    )
    reconstruct(small_awa6d, cfg, checkpoint=ck, uncertainty=False, checkpoint_every=2)
    d = torch.load(ck, weights_only=True)
    del d["model"]["quad"]
    torch.save(d, ck)
    with pytest.raises(ValueError, match=r"earlier diffaccel.*\['quad'\]"):
        reconstruct(small_awa6d, cfg, checkpoint=ck, resume=True, uncertainty=False)


def test_corrupt_checkpoint(tmp_path: Path) -> None:
    bad = tmp_path / "ck.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="cannot read checkpoint"):
        load_checkpoint(bad)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"steps": 10, "snapshots": 3}, "multiple of snapshots"),
        ({"dims": 5}, "dims must be 4 or 6"),
        ({"n_particles": 3}, "n_particles"),
        ({"penalty_end": 0.0}, "penalty_end must be > 0"),
        ({"penalty_end": math.nan}, "penalty_end must be a finite number"),
        ({"unseen_weight": -1.0}, "unseen_weight must be finite and >= 0"),
        ({"unseen_weight": math.nan}, "unseen_weight must be a finite number"),
        ({"moment_weight": -1.0}, "moment_weight must be finite and >= 0"),
        ({"moment_weight": math.inf}, "moment_weight must be a finite number"),
    ],
    ids=[
        "cycles",
        "dims",
        "particles",
        "penalty-zero",
        "penalty-nan",
        "hold-negative",
        "hold-nan",
        "moments-negative",
        "moments-inf",
    ],
)
def test_bad_config(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        ReconstructionConfig(**kwargs)


def test_bad_train_indices(small_scan) -> None:
    with pytest.raises(ValueError, match="train_indices"):
        reconstruct(small_scan, ReconstructionConfig(**FAST), train_indices=[0, 99])


def test_six_dimensional_training_runs(small_scan) -> None:
    cfg = ReconstructionConfig(**{**FAST, "dims": 6, "steps": 6})
    r = reconstruct(small_scan, cfg)
    x = r.sample(500)
    assert (x[:, 4:].std(0) > 0).all()
    assert "z" in r.unconstrained_coordinates()
    # the file's KDE screens of one-pixel bandwidth, not the 6D default
    assert small_scan.resolution_pixels == 1.0
    assert r.forward.blur_pixels == 1.0 and r.info["blur_pixels"] == 1.0


def test_blur_is_the_option_else_the_screen_resolution_else_by_dims(
    small_scan,
) -> None:
    unknown = replace(small_scan, resolution_pixels=None)
    six = ReconstructionConfig(dims=6)
    assert six.blur_pixels is None  # resolved per scan, not here
    assert six.blur_for(small_scan) == 1.0
    assert six.blur_for(unknown) == pytest.approx(math.sqrt(1 / 12))
    assert ReconstructionConfig(dims=4).blur_for(unknown) == 1.0
    assert ReconstructionConfig(dims=6, blur_pixels=0.3).blur_for(small_scan) == 0.3
    with pytest.raises(ValueError, match="blur_pixels"):
        ReconstructionConfig(blur_pixels=-1.0)


def test_defaults_depend_on_dims_and_explicit_values_win() -> None:
    four, six = ReconstructionConfig(dims=4), ReconstructionConfig(dims=6)
    assert (four.n_particles, four.steps, four.snapshots, four.burn_in) == (
        6144,
        1200,
        5,
        0,
    )
    # 6D: more particles (finite-sample bias of the small emittances) and only
    # the later cycles' members (the 6D emittance converges over cycles)
    assert (six.n_particles, six.steps, six.snapshots, six.burn_in) == (
        16384,
        360,
        6,
        3,
    )
    assert (four.cycle_length, six.cycle_length) == (240, 60)
    mine = ReconstructionConfig(dims=6, n_particles=2048, steps=40, snapshots=2)
    assert (mine.n_particles, mine.steps, mine.burn_in) == (2048, 40, 1)
    assert ReconstructionConfig(dims=6, steps=10, snapshots=1).burn_in == 0
    # a saved config is the resolved one
    assert ReconstructionConfig.from_dict(six.to_dict()) == six


def test_sampling_offset_and_penalty_defaults() -> None:
    assert ReconstructionConfig(dims=6).sampling_offset == 0.25
    assert ReconstructionConfig(dims=4).sampling_offset == 0.0
    # 6D: the images weigh more against the entropy (with the offset)
    assert ReconstructionConfig(dims=6).penalty_end == 3e4
    assert ReconstructionConfig(dims=4).penalty_end == 1e4
    assert ReconstructionConfig(dims=6, penalty_end=5e3).penalty_end == 5e3
    # older configs name the image distance and the unseen prior, fixed now
    old = {**ReconstructionConfig(dims=6).to_dict(), "image_loss": "kl"}
    old["unseen_prior"] = "pair"
    assert ReconstructionConfig.from_dict(old) == ReconstructionConfig(dims=6)
    d = ReconstructionConfig(dims=6).to_dict()
    # the prior term on the unseen directions: 1e3 in 6D, none in 4D; runs
    # saved before it trained without it (under its earlier name, or with
    # the stages that moved members after training, whose settings are dropped)
    assert ReconstructionConfig(dims=6).unseen_weight == 1e3
    assert ReconstructionConfig(dims=4).unseen_weight == 0.0
    d = ReconstructionConfig(dims=6, unseen_weight=50.0).to_dict()
    assert ReconstructionConfig.from_dict(d).unseen_weight == 50.0
    del d["unseen_weight"]
    assert ReconstructionConfig.from_dict(d).unseen_weight == 0.0
    old = {
        **d,
        "place_unseen": True,
        "hold_unseen": 0.0,
        "refit_steps": 60,
        "refit_lr": 3e-3,
        "refit_hold": 1e4,
        "probe_unseen": 0.05,
        "probe_gain": 5e-4,
        "probe_points": 2,
        "probe_away": True,
        "polish_moments": True,
        "place_coupling": False,
    }
    restored = ReconstructionConfig.from_dict(old)
    assert restored.unseen_weight == 0.0
    assert restored == ReconstructionConfig.from_dict({**d, "unseen_weight": 0.0})
    # the moment term: 3 in 4D, 1 in 6D; runs saved before it trained without it
    assert ReconstructionConfig(dims=6).moment_weight == 1.0
    assert ReconstructionConfig(dims=4).moment_weight == 3.0
    assert "moment_weight" in d
    del d["moment_weight"]
    assert ReconstructionConfig.from_dict(d).moment_weight == 0.0


def test_sampling_offset_reaches_the_image_penalty(small_scan, monkeypatch) -> None:
    from diffaccel.reconstruction import losses

    seen: list[float] = []
    init = losses.ImagePenalty.__init__

    def spy(self, *args, **kwargs) -> None:
        init(self, *args, **kwargs)
        seen.append(self.offset)

    monkeypatch.setattr(losses.ImagePenalty, "__init__", spy)
    cfg = ReconstructionConfig(**FAST)
    monkeypatch.setattr(ReconstructionConfig, "sampling_offset", 0.5)
    r = reconstruct(small_scan, cfg, uncertainty=False)
    # the noise of the images as compared: the file's 1-pixel screens with the
    # scan's loss smoothing on top
    from diffaccel.reconstruction.training import compared_for

    [compared], _ = compared_for(cfg, [r.forward], [small_scan.mean_images()])
    kappa = compared.pixel_kernel_sum_sq()
    assert kappa < r.forward.pixel_kernel_sum_sq()  # smoothing lowers the noise
    assert seen == [pytest.approx(0.5 * kappa / cfg.n_particles, rel=1e-12)]


def test_config_fields_come_in_four_groups() -> None:
    groups = ReconstructionConfig(dims=6).groups()
    assert list(groups) == ["model", "schedule", "image term", "prior"]
    names = [n for g in groups.values() for n in g]
    assert len(names) == len(set(names)) == len(fields(ReconstructionConfig)) <= 17
    assert groups["prior"]["unseen_weight"] == 1e3


def test_configs_with_fixed_settings_and_runtime_choices_are_read() -> None:
    """Older result folders and checkpoints store settings that are fixed now
    and runtime choices that are arguments now: both are dropped."""
    six = ReconstructionConfig(dims=6, seed=2)
    old = {
        **six.to_dict(),
        "quasi_random": True,
        "lr_min": 1e-4,
        "penalty_start": 10.0,
        "entropy_radius": 4.0,
        "prior_factor": 3.0,
        "sampling_offset": 0.25,
        "checkpoint_every": 100,
        "report_every": 10,
        "cuda_graph": True,
    }
    assert ReconstructionConfig.from_dict(old) == six
    with pytest.raises(TypeError, match="report_every"):
        ReconstructionConfig(report_every=10)  # an argument of training now


@pytest.mark.parametrize("name", ["checkpoint_every", "report_every"])
def test_runtime_choices_below_one_step_are_refused(small_scan, name: str) -> None:
    cfg = ReconstructionConfig(**FAST)
    with pytest.raises(ValueError, match=f"{name} must be an integer >= 1"):
        reconstruct(small_scan, cfg, uncertainty=False, **{name: 0})


def test_config_files_from_before_the_steps_rename_are_read() -> None:
    d = ReconstructionConfig(steps=6, snapshots=2).to_dict()
    d["epochs"] = d.pop("steps")
    assert ReconstructionConfig.from_dict(d).steps == 6


def test_a_checked_selection_is_not_checked_again(small_scan) -> None:
    from diffaccel.reconstruction import as_scans, training_selection

    scans = as_scans(small_scan)
    sel = training_selection(scans, "even")
    assert training_selection(scans, sel) is sel
    assert training_selection(scans, dict(sel)) == sel  # a plain dict is checked
    with pytest.raises(ValueError, match="distinct integers"):
        training_selection(scans, {"scan": [0, 0]})


def test_transfer_maps_are_computed_once_per_run(small_scan, monkeypatch) -> None:
    from diffaccel.dynamics import Beamline
    from diffaccel.reconstruction import evaluate

    calls = []
    real = Beamline.transfer_map

    def counted(self, *args, **kwargs):
        out = real(self, *args, **kwargs)
        calls.append(out.shape[0])
        return out

    # every map is a Beamline.transfer_map: the initial fit, the unconstrained
    # flags, the 4D training step (linear maps) and the uncertainty analysis
    monkeypatch.setattr(Beamline, "transfer_map", counted)
    cfg = ReconstructionConfig(**{**FAST, "steps": 3, "snapshots": 1})
    assert cfg.dims == 4  # the linear-map training path
    r = reconstruct(small_scan, cfg, train_indices=[0, 2, 4], uncertainty=True)
    assert "uncertainty" in r.info
    assert calls == [3]  # one computation for the 3 training settings
    evaluate(r, small_scan)
    # and one for the evaluation's predictions of every setting (4D: images
    # through the maps instead of tracking)
    assert calls == [3, small_scan.n_settings]
    assert r.unconstrained_coordinates() == r.info["unconstrained_coordinates"]
    # recomputed from the forward models (another tolerance bypasses the stored)
    recomputed = r.unconstrained_coordinates(tolerance=1.0000001e-3)
    assert recomputed == r.info["unconstrained_coordinates"]


def test_training_starts_from_an_initial_model(small_scan) -> None:
    """``initial_model``: training starts from a given generator state."""
    fwd = ScreenForwardModel.from_dataset(small_scan, blur_pixels=1.0)
    images, sets = small_scan.mean_images(), small_scan.settings
    guess = fit_gaussian([fwd], [images], [sets])
    cfg = ReconstructionConfig(**{**FAST, "steps": 4, "snapshots": 1})
    start = train_generator(fwd, images, sets, guess, cfg).model
    # a learning rate too small to move: the result is the initial model
    still = replace(cfg, lr_max=1e-12, seed=3)
    out = train_generator(fwd, images, sets, guess, still, initial_model=start).model
    for k, v in start.items():
        torch.testing.assert_close(out[k], v, rtol=0, atol=1e-9)
    fresh = train_generator(fwd, images, sets, guess, still).model
    assert not torch.allclose(fresh["log_scale"], start["log_scale"])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("dims", [4, 6])
def test_cuda_training_matches_cpu_in_distribution(small_scan, dims: int) -> None:
    # the initial weights come from the same CPU generator; the per-step
    # samples from a device generator (another random stream on CUDA), so the
    # two runs differ like two seeds: on the CPU seeds 0-3 give rms sizes
    # within 2 % of their mean after these 24 steps
    cfg = ReconstructionConfig(dims=dims, **FAST)
    rms = {}
    for device in ("cpu", "cuda"):
        r = reconstruct(small_scan, cfg, device=device, uncertainty=False)
        assert all(math.isfinite(v) for v in r.history["loss"])
        rms[device] = torch.tensor(r.history["rms"][-1])[:4]
    assert torch.allclose(rms["cpu"], rms["cuda"], rtol=0.06)


def _aten_ops(scan, steps: int, **config) -> tuple[int, int]:
    cfg = ReconstructionConfig(n_particles=1024, steps=steps, snapshots=1, **config)
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as p:
        reconstruct(scan, cfg, uncertainty=False)
    names = [e.name for e in p.events() if e.name.startswith("aten::")]
    syncs = sum(n in ("aten::item", "aten::_local_scalar_dense") for n in names)
    return len(names), syncs


def test_default_4d_step_stays_within_the_op_budget(small_scan) -> None:
    # budget: at most 300 ATen ops (nested ones included) and 1 host sync per
    # step without the moment term, and 80 more for the moment term (its
    # written-out gradient, 75); the difference of two runs cancels set-up
    # and bookkeeping (the same snapshot count, reads every report_every = 10
    # steps in both). A fresh placeholder tensor per step pushes the count
    # without the moment term to 304.4; the moment term through autograd
    # costs 127
    # (for a generator of 2 hidden layers; each further layer, as in the
    # default 4D generator, adds its matrix product, activation and their
    # gradients: at most 20 ops)
    per_step = {}
    small = {"width": 48, "depth": 2}
    for weight in (0.0, None):  # None: the 4D default (3)
        (ops_short, syncs_short), (ops_long, syncs_long) = (
            _aten_ops(small_scan, s, moment_weight=weight, **small) for s in (20, 40)
        )
        per_step[weight] = (ops_long - ops_short) / 20
        assert (syncs_long - syncs_short) / 20 <= 1
    assert 250 < per_step[0.0] <= 300
    assert 0 < per_step[None] - per_step[0.0] <= 80
    default = ReconstructionConfig()
    (ops_short, syncs_short), (ops_long, syncs_long) = (
        _aten_ops(small_scan, s) for s in (20, 40)
    )
    assert (syncs_long - syncs_short) / 20 <= 1
    extra = (ops_long - ops_short) / 20 - per_step[None]
    assert 0 < extra <= 20 * (default.depth - 2)


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("longitudinal_scale", (-1.0, 1.0), r"longitudinal_scale .* must be > 0"),
        ("longitudinal_scale", (1e-3,), "longitudinal_scale must be two finite"),
        ("seed", 1.5, "seed must be an integer"),
        ("n_particles", 100.5, "n_particles must be an integer"),
        ("steps", True, "steps must be an integer"),
        ("lr_max", math.inf, "lr_max must be a finite number"),
        ("lr_max", 0.0, "lr_max must be > 0"),
        ("width", 0, "width must be >= 1"),
        ("unseen_weight", "1e3", "unseen_weight must be a finite number"),
    ],
)
def test_config_refuses_wrong_types_and_values_naming_the_field(
    field: str, value: object, match: str
) -> None:
    # each of these failed only later, deep in training, with a message about
    # something else (e.g. NaN prior widths read as "loss became nan")
    with pytest.raises(ValueError, match=match):
        ReconstructionConfig(dims=6, **{field: value})


def test_config_takes_integers_for_numbers_and_lists_for_the_scale() -> None:
    config = ReconstructionConfig(dims=6, unseen_weight=1000, longitudinal_scale=[1, 2])
    assert config.unseen_weight == 1000
    assert config.longitudinal_scale == (1, 2)
    assert ReconstructionConfig.from_dict(config.to_dict()) == config


@pytest.mark.parametrize("dims", [4, 6])
def test_non_finite_generated_particles_are_reported_as_divergence(
    small_scan, monkeypatch: pytest.MonkeyPatch, dims: int
) -> None:
    # the particle checks of tracking name user input ("remove or fix them");
    # for the generator's own output the error must say that training diverged
    sample = FlatGenerator.sample

    def poisoned(self, generator):
        return sample(self, generator) * math.nan

    monkeypatch.setattr(FlatGenerator, "sample", poisoned)
    config = ReconstructionConfig(dims=dims, n_particles=256, steps=2, snapshots=1)
    with pytest.raises(FloatingPointError, match="training diverged at step 0"):
        reconstruct(small_scan, config, uncertainty=False)


def test_damaged_tensor_files_get_a_safe_one_line_error(tmp_path: Path) -> None:
    torch.save({"a": torch.ones(3)}, tmp_path / "good.pt")
    good = (tmp_path / "good.pt").read_bytes()
    files = {
        "garbage.pt": bytes(range(256)) * 2,
        "cut.pt": good[: len(good) // 2],
        "empty.pt": b"",
        "pickle.pt": pickle.dumps(object),
    }
    for name, content in files.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(ValueError) as err:
            load_tensors(tmp_path / name, "ensemble")
        text = str(err.value)
        assert text.startswith(f"cannot read ensemble {tmp_path / name}: ")
        assert "not written by diffaccel, or damaged since" in text
        # torch's own text suggests weights_only=False, i.e. running the file
        assert "weights_only" not in text and "\n" not in text
    with pytest.raises(ValueError, match="No such file or directory"):
        load_tensors(tmp_path / "missing.pt", "ensemble")


def test_reconstruct_names_a_device_or_checkpoint_it_cannot_use(
    small_scan, tmp_path: Path
) -> None:
    config = ReconstructionConfig(n_particles=256, steps=2, snapshots=1)
    with pytest.raises(ValueError, match="'tpu' is not a torch device"):
        reconstruct(small_scan, config, device="tpu")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="CUDA is not available"):
            reconstruct(small_scan, config, device="cuda")
    with pytest.raises(ValueError, match="is a folder; give a file name in it"):
        reconstruct(small_scan, config, checkpoint=tmp_path)
