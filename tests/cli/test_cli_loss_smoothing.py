"""``reconstruct --loss-smoothing``: a number of camera pixels or 'auto'."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from diffaccel.cli import main
from diffaccel.data import make_synthetic_quad_scan, write_quad_scan
from diffaccel.reconstruction import load

FAST = ["--particles", "512", "--steps", "6", "--snapshots", "2", "--no-figures"]


@pytest.fixture(scope="module")
def scan_file(tmp_path_factory) -> Path:
    ds = make_synthetic_quad_scan(
        "gaussian",
        n_particles=2000,
        n_settings=4,
        k1_range=(-8.0, 8.0),
        screen_shape=(40, 40),
        pixel_size=(5e-4, 5e-4),
        seed=3,
    )
    path = tmp_path_factory.mktemp("scan") / "scan.h5"
    write_quad_scan(ds, path)
    return path


@pytest.mark.parametrize(("given", "stored"), [("auto", "auto"), ("2.5", 2.5)])
def test_loss_smoothing_reaches_the_config(
    scan_file: Path, tmp_path: Path, given: str, stored: object
) -> None:
    out = tmp_path / "run"
    args = ["reconstruct", str(scan_file), "--out", str(out), *FAST]
    result = CliRunner().invoke(main, [*args, "--loss-smoothing", given])
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["config"]["loss_smoothing"] == stored
    assert load(out).config.loss_smoothing == stored  # the folder loads again


def test_a_bad_loss_smoothing_is_one_line(scan_file: Path, tmp_path: Path) -> None:
    args = ["reconstruct", str(scan_file), "--out", str(tmp_path / "r"), *FAST]
    result = CliRunner().invoke(main, [*args, "--loss-smoothing", "fine"])
    assert result.exit_code != 0
    assert "--loss-smoothing" in result.output
    assert "expected a number of pixels or 'auto'" in result.output
    assert "Traceback" not in result.output
