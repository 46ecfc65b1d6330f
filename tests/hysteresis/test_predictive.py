"""Acceptance: held-out predictions beat a straight line by 2x, honest bands.

Cases of the acceptance shapes from magnets with known symmetric densities plus
noise (``hysteresis.synthetic``), several magnets (seeds) each. The full set,
with the SLAC quadrupole, runs in ``benchmarks/preisach_acceptance.py``.
"""

from __future__ import annotations

import warnings

import pytest
import torch

from diffaccel.hysteresis import (
    InputRangeWarning,
    fit_magnet,
    predict_stream,
    symmetric_default,
)
from diffaccel.hysteresis.predictive import parse_mesh_adapt
from diffaccel.hysteresis.synthetic import bh_loop_case, bipolar_quadrupole_case


def _line_rms(current: torch.Tensor, field: torch.Tensor, n: int) -> float:
    """Held-out rms of a straight line fitted to the first ``n`` rows."""
    basis = torch.stack([torch.ones_like(current), current], dim=1)
    coef = torch.linalg.lstsq(basis[:n], field[:n, None]).solution
    return float(((basis @ coef).squeeze(1)[n:] - field[n:]).pow(2).mean().sqrt())


def _case(kind: str, seed: int):
    case = bipolar_quadrupole_case if kind == "bipolar" else bh_loop_case
    current, field, n, magnet = case(seed)
    fit = fit_magnet(
        current[:n], field[:n], initial_state=magnet.initial_state_kind, steps=150
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputRangeWarning)  # B-H: beyond the range
        with torch.no_grad():
            pred = fit.model(current)
            std = fit.band.std(fit.model, current)
    return current, field, n, fit, pred, std


@pytest.mark.parametrize(
    ("kind", "seed"),
    [("bipolar", 0), ("bipolar", 1), ("bh", 0), ("bh", 1)],
    ids=["bipolar-0", "bipolar-1", "bh-0", "bh-1"],
)
def test_acceptance_beats_straight_line(kind: str, seed: int) -> None:
    current, field, n, fit, pred, std = _case(kind, seed)
    assert fit.symmetric  # both ranges are centred on zero
    err = pred[n:] - field[n:]
    assert float(err.pow(2).mean().sqrt()) < 0.5 * _line_rms(current, field, n)
    assert (std[n:] > 0).all()


def test_band_covers_held_out_rows() -> None:
    inside = []
    for kind, seed in (("bipolar", 2), ("bh", 2)):
        _, field, n, _, pred, std = _case(kind, seed)
        inside.append(((pred[n:] - field[n:]).abs() < 2 * std[n:]).double().mean())
    # acceptance: at least 80 % of held-out points inside 2 std, over cases
    assert float(torch.stack(inside).mean()) >= 0.8


def test_symmetric_default_follows_the_range() -> None:
    assert symmetric_default((-6.06, 6.06)) is True
    assert symmetric_default((-1.65, 166.65)) is False


def test_asymmetric_misses_the_negative_half_of_a_bh_loop() -> None:
    # the symmetry is what identifies the negative half: without it the fit
    # is no better than a straight line (checks the test above can fail)
    current, field, n, _ = bh_loop_case(0)
    fit = fit_magnet(
        current[:n], field[:n], initial_state="demagnetized", symmetric=False,
        steps=150,
    )  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputRangeWarning)
        with torch.no_grad():
            pred = fit.model(current)
    err = float((pred[n:] - field[n:]).pow(2).mean().sqrt())
    assert err > 0.5 * _line_rms(current, field, n)


@pytest.mark.parametrize("chunk", [1, 7, 1000], ids=["1", "7", "1000"])
def test_stream_equals_one_pass(chunk: int) -> None:
    fit = _case("bipolar", 0)[3]
    gen = torch.Generator().manual_seed(0)
    u = -6.0 + 12.0 * torch.rand(300, generator=gen, dtype=torch.float64)
    with torch.no_grad():
        whole = fit.model(u)
        whole_std = fit.band.std(fit.model, u)
    parts = list(predict_stream(fit.model, u.split(chunk), fit.band))
    got = torch.cat([p for p, _ in parts])
    got_std = torch.cat([s for _, s in parts])
    # float64 round-off of prefix sums in a different order
    torch.testing.assert_close(got, whole, rtol=0, atol=1e-12)
    torch.testing.assert_close(got_std, whole_std, rtol=1e-5, atol=0)  # float32 sums


def test_parse_mesh_adapt_takes_auto_or_a_share() -> None:

    assert parse_mesh_adapt("auto") == "auto"
    assert parse_mesh_adapt("0.8") == 0.8 and parse_mesh_adapt("0") == 0.0
    for bad in ("1", "-0.1", "nan", "many"):
        with pytest.raises(
            ValueError, match=r"expected 'auto' or a number in \[0, 1\)"
        ):
            parse_mesh_adapt(bad)
