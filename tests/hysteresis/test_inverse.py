"""Inverse: the next input that reaches a target output."""

from __future__ import annotations

import pytest
import torch

from diffaccel.hysteresis import invert_preisach, next_step_output
from diffaccel.hysteresis.synthetic import synthetic_magnet

F64 = torch.float64


@pytest.fixture
def magnet():
    return synthetic_magnet(i_max=10.0, n=20)


HISTORIES = {
    "fresh": torch.tensor([0.0], dtype=F64),
    "after-max": torch.tensor([0.0, 10.0, 4.0], dtype=F64),
    "minor-loop": torch.tensor([0.0, 8.0, 2.0, 6.0], dtype=F64),
}


@pytest.mark.parametrize("history", HISTORIES, ids=list(HISTORIES))
def test_round_trip(magnet, history: str) -> None:
    h = HISTORIES[history]
    with torch.no_grad():
        targets = magnet(torch.tensor([1.3, 5.2, 7.7, 9.1], dtype=F64))
    res = invert_preisach(magnet, targets, h)
    assert res.reached.all()
    with torch.no_grad():
        state = magnet.final_state(h)
        smooth = next_step_output(magnet, res.input, state, h[-1])
        exact = magnet.predict(res.input[:, None], history=h.expand(4, -1))[:, 0]
    span = float(magnet.output_scale)
    # the smooth one-step response is what is inverted: solved to 1e-9 of scale
    torch.testing.assert_close(smooth, targets, rtol=0, atol=1e-9 * span)
    # exact relays: within the staircase and smoothing width of a 20-cell mesh
    # (hysteresis is 2 % of scale here; one row of hysterons < 10 % of it)
    torch.testing.assert_close(exact, targets, rtol=0, atol=2e-3 * span)


def test_unreachable_target_stops_at_limit(magnet) -> None:
    h = torch.tensor([0.0, 5.0], dtype=F64)
    res = invert_preisach(magnet, torch.tensor([10.0, -1.0]), h, limits=(1.0, 9.0))
    assert not res.reached.any()
    torch.testing.assert_close(res.input, torch.tensor([9.0, 1.0], dtype=F64))


def test_limits_respected(magnet) -> None:
    h = torch.tensor([0.0, 5.0], dtype=F64)
    with torch.no_grad():
        target = magnet.predict(torch.tensor([3.0], dtype=F64), history=h)
    res = invert_preisach(magnet, target, h, limits=(2.0, 4.0))
    assert res.reached.all() and 2.0 <= float(res.input) <= 4.0


def test_bad_arguments_raise(magnet) -> None:
    h = torch.tensor([0.0], dtype=F64)
    with pytest.raises(ValueError, match="NaN"):
        invert_preisach(magnet, torch.tensor([float("nan")]), h)
    with pytest.raises(ValueError, match="history"):
        invert_preisach(magnet, torch.tensor([0.1]), torch.zeros(0))
    with pytest.raises(ValueError, match="limits"):
        invert_preisach(magnet, torch.tensor([0.1]), h, limits=(5.0, 5.0))
