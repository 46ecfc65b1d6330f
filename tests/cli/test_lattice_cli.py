"""``diffaccel lattice``: listing, --out, refusal and --approximate."""

from __future__ import annotations

import json
from pathlib import Path

from click.testing import CliRunner

from diffaccel.cli.lattice import lattice

LATTICES = Path(__file__).parents[1] / "dynamics" / "lattices"


def test_lists_elements_with_units_and_writes_the_spec(tmp_path) -> None:
    out = tmp_path / "beamline.json"
    result = CliRunner().invoke(
        lattice,
        [str(LATTICES / "awa_6d.lte"), "--line", "DIPOLE_ON", "--out", str(out)],
    )
    assert result.exit_code == 0, result.output
    assert "SCAN_TDC" in result.output
    assert "frequency = 1300000000 Hz" in result.output
    assert "angle = -0.3490658504 rad" in result.output
    spec = json.loads(out.read_text())
    assert [e["name"] for e in spec][-1] == "DYG2"
    again = CliRunner().invoke(
        lattice, [str(LATTICES / "awa_6d.lte"), "--out", str(out)]
    )
    assert again.exit_code != 0 and "--force" in again.output


def test_start_end(tmp_path) -> None:
    result = CliRunner().invoke(
        lattice,
        [str(LATTICES / "awa_6d.bmad"), "--start", "D1", "--end", "SCAN_DIPOLE"],
    )
    assert result.exit_code == 0, result.output
    assert "SCAN_QUAD" not in result.output and "D3_ON" not in result.output


def test_missing_element_one_line_error_then_approximate(tmp_path) -> None:
    lte = tmp_path / "line.lte"
    lte.write_text(
        "Q1: QUAD, L=0.1, K1=2\nHK: HKICK, L=0.1, KICK=1e-3\nL1: LINE=(Q1, HK)\n"
    )
    result = CliRunner().invoke(lattice, [str(lte)])
    assert result.exit_code != 0
    error = [line for line in result.output.splitlines() if line.startswith("Error")]
    assert len(error) == 1 and "HK" in error[0] and "--approximate" in error[0]
    drift = CliRunner().invoke(lattice, [str(lte), "--approximate"])
    assert drift.exit_code == 0, drift.output
    assert "replaced by a drift of 0.1 m" in drift.output
    linear = CliRunner().invoke(
        lattice, [str(lte), "--approximate", "linear", "--p0c", "1e8"]
    )
    assert linear.exit_code == 0, linear.output
    assert "LinearMap" in linear.output
