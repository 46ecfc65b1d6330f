"""Inverse: the next input that reaches a target output."""

from __future__ import annotations

import pytest
import torch

from diffaccel.hysteresis import invert_preisach, next_step_output
from diffaccel.hysteresis.setpoint import UnreachableTargetError, plan_setpoint
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
    span = float(magnet.output_scale)
    # default: the exact relays the model predicts with, solved to round-off
    res = invert_preisach(magnet, targets, h)
    with torch.no_grad():
        exact = magnet.predict(res.input[:, None], history=h.expand(4, -1))[:, 0]
    torch.testing.assert_close(res.output, exact, rtol=0, atol=1e-12 * span)
    hit = res.reached
    assert int(hit.sum()) >= 3
    torch.testing.assert_close(exact[hit], targets[hit], rtol=0, atol=1e-9 * span)
    # a target inside a jump (a row of hysterons switching at a threshold) is
    # missed in one step by less than that row's share of the hysteresis
    assert ((exact - targets).abs()[~hit] < 2e-3 * span).all()
    # smooth=True: the smooth one-step response is what is inverted
    res = invert_preisach(magnet, targets, h, smooth=True)
    assert res.reached.all()
    with torch.no_grad():
        state = magnet.final_state(h)
        smooth = next_step_output(magnet, res.input, state, h[-1])
        exact = magnet.predict(res.input[:, None], history=h.expand(4, -1))[:, 0]
    torch.testing.assert_close(smooth, targets, rtol=0, atol=1e-9 * span)
    # exact relays at the smooth answer: within the staircase and smoothing
    # width of a 20-cell mesh (hysteresis is 2 % of scale here)
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


@pytest.mark.parametrize("history", HISTORIES, ids=list(HISTORIES))
def test_plan_setpoint_hits_every_target_exactly(magnet, history: str) -> None:
    # targets in a jump of the one-step response get another approach
    h = HISTORIES[history]
    spec = magnet.stream_spec()
    span = float(magnet.output_scale)
    with torch.no_grad():
        targets = magnet(torch.linspace(0.2, 9.8, 40, dtype=F64)).tolist()
    kinds = set()
    for t in targets:
        plan = plan_setpoint(spec, h.numpy(), t)
        with torch.no_grad():
            seq = torch.tensor(plan.sequence, dtype=F64)
            y = magnet.predict(seq, history=h)[-1]
        assert abs(plan.error) <= 1e-9 * span
        assert abs(float(y) - t) <= 1e-9 * span
        kinds.add(plan.kind)
        last = plan.cycle[-1] if plan.cycle else float(h[-1])
        assert plan.approach == ("from below" if plan.input > last else "from above")
    assert "direct" in kinds


def test_plan_setpoint_refuses_unreachable_target_naming_interval(magnet) -> None:
    spec = magnet.stream_spec()
    h = HISTORIES["after-max"].numpy()
    with pytest.raises(UnreachableTargetError, match=r"reachable .*: \[") as err:
        plan_setpoint(spec, h, 10.0 * float(magnet.output_scale))
    lo, hi = err.value.reachable
    with torch.no_grad():
        ends = magnet.predict(torch.tensor([0.0, 10.0], dtype=F64), history=h)
    assert lo == pytest.approx(float(ends[0]), abs=1e-12)
    assert hi == pytest.approx(float(ends[1]), abs=1e-12)


def test_plan_setpoint_overshoots_where_jumps_are_wide() -> None:
    # hysteresis 30 % of the linear term on a 6-cell mesh: a row of hysterons
    # switching outweighs the linear term across a cell, so many targets sit
    # in a jump of the one-step and cycle responses
    magnet = synthetic_magnet(i_max=10.0, n=6, hysteresis_fraction=0.3)
    spec = magnet.stream_spec()
    h = torch.tensor([0.0, 8.0, 2.0, 6.0], dtype=F64)
    span = float(magnet.output_scale)
    with torch.no_grad():
        lo, hi = magnet.predict(torch.tensor([0.0, 10.0], dtype=F64), history=h)
    kinds: dict[str, int] = {}
    for t in torch.linspace(float(lo), float(hi), 60, dtype=F64)[1:-1].tolist():
        plan = plan_setpoint(spec, h.numpy(), t)
        if abs(plan.error) > 1e-9 * span:
            continue  # inside a jump of every approach tried
        kinds[plan.kind] = kinds.get(plan.kind, 0) + 1
        with torch.no_grad():
            seq = torch.tensor(plan.sequence, dtype=F64)
            y = magnet.predict(seq, history=h)[-1]
        assert abs(float(y) - t) <= 1e-9 * span
        if plan.kind == "overshoot":
            (turn,) = plan.cycle
            assert (plan.input < turn) == (plan.approach == "from above")
    assert kinds.get("overshoot", 0) >= 3 and kinds.get("cycle", 0) >= 3
    assert sum(kinds.values()) >= 50
