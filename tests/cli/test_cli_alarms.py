"""Fit-quality alarms printed by ``diffaccel predict``."""

from __future__ import annotations

import torch
from click.testing import CliRunner

from diffaccel.cli import main
from diffaccel.data import make_synthetic_awa6d, make_synthetic_quad_scan, write_scans
from diffaccel.reconstruction import ReconstructionConfig, reconstruct


def test_predict_warns_a_4d_result_through_a_cavity(tmp_path) -> None:
    scan = make_synthetic_quad_scan(
        "gaussian",
        n_particles=1000,
        n_settings=4,
        screen_shape=(16, 16),
        pixel_size=(2e-3, 2e-3),
    )
    result = reconstruct(
        scan,
        ReconstructionConfig(n_particles=256, steps=2, snapshots=1),
        uncertainty=False,
    )
    result.save(tmp_path / "result")
    awa = make_synthetic_awa6d(
        "gaussian",
        n_particles=1000,
        k1_values=torch.tensor([-6.0, 6.0]),
        screen_shape=(16, 16),
    )
    write_scans(awa, tmp_path / "awa.h5")
    args = ["predict", str(tmp_path / "result"), "--particles", "500"]
    r = CliRunner().invoke(
        main,
        [
            *args,
            "--dataset",
            str(tmp_path / "awa.h5"),
            "--out",
            str(tmp_path / "pred.h5"),
        ],
    )
    assert r.exit_code == 0, r.output
    assert (
        "warning: a 4D reconstruction (z = pz = 0 for every particle) is "
        "predicted through elements that read z or pz" in r.output
    )
    assert "TransverseDeflectingCavity" in r.output and "--dims 6" in r.output
    # the same result on its own quadrupole line: no such warning
    r = CliRunner().invoke(
        main, [*args, "--settings", "-5; 5", "--out", str(tmp_path / "p.npy")]
    )
    assert r.exit_code == 0, r.output
    assert "4D reconstruction" not in r.output
