"""The library's result-folder writer and resume policy."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from diffaccel.cli import main
from diffaccel.data import (
    make_synthetic_quad_scan,
    partial_folder,
    read_scans,
    result_folder,
    write_quad_scan,
)
from diffaccel.reconstruction import (
    ReconstructionConfig,
    as_scans,
    reconstruct,
    training_selection,
)
from diffaccel.reconstruction.results import (
    OWNED,
    SELECTION,
    OptionError,
    ResumeError,
    RunError,
    config_options,
    demo_config,
    demo_dataset,
    demo_report_markdown,
    finding_lines,
    plan_run,
    read_dataset,
    resume_checkpoint,
    resume_config,
    resume_selection,
    score_lines,
    stopped_note,
    store_selection,
    write_result,
)

FAST = ["--particles", "512", "--steps", "6", "--snapshots", "2"]


@pytest.fixture(scope="module")
def scan_file(tmp_path_factory) -> Path:
    ds = make_synthetic_quad_scan(
        "gaussian",
        n_particles=2000,
        n_settings=6,
        k1_range=(-8.0, 8.0),
        screen_shape=(24, 24),
        pixel_size=(1e-3, 1e-3),
        seed=2,
    )
    path = tmp_path_factory.mktemp("scan") / "scan.h5"
    write_quad_scan(ds, path)
    return path


def test_cli_and_library_write_byte_identical_summaries(
    scan_file: Path, tmp_path: Path, monkeypatch
) -> None:
    # a frozen clock: the wall times are the only numbers that differ by run
    monkeypatch.setattr(time, "perf_counter", lambda: 0.0)
    cli_out = tmp_path / "cli"
    args = ["reconstruct", str(scan_file), "--out", str(cli_out), "--no-figures"]
    r = CliRunner().invoke(main, [*args, "--train-indices", "even", *FAST])
    assert r.exit_code == 0, r.output
    ds = as_scans(read_scans(scan_file))
    selection = training_selection(ds, "even")
    config = ReconstructionConfig(n_particles=512, steps=6, snapshots=2)
    lib_out = tmp_path / "lib"
    with result_folder(lib_out, command="reconstruct", owned=OWNED) as folder:
        result = reconstruct(ds, config, train_indices=selection, device="cpu")
        summary = write_result(
            result, ds, folder.path, dataset_path=scan_file, train_indices=selection
        )
    want = (cli_out / "summary.json").read_bytes()
    assert (lib_out / "summary.json").read_bytes() == want
    assert summary["train_indices"] == [0, 2, 4]
    assert {p.name for p in lib_out.iterdir()} == {
        ".diffaccel-result",
        "ensemble.pt",
        "particles.h5",
        "report.md",
        "summary.json",
    }


def test_resume_policy_refuses_other_settings_and_options(
    scan_file: Path, tmp_path: Path
) -> None:
    ds = as_scans(read_scans(scan_file))
    even, odd = training_selection(ds, "even"), training_selection(ds, "odd")
    store_selection(tmp_path, even)
    assert json.loads((tmp_path / SELECTION).read_text()) == {
        "train_indices": {"scan": [0, 2, 4]}
    }
    assert resume_selection(tmp_path, ds, odd, given=False) == even
    with pytest.raises(ResumeError, match="trained on other settings"):
        resume_selection(tmp_path, ds, odd, given=True)
    # a run without the file resumes with what is given
    assert resume_selection(tmp_path / "none", ds, odd, given=True) == odd
    stored = ReconstructionConfig(steps=6, snapshots=2)
    asked = ReconstructionConfig(steps=8, snapshots=2)
    assert resume_config(stored, asked, given=set()) is stored
    with pytest.raises(ResumeError, match=r"--steps 8 \(checkpoint: 6\)"):
        resume_config(stored, asked, given={"--steps"})


def test_resume_checkpoint_prefers_the_staging_folder(tmp_path: Path) -> None:
    out = tmp_path / "out"
    with pytest.raises(ResumeError, match="run without --resume"):
        resume_checkpoint(out)
    partial_folder(out).mkdir()
    with pytest.raises(ResumeError, match="--force instead of --resume"):
        resume_checkpoint(out)
    out.mkdir()
    torch.save({}, out / "checkpoint.pt")
    assert resume_checkpoint(out) == out / "checkpoint.pt"
    torch.save({}, partial_folder(out) / "checkpoint.pt")
    assert resume_checkpoint(out) == partial_folder(out) / "checkpoint.pt"


def _summary(**extra) -> dict:
    moments = {"norm_emit_x": {"mean": 2e-6, "std": 1e-7}}
    metrics = {
        "images_train": {"relative_l1": 0.01234},
        "images_held_out": {"relative_l1": 0.05},
    }
    return {"metrics": metrics, "moments": moments, **extra}


def test_score_lines_give_held_out_then_training() -> None:
    assert score_lines(_summary()) == [
        "held-out image relative L1: 0.0500",
        "train image relative L1: 0.0123",
    ]


def test_score_lines_give_the_noise_beside_each_image_error() -> None:
    summary = _summary()
    summary["metrics"]["images_train"] |= {
        "prediction_noise_l1": 0.0031,
        "data_noise_l1": 0.0102,
    }
    summary["metrics"]["images_held_out"] |= {
        "prediction_noise_l1": None,
        "data_noise_l1": None,
    }
    assert score_lines(summary) == [
        "held-out image relative L1: 0.0500 (data floor unknown: single shots)",
        "train image relative L1: 0.0123 (predictions' own noise 0.003; "
        "data floor 0.010)",
    ]


def test_finding_lines_hold_only_what_the_summary_found() -> None:
    plain = finding_lines(_summary(unconstrained_coordinates=[]))
    assert plain == ["emittance (normalised): x 2 +- 0.1 mm mrad"]
    full = finding_lines(
        _summary(
            unconstrained_coordinates=["z", "pz"],
            observability="only 3 of 4 directions seen",
        )
    )
    assert full == [
        "not constrained by the scan: z, pz",
        plain[0],
        "only 3 of 4 directions seen",
    ]
    # 6D: what the prior sets comes with the command that ranks settings to add
    left = "observability: px-pz together with pz-pz unseen; left to the prior: emit_z"
    six = finding_lines(
        _summary(
            unconstrained_coordinates=[],
            observability=left,
            config={"dims": 6},
            dataset="scan.h5",
        )
    )
    assert six[-2] == left
    assert six[-1].startswith("settings that would see them: diffaccel design scan.h5")
    four = finding_lines(
        _summary(unconstrained_coordinates=[], observability=left, config={"dims": 4})
    )
    assert four[-1] == left


def test_stopped_note_names_the_kept_checkpoint(tmp_path: Path) -> None:
    out = tmp_path / "out"
    assert stopped_note(out, interrupted=False, checkpoint_every=50) is None
    note = stopped_note(out, interrupted=True, checkpoint_every=50)
    assert note is not None and "every 50 steps): nothing to resume" in note
    partial_folder(out).mkdir()
    torch.save({}, partial_folder(out) / "checkpoint.pt")
    for interrupted in (False, True):
        note = stopped_note(out, interrupted=interrupted, checkpoint_every=50)
        assert note == (
            f"note: the run's checkpoint is kept in {partial_folder(out)}; "
            f"--resume continues it ({out} is unchanged)"
        )


def test_demo_report_lists_the_moments_against_the_truth() -> None:
    rms = {"mean": [1e-3, 2e-3, 3e-3, 4e-3, 5e-3, 6e-3], "std": [1e-5] * 6}
    moments = {"rms": rms}
    moments.update({k: {"mean": 1e-6, "std": 1e-8} for k in ("emit_x", "emit_y")})
    moments["emit_6d"] = {"mean": 1e-18, "std": 1e-20}
    summary = _summary(unconstrained_coordinates=["z"])
    summary["moments"] = moments
    summary["metrics"]["ground_truth"] = {"rms_x": 0.012, "emit_6d": -0.5}
    text = demo_report_markdown(summary, "dataset.h5", 42.4)
    assert "Dataset: `dataset.h5`" in text and "Total time 42 s." in text
    assert "| rms x [mm] | 1 +- 0.01 | +1.2 % |" in text
    assert "| rms pz [1e-3] | 6 +- 0.01 | n/a |" in text
    assert "| emit_6d [m^3] | 1e-18 +- 1e-20 | -50.0 % |" in text
    assert "Held-out image relative L1: 0.0500; training: 0.0123." in text
    assert "treat them as unknown): z\n" in text


def test_plan_run_checks_config_file_charge_and_selection(
    scan_file: Path, tmp_path: Path
) -> None:
    out = tmp_path / "run"
    options = {"n_particles": 256, "steps": 4, "snapshots": 2}
    plan = plan_run(scan_file, out, options, given=set(), train_indices="even")
    assert plan.config == ReconstructionConfig(**options)
    assert plan.selection == {"scan": [0, 2, 4]} and plan.dataset.names == ["scan"]
    assert plan.checkpoint is None and not plan.finished
    assert read_dataset(scan_file).names == ["scan"]
    with pytest.raises(RunError, match=r"cannot read .*nothing.h5"):
        plan_run(tmp_path / "nothing.h5", out, options, given=set())
    with pytest.raises(RunError, match="steps"):
        plan_run(scan_file, out, {**options, "steps": 3}, given=set())
    with pytest.raises(RunError, match=r"scan.h5: bunch charge \(given\)"):
        plan_run(scan_file, out, options, given=set(), charge_C=-1.0)
    with pytest.raises(OptionError) as err:
        plan_run(
            scan_file, out, options, given=set(), train_indices="9", indices_given=True
        )
    assert err.value.option == "--train-indices"
    with pytest.raises(ResumeError, match="resume"):
        plan_run(scan_file, out, options, given=set(), resume=True)


def test_demo_inputs_are_a_6d_scan_and_a_short_6d_run() -> None:
    ds = demo_dataset(seed=3)
    assert ds.images.shape[0] == 20 and ds.images.shape[-2:] == (64, 64)
    assert torch.equal(demo_dataset(seed=3).images, ds.images)  # seeded
    config = demo_config(seed=3)
    assert (config.dims, config.steps, config.snapshots) == (6, 300, 5)
    assert (config.burn_in, config.n_particles, config.seed) == (1, 4096, 3)


def test_config_options_are_the_configs_keywords() -> None:
    given = dict(
        dims="6", particles=None, steps=60, snapshots=2, seed=1, blur=None,
        loss_smoothing="0.5",
    )  # fmt: skip
    options = config_options(**given)
    assert options["dims"] == 6 and options["loss_smoothing"] == 0.5
    assert ReconstructionConfig(**options).steps == 60
    auto = config_options(**{**given, "loss_smoothing": "auto"})
    assert auto["loss_smoothing"] == "auto"
    with pytest.raises(OptionError, match="a number of pixels or 'auto'") as err:
        config_options(**{**given, "loss_smoothing": "wide"})
    assert err.value.option == "--loss-smoothing"
