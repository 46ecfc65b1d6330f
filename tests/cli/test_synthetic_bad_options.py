"""``diffaccel synthetic``: options out of range are refused naming the option."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from diffaccel.cli.main import main

CASES = {
    "shape": (["--shape", "100000", "100000"], "'--shape'"),
    "k1_min": (["--k1-min", "1e9"], "'--k1-min'"),
    "k1_max": (["--k1-max", "-2e4"], "'--k1-max'"),
    "p0c": (["--p0c", "1e-3"], "--p0c: expected >= 510.999 eV"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_refused_before_writing(tmp_path: Path, case: str) -> None:
    args, message = CASES[case]
    out = tmp_path / "x.h5"
    result = CliRunner().invoke(main, ["synthetic", str(out), *args])
    assert result.exit_code == 2, result.output
    assert message in result.output and "Traceback" not in result.output
    assert not out.exists()


def test_out_must_be_hdf5(tmp_path: Path) -> None:
    out = tmp_path / "out.txt"
    result = CliRunner().invoke(main, ["synthetic", str(out)])
    assert (
        result.exit_code == 2 and "expected a .h5 or .hdf5 file name" in result.output
    )
    assert not out.exists()
