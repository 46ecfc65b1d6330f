"""A set point as text and JSON."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from diffaccel.data import FormatError, OptionError, iter_magnet_csv
from diffaccel.hysteresis import (
    SetPoint,
    StreamSpec,
    UnreachableTargetError,
    field_for_k1,
)
from diffaccel.hysteresis.setpoint_report import (
    ACCEPT,
    check_limits,
    jump_text,
    plan_history_setpoint,
    setpoint_lines,
    setpoint_summary,
    unreachable_text,
)

NAMES = {"input_column": "I", "output_column": "G"}


def _plan(**kw) -> SetPoint:
    base = dict(
        target=1.0, input=2.5, approach="from below", cycle=(10.0, 0.0),
        kind="cycle", output=1.0, std=0.01, reachable=(-1.0, 2.0),
        limits=(0.0, 10.0), present_input=3.0, present_output=0.5, tolerance=1e-9,
    )  # fmt: skip
    base.update(kw)
    return SetPoint(**base)


def test_lines_name_the_cycle_the_input_and_the_inputs_to_apply() -> None:
    first, second = setpoint_lines(_plan(), **NAMES)
    assert first == (
        "first a degaussing cycle: I 10, then 0; then set I to 2.5 from below "
        "(present I 3, G 0.5): G 1 +- 0.01 (1 std) predicted there"
    )
    assert second == (
        "reachable G -1 .. 2 within I 0 .. 10; inputs to apply: 10, 0, 2.5"
    )
    over = setpoint_lines(
        _plan(kind="overshoot", cycle=(7.0,), std=math.nan), **NAMES, k1=4.0
    )[0]
    assert over.startswith("first I 7 (overshoot); then set I to 2.5")
    assert "): k1 4 1/m^2: G 1 (1 std) predicted there" in over  # no std
    direct = setpoint_lines(_plan(kind="direct", cycle=(), std=None), **NAMES)[0]
    assert direct.startswith("set I to 2.5 from below")


def test_summary_is_json_and_records_a_k1_target() -> None:
    plan = _plan(output=1.0 + 1e-7)
    s = setpoint_summary(
        plan, fit="fit", history="h.csv", target=1.0, output=1.0,
        output_scale=2.0, notes=["n"], **NAMES,
    )  # fmt: skip
    assert s["target_kind"] == "output" and "length" not in s
    assert s["sequence"] == [10.0, 0.0, 2.5] and s["notes"] == ["n"]
    assert s["error_fraction_of_range"] == pytest.approx(0.5e-7)
    k1 = setpoint_summary(
        plan, fit="fit", history="h.csv", target=3.0, output=1.0,
        output_scale=2.0, length=0.1, p0c=1e8, **NAMES,
    )  # fmt: skip
    assert (k1["target_kind"], k1["length"], k1["p0c"]) == ("k1", 0.1, 1e8)
    assert json.loads(json.dumps(k1, allow_nan=False)) == k1


def test_jump_text_only_beyond_the_accepted_error() -> None:
    scale = 2.0
    inside = _plan(output=1.0 + 0.5 * ACCEPT * scale)
    assert jump_text(inside, 1.0, scale, "I", "G") is None
    text = jump_text(_plan(output=1.1), 1.0, scale, "I", "G")
    assert text == (
        "G 1 lies in a jump of the fitted model (a row of hysterons switching) "
        "for every approach tried; nearest: I 2.5 gives 1.1."
    )


def test_unreachable_text_names_the_reachable_outputs_or_strengths() -> None:
    err = UnreachableTargetError("x", reachable=(-1.0, 2.0), limits=(0.0, 10.0))
    text = unreachable_text(err, target=5.0, output=5.0, **NAMES)
    assert text == (
        "G 5 cannot be reached: the fit reaches G -1 .. 2 within I 0 .. 10 "
        "after this history."
    )
    out = field_for_k1(20.0, 0.1, 1e8)
    text = unreachable_text(err, target=20.0, output=out, length=0.1, p0c=1e8, **NAMES)
    per = out / 20.0
    assert text.startswith(f"k1 20 1/m^2 (G {out:.6g}) cannot be reached")
    assert f"k1 {-1.0 / per:.6g} .. {2.0 / per:.6g} 1/m^2 (G -1 .. 2)" in text


#: one hysteron (up at 0.5, down at 0.25) plus a linear term, inputs in [0, 1]
SPEC = StreamSpec(
    (0.0, 1.0),
    np.array([0.5]),
    np.array([0.25]),
    np.array([1.0]),
    np.array([-1.0]),
    0.0,
    1.0,
    0.1,
    0.0,
    1.0,
)


def _history(tmp_path: Path, inputs: list[float]):
    path = tmp_path / "h.csv"
    path.write_text("I\n" + "".join(f"{x}\n" for x in inputs))
    return path, iter_magnet_csv(path, "I")[1]


def test_check_limits_refuses_limits_outside_the_input_range() -> None:
    check_limits(SPEC, None, "I")
    check_limits(SPEC, (0.5, 2.0), "I")
    with pytest.raises(OptionError, match=r"leave no I inside .* \[0, 1\]") as err:
        check_limits(SPEC, (1.0, 2.0), "I")
    assert err.value.option == "--limits"


def test_plan_history_setpoint_plans_after_the_history(tmp_path: Path) -> None:
    data, chunks = _history(tmp_path, [0.1, 0.9, 0.3])
    plan, notes = plan_history_setpoint(
        SPEC, data, chunks, **NAMES, target=0.5, output=0.5
    )
    assert abs(plan.output - 0.5) <= ACCEPT and notes == []
    data, chunks = _history(tmp_path, [0.1, 1e101])
    with pytest.raises(FormatError, match=r"^\S*h.csv: column 'I', data row 2"):
        plan_history_setpoint(SPEC, data, chunks, **NAMES, target=0.5, output=0.5)
    data, chunks = _history(tmp_path, [0.1])
    with pytest.raises(ValueError, match="G 9 cannot be reached"):
        plan_history_setpoint(SPEC, data, chunks, **NAMES, target=9.0, output=9.0)
