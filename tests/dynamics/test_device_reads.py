"""Host reads (device synchronisations) of the dynamics' checks and branches.

On a GPU every value read back on the host stalls the stream and cannot be
captured in a CUDA graph. These tests count ``aten::_local_scalar_dense`` (the
op behind ``bool(tensor)`` and ``.item()``) on the CPU, with the CPU's
cheap-read shortcut switched off where the code keeps one.
"""

from __future__ import annotations

import math

import pytest
import torch

from diffaccel.dynamics import Beamline, cic_image, finite_checks
from diffaccel.dynamics._validate import as_p0c, check_particles
from diffaccel.dynamics.elements import _kernels


def _reads(fn) -> int:
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as p:
        fn()
    return sum(e.name == "aten::_local_scalar_dense" for e in p.events())


def test_p0c_number_is_checked_on_the_host() -> None:
    like = torch.zeros(3, dtype=torch.float32)
    out = {}
    assert _reads(lambda: out.update(t=as_p0c(43.36e6, like))) == 0
    assert out["t"].dtype == torch.float32 and out["t"].item() == pytest.approx(43.36e6)
    for bad in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="p0c"):
            as_p0c(bad, like)
    with pytest.raises(ValueError, match="p0c"):  # tensors: checked where they live
        as_p0c(torch.tensor(-1.0), like)


def test_finite_checks_can_be_turned_off_and_come_back() -> None:
    bad = torch.zeros(4, 6)
    bad[1, 2] = math.nan
    x, y = torch.tensor([0.0, math.inf]), torch.zeros(2)
    with finite_checks(False):
        check_particles(bad)  # not checked: the caller made these particles
        cic_image(x, y, (3, 3), 1.0)
        assert _reads(lambda: check_particles(bad)) == 0
    with pytest.raises(ValueError, match="NaN or infinite coordinate"):
        check_particles(bad)
    with pytest.raises(ValueError, match="NaN or infinite positions"):
        cic_image(x, y, (3, 3), 1.0)
    with pytest.raises(ValueError, match="shaped"):  # shape checks always run
        with finite_checks(False):
            check_particles(torch.zeros(4, 5))


def test_is_zero_remembers_its_answer_off_the_cpu(monkeypatch) -> None:
    monkeypatch.setattr(_kernels, "cheap_reads", lambda t: False)
    tilt = torch.zeros(())
    assert _reads(lambda: _kernels.is_zero(tilt)) == 1
    assert _reads(lambda: _kernels.is_zero(tilt)) == 0  # remembered
    assert _kernels.is_zero(tilt)
    tilt.add_(0.1)  # an in-place change: asked again
    assert not _kernels.is_zero(tilt)
    assert not _kernels.is_zero(torch.zeros((), requires_grad=True))
    with torch.inference_mode():  # inference tensors keep no version: no memo
        frozen = torch.zeros(())
    assert _kernels.is_zero(frozen) and _kernels.is_zero(frozen)
    # the memo is of that tensor object: a copy asks again, and a freed
    # tensor's entry goes
    assert _reads(lambda: _kernels.is_zero(tilt.clone())) == 1
    gone = torch.zeros(())
    assert _kernels.is_zero(gone)
    n = len(_kernels._ZERO_MEMO)
    del gone
    assert len(_kernels._ZERO_MEMO) == n - 1


def test_stacked_columns_backward_reads_nothing_off_the_cpu(monkeypatch) -> None:
    line = Beamline.from_spec(
        [
            {"type": "Quadrupole", "name": "Q", "length": 0.1, "k1": 3.0},
            {"type": "Drift", "name": "D", "length": 1.0},
        ]
    )
    p = (torch.randn(200, 6) * 1e-3).requires_grad_(True)
    out = line.track(p, 43.36e6)
    grad = torch.zeros_like(out)
    grad[:, 0] = 1.0  # only x differentiated: the other columns' grads are 0
    reads_cpu = _reads(lambda: out.backward(grad, retain_graph=True))
    monkeypatch.setattr(_kernels, "cheap_reads", lambda t: False)
    g_cpu = p.grad.clone()
    p.grad = None
    assert reads_cpu > 0 and _reads(lambda: out.backward(grad)) == 0
    torch.testing.assert_close(p.grad, g_cpu, rtol=0, atol=0)  # same gradient


def test_scan_settings_finite_check_follows_finite_checks() -> None:
    line = Beamline.from_spec(
        [{"type": "Quadrupole", "name": "Q", "length": 0.1, "k1": 0.0}]
    )
    p = torch.zeros(10, 6)
    bad = torch.tensor([[1.0], [math.nan]])
    with pytest.raises(ValueError, match="settings contain NaN"):
        line.track(p, 1e7, bad, ["Q.k1"])
    good = torch.tensor([[1.0], [2.0]])
    checked = _reads(lambda: line.track(p, 1e7, good, ["Q.k1"]))
    with finite_checks(False):
        unchecked = _reads(lambda: line.track(p, 1e7, good, ["Q.k1"]))
    # one read fewer for the particles, one for the settings
    assert checked - unchecked == 2
