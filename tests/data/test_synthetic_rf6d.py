"""The RF-phase-plus-dipole 6D layout (no deflecting cavity)."""

from __future__ import annotations

import math

import pytest
import torch

from diffaccel.data import RF6D_BEAMLINES, make_synthetic_rf6d
from diffaccel.dynamics import Beamline, RFCavity


def _x_moments(scan, i: int) -> tuple[float, float]:
    """Centroid and rms x of image i [m]."""
    img = scan.mean_images().double()[i]
    xs, _ = scan.pixel_centers()
    w = img.sum(0) / img.sum()
    mean = float((w * xs).sum())
    return mean, float((w * (xs - mean) ** 2).sum()) ** 0.5


def test_layout_has_an_rf_cavity_and_no_deflector() -> None:
    for spec in RF6D_BEAMLINES.values():
        line = Beamline.from_spec(spec)
        kinds = [type(e).__name__ for e in line]
        assert "TransverseDeflectingCavity" not in kinds
        assert isinstance(line["SCAN_RF"], RFCavity)
    # the screens stay where the AWA layout has them
    from diffaccel.data import AWA6D_BEAMLINES

    for name, spec in RF6D_BEAMLINES.items():
        assert float(Beamline.from_spec(spec).length) == pytest.approx(
            float(Beamline.from_spec(AWA6D_BEAMLINES[name]).length), abs=1e-12
        )


def test_rf_phase_and_dipole_see_the_chirp() -> None:
    """correlated preset: z-pz correlation -0.7; at phase 0 the cavity adds
    +h z to pz (h = V k / p0c ~ 5.6 / m), at phase pi -h z: the dipole screen's
    x width shrinks at phase 0 and grows at pi; the straight screen never sees it."""
    ms = make_synthetic_rf6d(
        "correlated", n_particles=20_000, k1_values=[0.0], screen_shape=(96, 96)
    )
    off, on = ms["dipole_off"], ms["dipole_on"]
    assert (
        off.setting_names
        == on.setting_names
        == [
            "SCAN_QUAD.k1",
            "SCAN_RF.voltage",
            "SCAN_RF.phase",
        ]
    )
    assert on.settings[:, 1:].tolist() == [[0.0, 0.0], [4e6, 0.0], [4e6, math.pi]]
    assert off.settings[:, 1:].abs().max() == 0
    for scan in (off, on):
        assert min(scan.metadata["synthetic"]["fraction_on_screen"]) > 0.99
    widths = [_x_moments(on, i)[1] for i in range(3)]
    assert widths[1] < 0.9 * widths[0] < 0.9 * widths[2], widths
    # the reference particle sits at the zero crossing: centroids stay put
    centroids = [_x_moments(on, i)[0] for i in range(3)]
    assert max(abs(c - centroids[0]) for c in centroids) < 2e-4, centroids


def test_cli_layout_rf6d(tmp_path) -> None:
    from click.testing import CliRunner

    from diffaccel.cli.synthetic import synthetic

    out = tmp_path / "rf6d.h5"
    result = CliRunner().invoke(
        synthetic,
        [str(out), "--layout", "rf6d", "--particles", "3000", "--settings", "3"],
    )
    assert result.exit_code == 0, result.output
    assert "RF-phase-plus-dipole" in result.output
    from diffaccel.data import read_scans

    ms = read_scans(out)
    assert ms["dipole_on"].n_settings == 9 and ms["dipole_off"].n_settings == 3
    assert torch.isfinite(ms["dipole_on"].mean_images()).all()


def test_a_second_dipole_current_measures_the_energy_spread() -> None:
    """Alone the scans see pz-pz only together with px-pz (R12 and R16 of the
    dipole screen fixed over the scan); a scan at 0.8 of the bend separates
    them: the energy spread's, z emittance's and chirp's predicted std fall
    from 25-51 % to below 3 %."""
    from diffaccel.reconstruction import design as dz

    def stds(scales: tuple[float, ...]) -> dict[str, float]:
        ms = make_synthetic_rf6d(
            "correlated",
            n_particles=20_000,
            k1_values=torch.linspace(-12.0, 12.0, 5),
            dipole_scales=scales,
        )
        obs = dz.observability(
            dz.layouts_from_dataset(ms), torch.cov(ms.ground_truth.double().T)
        )
        return {q: obs.quantities[q]["relative_std"] for q in ("rms_pz", "emit_z")}

    alone, with_second = stds(()), stds((0.8,))
    assert alone["rms_pz"] > 0.2 and alone["emit_z"] > 0.4, alone
    assert with_second["rms_pz"] < 0.03 and with_second["emit_z"] < 0.04, with_second


def test_dipole_scales_add_a_scan_at_the_weaker_bend() -> None:
    ms = make_synthetic_rf6d(
        "correlated", n_particles=5000, k1_values=[-6.0, 6.0], dipole_scales=(0.8,)
    )
    assert ms.names == ["dipole_off", "dipole_on", "dipole_on_0.8"]
    weak, nominal = ms["dipole_on_0.8"], ms["dipole_on"]
    assert torch.equal(weak.settings, nominal.settings)
    angle = {
        n: Beamline.from_spec(ms[n].beamline_spec)["SCAN_DIPOLE"].angle
        for n in ("dipole_on", "dipole_on_0.8")
    }
    assert float(angle["dipole_on_0.8"]) == pytest.approx(
        0.8 * float(angle["dipole_on"]), rel=1e-12
    )
    assert min(weak.metadata["synthetic"]["fraction_on_screen"]) > 0.99
    with pytest.raises(ValueError, match="dipole_scales must be positive"):
        make_synthetic_rf6d(n_particles=100, k1_values=[0.0], dipole_scales=(0.0,))
