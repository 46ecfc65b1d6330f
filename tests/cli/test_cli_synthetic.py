"""``diffaccel synthetic`` through click's CliRunner."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from diffaccel.cli.main import main
from diffaccel.data import read_quad_scan

SMALL = ["--particles", "1000", "--settings", "5", "--shape", "32", "24"]


def test_writes_dataset_and_summary(tmp_path: Path) -> None:
    out = tmp_path / "scan.h5"
    args = ["synthetic", str(out), *SMALL, "--pixel-size", "0.002", "--seed", "7"]
    result = CliRunner().invoke(main, [*args, "--preset", "correlated"])
    assert result.exit_code == 0, result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"wrote {out}: 5 settings")
    ds = read_quad_scan(out)
    assert ds.shape == (5, 1, 32, 24)
    assert ds.pixel_size == pytest.approx((2e-3, 2e-3))
    assert ds.ground_truth.shape == (1000, 6)
    assert ds.metadata["synthetic"]["seed"] == 7
    assert ds.settings[0, 0].item() == -25.0 and ds.settings[-1, 0].item() == 15.0


def test_noise_shots_and_k1_range(tmp_path: Path) -> None:
    out = tmp_path / "scan.h5"
    args = [*SMALL, "--noise", "0.1", "--shots", "3", "--k1-min", "-5", "--k1-max", "5"]
    result = CliRunner().invoke(main, ["synthetic", str(out), *args])
    assert result.exit_code == 0, result.output
    ds = read_quad_scan(out)
    assert ds.shape == (5, 3, 32, 24)
    assert not torch.equal(ds.images[:, 0], ds.images[:, 1])  # shots differ
    assert ds.settings[:, 0].tolist() == [-5.0, -2.5, 0.0, 2.5, 5.0]


def test_refuses_to_overwrite_without_force(tmp_path: Path) -> None:
    out = tmp_path / "scan.h5"
    out.write_bytes(b"keep me")
    runner = CliRunner()
    result = runner.invoke(main, ["synthetic", str(out), *SMALL])
    assert result.exit_code != 0
    assert "--force" in result.output
    assert out.read_bytes() == b"keep me"
    # --force replaces only a file diffaccel wrote: this one is the user's
    result = runner.invoke(main, ["synthetic", str(out), *SMALL, "--force"])
    assert result.exit_code == 1
    assert "was not written by diffaccel" in result.output
    assert out.read_bytes() == b"keep me"
    out.unlink()
    assert runner.invoke(main, ["synthetic", str(out), *SMALL]).exit_code == 0
    result = runner.invoke(main, ["synthetic", str(out), *SMALL, "--force"])
    assert result.exit_code == 0, result.output
    assert read_quad_scan(out).n_settings == 5


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--preset", "flat"], "Invalid value for '--preset'"),
        (["--pixel-size", "-1"], "Invalid value for '--pixel-size'"),
        (["--pixel-size", "10", "--shape", "4", "4"], None),
    ],
    ids=["preset", "pixel_size", "off_screen_ok"],
)
def test_bad_options(tmp_path: Path, args: list[str], message: str | None) -> None:
    result = CliRunner().invoke(main, ["synthetic", str(tmp_path / "s.h5"), *args])
    if message is None:  # a huge screen is fine: the whole beam in few pixels
        assert result.exit_code == 0, result.output
    else:
        assert result.exit_code == 2
        assert message in result.output


def test_beam_off_screen_is_an_error(tmp_path: Path) -> None:
    # 1 um pixels: a 32 x 24 um screen sees almost none of a mm-sized beam
    args = ["synthetic", str(tmp_path / "s.h5"), *SMALL, "--pixel-size", "1e-6"]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 1
    assert "misses the screen" in result.output
    assert not (tmp_path / "s.h5").exists()


def test_awa6d_layout_writes_version_2(tmp_path: Path) -> None:
    from diffaccel.data import read_scans

    out = tmp_path / "six.h5"
    args = ["synthetic", str(out), "--layout", "awa6d", "--particles", "3000"]
    r = CliRunner().invoke(main, [*args, "--settings", "2", "--shape", "32", "32"])
    assert r.exit_code == 0, r.output
    ms = read_scans(out)
    assert ms.names == ["dipole_off", "dipole_on"]
    assert ms["dipole_on"].shape == (4, 1, 32, 32)
    assert ms["dipole_on"].setting_names == ["SCAN_QUAD.k1", "SCAN_TDC.voltage"]
    r = CliRunner().invoke(main, [*args, "--pixel-size", "1e-3", "--force"])
    assert r.exit_code == 2 and "DYG1/DYG2 calibration" in r.output


def test_shape_one_by_one_is_refused(tmp_path: Path) -> None:
    r = CliRunner().invoke(
        main, ["synthetic", str(tmp_path / "s.h5"), "--shape", "1", "1"]
    )
    assert r.exit_code == 2 and "Invalid value for '--shape'" in r.output
