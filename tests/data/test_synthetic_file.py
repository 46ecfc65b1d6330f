"""Synthetic quad-scan files written from a request."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from diffaccel.data import OptionError, read_scans
from diffaccel.data.owned_files import OutputFileError
from diffaccel.data.synthetic_file import (
    SyntheticRequest,
    check_synthetic,
    write_synthetic,
)

SMALL = SyntheticRequest(
    layout="quad", preset="gaussian", particle_file=None, n_particles=300,
    n_settings=3, k1_min=None, k1_max=None, shape=(16, 12), pixel_size=None,
    p0c=None, image_method=None, noise=0.0, noise_model="poisson", shots=1, seed=0,
)  # fmt: skip


def test_quad_layout_uses_its_defaults(tmp_path: Path) -> None:
    out = tmp_path / "q.h5"
    line = write_synthetic(SMALL, out, overwrite=False)
    assert line.startswith(f"wrote {out}: 3 settings (k1 -25 .. 15 1/m^2) x 1 shot")
    assert "of 16x12 px at 1 mm, preset gaussian, 300 particles" in line
    assert "kde images" in line
    scans = read_scans(out)
    assert scans.format_version == 1 and len(scans) == 1
    (scan,) = (s for _, s in scans)
    assert scan.n_settings == 3 and tuple(scan.screen_shape) == (16, 12)
    assert scan.settings[:, 0].tolist() == pytest.approx([-25.0, -5.0, 15.0])
    with pytest.raises(FileExistsError):
        write_synthetic(SMALL, out, overwrite=False)


def test_6d_layouts_write_two_scans_and_refuse_a_pixel_size(tmp_path: Path) -> None:
    awa = replace(SMALL, layout="awa6d", n_settings=2, shape=(16, 16))
    line = write_synthetic(awa, tmp_path / "a.h5", overwrite=False)
    assert "(format version 2, AWA 6D layout)" in line and "TDC {0, 4 MV}" in line
    scans = read_scans(tmp_path / "a.h5")
    assert scans.format_version == 2 and len(scans) == 2
    assert all(s.n_settings >= 2 for _, s in scans)
    with pytest.raises(ValueError, match="DYG1/DYG2 calibration"):
        write_synthetic(replace(awa, pixel_size=1e-3), tmp_path / "b.h5", False)
    assert not (tmp_path / "b.h5").exists()


def test_check_synthetic_names_the_option_it_refuses(tmp_path: Path) -> None:
    out = tmp_path / "s.h5"
    check_synthetic(SMALL, out, force=False)
    cases = [
        (SMALL, tmp_path / "s.npy", "OUT", "expected a .h5 or .hdf5 file name"),
        (replace(SMALL, p0c=1.0), out, "--p0c", "expected >= "),
        (replace(SMALL, layout="rf6d", pixel_size=1e-3), out, "--pixel-size", "rf6d"),
    ]
    for request, path, option, text in cases:
        with pytest.raises(OptionError) as err:
            check_synthetic(request, path, force=False)
        assert err.value.option == option and text in str(err.value)
    out.write_text("mine")
    with pytest.raises(OutputFileError, match="pass --force"):
        check_synthetic(SMALL, out, force=False)
