"""The experiment design as text and JSON, and the beam of a moment posterior."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from diffaccel.data import write_scans
from diffaccel.plotting.design import design_figures
from diffaccel.reconstruction import design as dz
from diffaccel.reconstruction.design_report import (
    design_answers,
    design_inputs,
    design_json,
    design_lines,
    posterior_beam,
)
from diffaccel.reconstruction.uncertainty import MomentUncertainty


@pytest.fixture(scope="module")
def answers(small_awa6d):
    layouts = dz.layouts_from_dataset(small_awa6d)
    cov = torch.cov(small_awa6d.ground_truth.double().T)
    obs = dz.observability(layouts, cov).to_dict()
    knobs = [dz.parse_knob("SCAN_TDC.voltage=-4e6:4e6")]
    return obs, dz.recommend(layouts, cov, knobs, max_images_per_scan=2)


def test_design_lines_without_and_with_a_report(answers) -> None:
    obs, report = answers
    plain = design_lines(None, obs)
    assert plain[0] == obs["summary"]
    assert plain[1].startswith("singular values (relative, smallest 4): ")
    assert plain[2] == "determined: " + ", ".join(obs["determined"])
    unseen = [line for line in plain if line.startswith("  unseen: ")]
    assert len(unseen) == len(obs["unseen"]) > 0
    full = design_lines(report, obs)
    assert full[: len(plain)] == plain
    assert full[len(plain)].startswith("today's relative std: emit_z ")
    assert "recommended added settings:" in full
    n_rows = sum(1 for line in full if line[:2].strip().isdigit())
    assert n_rows == len(report["recommended"])


def test_design_json_is_json_and_keeps_the_report(answers) -> None:
    obs, report = answers
    plain = design_json(None, obs)
    assert plain == {"unseen": obs["unseen"], "recommended": [], "observability": obs}
    full = json.loads(json.dumps(design_json(report, obs)))
    assert full["baseline_std"] == pytest.approx(report["baseline_std"])
    assert len(full["recommended"]) == len(report["recommended"])
    assert set(full) == {
        "unseen", "recommended", "observability", "baseline_std", "excluded"
    }  # fmt: skip


def test_design_figures_follow_the_report(answers) -> None:
    obs, report = answers
    assert [n for n, _ in design_figures(obs)] == ["singular_values.png"]
    names = [n for n, _ in design_figures(obs, report)]
    assert names == ["singular_values.png", "expected_std.png"]


def test_posterior_beam_fills_the_longitudinal_block_of_a_4d_result() -> None:
    cov = torch.diag(torch.tensor([4.0, 1.0, 9.0, 1.0, 0.0, 0.0])) * 1e-6
    cov[0, 4] = cov[4, 0] = 1e-7  # not reconstructed in 4D: dropped
    theta = torch.eye(21)
    unc = MomentUncertainty(
        dims=4, mean=torch.zeros(6), cov=cov.float(), theta_cov=theta,
        centroid_cov=torch.eye(4),
        diagnostics={"error_scale_second_moments": [0.01, 0.03, 0.02]},
    )  # fmt: skip
    beam, post, rel = posterior_beam(unc)
    assert beam.dtype == torch.float64 and post is theta
    assert rel == pytest.approx(0.02)  # the median
    assert float(beam[0, 4]) == 0.0
    assert float(beam[4, 4]) == pytest.approx(dz.LONGITUDINAL_RMS[0] ** 2)
    assert float(beam[0, 0]) == pytest.approx(4e-6)
    assert unc.cov[0, 4] != 0  # the result's own covariance is not changed
    unc.diagnostics = {}
    assert posterior_beam(unc)[2] is None


def test_design_answers_read_a_scan_file_and_recommend(
    small_awa6d, tmp_path: Path
) -> None:
    path = write_scans(small_awa6d, tmp_path / "scans.h5")
    layouts, cov, posterior, rel = design_inputs(path)
    assert len(layouts) == len(small_awa6d.names) and cov.shape == (6, 6)
    assert posterior is None and rel is None
    obs, report = design_answers(path)
    assert report is None and obs == dz.observability(layouts, cov).to_dict()
    obs, report = design_answers(
        path, knobs=["SCAN_TDC.voltage=-4e6:4e6"], max_images_per_scan=2
    )
    assert report is not None and report["recommended"]
    with pytest.raises(ValueError, match=r"^--result \S*nothing: "):
        design_inputs(path, tmp_path / "nothing")


def test_design_inputs_name_the_file_and_the_problem(tmp_path: Path) -> None:
    bad = tmp_path / "spec.json"
    bad.write_text("[1, 2]")
    with pytest.raises(ValueError, match=r"spec.json: expected a JSON object"):
        design_inputs(bad)
    bad.write_text("{")
    with pytest.raises(ValueError, match=r"spec\.json: not a readable JSON file"):
        design_inputs(bad)
