"""What the prior sets in the AWA 6D layout: the unseen correlations' report."""

from __future__ import annotations

import pytest
import torch
from test_unseen import _beam_cov, _change, _maps, _quad_scan_maps, _screen_moments

from diffaccel.reconstruction.prior_dependence import (
    move_to_partial,
    partial_correlation,
    prior_dependence,
)
from diffaccel.reconstruction.unseen import traded_pairs, unseen_directions


def _emit_z(cov: torch.Tensor) -> float:
    return float(torch.linalg.det(cov[4:6, 4:6]).sqrt())


def test_moves_reach_each_partial_correlation_without_changing_the_screens() -> None:
    maps, cov = _maps(), _beam_cov()
    v = unseen_directions(maps, cov)
    before = _screen_moments(maps, cov)
    for d, pair in zip(v, traded_pairs(v, cov), strict=True):
        for target in (-0.3, -0.1, 0.1, 0.3):
            moved = move_to_partial(cov, d, pair, target)
            assert moved is not None
            assert partial_correlation(moved, *pair) == pytest.approx(target, abs=1e-9)
            assert float(torch.linalg.eigvalsh(moved).min()) > 0
            # on the unseen line: the screens' second moments stay (< 1 % of
            # the spot size^2; a seen pz change of 20 % moves them > 5 %)
            assert _change(_screen_moments(maps, moved), before) < 1e-2


def test_report_gives_the_moved_beams_moments() -> None:
    maps, cov = _maps(), _beam_cov()
    report = prior_dependence(maps, cov, (-0.1, 0.1))
    assert {e["pair"] for e in report} == {"px-pz", "py-z"}
    v = unseen_directions(maps, cov)
    pairs = traded_pairs(v, cov)
    for e in report:
        names = e["pair"].split("-")
        coords = ["x", "px", "y", "py", "z", "pz"]
        pair = (coords.index(names[0]), coords.index(names[1]))
        d = v[pairs.index(pair)]
        assert e["partial_correlation"] == pytest.approx(
            partial_correlation(cov, *pair), abs=1e-12
        )
        k = coords.index(e["moves"][len("rms_") :])
        assert k == (5 if pair == (1, 5) else 4)  # pz variance, z variance
        for at in e["if_partial_correlation"]:
            moved = move_to_partial(cov, d, pair, at["partial_correlation"])
            change = at["relative_change"]
            assert change["emit_z"] == pytest.approx(
                _emit_z(moved) / _emit_z(cov) - 1, rel=1e-9
            )
            assert change[e["moves"]] == pytest.approx(
                float((moved[k, k] / cov[k, k]).sqrt()) - 1, rel=1e-9
            )
            ratio = (torch.linalg.det(moved) / torch.linalg.det(cov)).sqrt()
            assert change["emit_6d"] == pytest.approx(float(ratio) - 1, rel=1e-9)
    # this beam (z-pz 0.7, px-pz partial -0.20): a px-pz partial correlation
    # of +0.1 instead gives the same screens with a 31 % larger z emittance,
    # -0.1 a 9 % larger one (the line passes the smallest emittance between)
    pxpz = next(e for e in report if e["pair"] == "px-pz")
    ez = [a["relative_change"]["emit_z"] for a in pxpz["if_partial_correlation"]]
    assert ez[0] == pytest.approx(0.091, abs=0.005)
    assert ez[1] == pytest.approx(0.308, abs=0.005)


def test_unreachable_partial_correlation_is_reported_as_none() -> None:
    maps, cov = _maps(), _beam_cov()
    report = prior_dependence(maps, cov, (-0.99,))
    pxpz = next(e for e in report if e["pair"] == "px-pz")
    # -0.99 lies past the edge where the covariance stops being positive definite
    assert pxpz["if_partial_correlation"][0]["relative_change"] is None


def test_no_report_without_unseen_directions() -> None:
    # a quadrupole scan alone: z and pz are not seen at all, the prior sets
    # them whole (unconstrained_coordinates), no correlation is traded
    assert prior_dependence(_quad_scan_maps(), _beam_cov()) == []


@pytest.mark.parametrize(
    "bad", [torch.eye(5), torch.full((6, 6), float("nan")), -torch.eye(6)]
)
def test_bad_covariance_is_refused(bad: torch.Tensor) -> None:
    with pytest.raises(ValueError, match="cov"):
        prior_dependence(_maps(), bad.double())
