"""The training step captured as a CUDA graph (reconstruction.graphed_step).

On the CPU the captured step's arithmetic is checked by replaying its body
eagerly (a stand-in for the graph); on a CUDA device the real graph is compared
with eager steps.
"""

from __future__ import annotations

import logging
import math

import pytest
import torch

from diffaccel.dynamics import images
from diffaccel.dynamics.elements import _kernels
from diffaccel.reconstruction import ReconstructionConfig, graphed_step, reconstruct
from diffaccel.reconstruction import training as training_module
from diffaccel.reconstruction.config import PENALTY_START
from diffaccel.reconstruction.graphed_step import (
    BC2_SQRT,
    GRAPH_WARMUP_STEPS,
    LAM,
    STEP_SIZE,
    step_factors,
)
from diffaccel.reconstruction.hold import MomentHold
from diffaccel.reconstruction.losses import (
    StepSchedule,
    cyclic_cosine_lr,
    penalty_schedule,
)
from diffaccel.reconstruction.optimiser import FlatAdam

FAST = {"n_particles": 1024, "steps": 24, "snapshots": 3}
#: Runtime choices of these runs: checkpoints every 5 steps.
RUN = {"checkpoint_every": 5}


def test_factored_adam_step_equals_adam_step() -> None:
    g = torch.Generator().manual_seed(1)
    start = torch.randn(500, generator=g)
    plain, factored = start.clone(), start.clone()
    a, b = FlatAdam(plain), FlatAdam(factored)
    lrs = [cyclic_cosine_lr(s, 8, 1e-2, 1e-4) for s in range(40)]
    table = step_factors(lrs, [0.0] * 40, 1, a.betas, torch.device("cpu"))
    for i, lr in enumerate(lrs):
        grad = torch.randn(500, generator=g)
        a.step(grad, lr)
        row = table[i]
        b.step_factored(grad, row[STEP_SIZE], row[BC2_SQRT])
    # same arithmetic, the factors rounded through float64 device scalars
    torch.testing.assert_close(factored, plain, rtol=1e-5, atol=1e-7)
    assert not torch.allclose(plain, start, atol=1e-3)  # it moved
    torch.testing.assert_close(b.exp_avg_sq, a.exp_avg_sq, rtol=0, atol=0)


def test_step_factors_columns() -> None:
    t = step_factors([1e-2, 5e-3], [10.0, 20.0], 3, (0.9, 0.999), torch.device("cpu"))
    assert t.shape == (2, 3) and t.dtype == torch.float64
    assert t[:, LAM].tolist() == [10.0, 20.0]
    assert t[0, STEP_SIZE].item() == pytest.approx(-1e-2 / (1 - 0.9**3))
    assert t[1, STEP_SIZE].item() == pytest.approx(-5e-3 / (1 - 0.9**4))
    assert t[1, BC2_SQRT].item() == pytest.approx(math.sqrt(1 - 0.999**4))


class _EagerReplay:
    """Stands in for GraphedStep on the CPU: runs the captured body each call."""

    made: list[_EagerReplay] = []  # noqa: RUF012

    def __init__(self, body, table, generator) -> None:
        self.body, self.table, self.calls = body, table, []
        _EagerReplay.made.append(self)

    def __call__(self, i: int):
        self.calls.append(i)
        return tuple(self.body(self.table[i].clone()))


@pytest.fixture
def eager_graph(monkeypatch):
    _EagerReplay.made = []
    monkeypatch.setattr(graphed_step, "graph_capable", lambda device: True)
    monkeypatch.setattr(graphed_step, "GraphedStep", _EagerReplay)
    return _EagerReplay


@pytest.mark.parametrize("smoothing", [0.0, "auto"], ids=["pixelwise", "smoothed"])
def test_captured_step_body_trains_like_eager_steps(
    small_scan, eager_graph, smoothing
) -> None:
    # moment weight 1: the body is the same for any weight, but with the 4D
    # default 3 this 24-step run's loss spikes to ~640 at step 9 and the
    # following Adam step amplifies the body's ~5e-6 rounding to ~2e-4
    # (chaotically, as in the 6D test below), which is not what this test is about
    fast = {**FAST, "loss_smoothing": smoothing, "moment_weight": 1.0}
    cfg = ReconstructionConfig(**fast)
    ref = reconstruct(small_scan, ReconstructionConfig(**fast), cuda_graph=False)
    got = reconstruct(small_scan, cfg, uncertainty=False)
    (replay,) = eager_graph.made
    # the body replaces every step after the eager warm-up, each with its row
    n = FAST["steps"] - GRAPH_WARMUP_STEPS
    assert replay.calls == list(range(n)) and replay.table.shape == (n, 3)
    cyc = cfg.cycle_length
    s = GRAPH_WARMUP_STEPS + 5
    assert replay.table[5, LAM].item() == penalty_schedule(
        s, cyc, PENALTY_START, cfg.penalty_end
    )
    assert got.history["lr"] == ref.history["lr"]
    assert got.history["penalty"] == ref.history["penalty"]
    # the same steps up to the rounding of the factors (float32 parameters)
    assert got.history["loss"] == pytest.approx(ref.history["loss"], rel=1e-4)
    assert got.history["snapshot_steps"] == ref.history["snapshot_steps"]
    # the smoothed images' blur matrices sum in another order inside the body:
    # the first captured step's loss differs by ~5e-6 (float32 rounding), and
    # 19 Adam steps carry that to ~1e-5 in a few small weights
    atol = 1e-5 if smoothing == 0.0 else 3e-5
    for sa, sb in zip(got.snapshots, ref.snapshots, strict=True):
        for k in sa:
            torch.testing.assert_close(sa[k], sb[k], rtol=1e-4, atol=atol)


@pytest.mark.parametrize("unseen_weight", [0.0, None], ids=["no-prior", "default"])
def test_captured_6d_step_body_trains_like_eager_steps(
    small_awa6d, eager_graph, monkeypatch, request, unseen_weight
) -> None:
    # the 6D body as it would be captured (GRAPH_DIMS admitting 6), replayed
    # eagerly on the CPU: the same training up to the factors' rounding, also
    # with the default prior term on the unseen directions (the body reads the
    # hold's directions and prior point, which training refreshes in place
    # between replays). One
    # thread: with two, the sums of the staged tracking change order between
    # runs and the two trainings drift apart by up to 1e-3 (chaotically, from
    # 1.6e-5 at step 5 on one CPU), which is not what this test is about
    monkeypatch.setattr(graphed_step, "GRAPH_DIMS", (4, 6))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    request.addfinalizer(lambda: torch.set_num_threads(threads))
    cfg = {**FAST, "dims": 6, "unseen_weight": unseen_weight}
    ref = reconstruct(small_awa6d, ReconstructionConfig(**cfg), cuda_graph=False)
    got = reconstruct(small_awa6d, ReconstructionConfig(**cfg), uncertainty=False)
    (replay,) = eager_graph.made
    assert len(replay.calls) == FAST["steps"] - GRAPH_WARMUP_STEPS
    # The captured Adam step rounds its factors differently (it divides, then
    # multiplies, where the eager step fuses), and Adam's normalised steps let
    # a parameter whose gradient is near 0 (the quadratic term's) carry that
    # rounding into the beam: on this seed the loss differs by at most 1.4e-6
    # for 11 steps, then by up to 1.0e-4 (the staged 6D tracking sums the
    # same gradients in another order); 2e-6
    # on seeds 1, 2. A step with a wrong factor (another step's learning rate
    # or penalty) differs by more than 1e-3 from its first replay (step 3).
    loss_got = torch.tensor(got.history["loss"], dtype=torch.float64)
    loss_ref = torch.tensor(ref.history["loss"], dtype=torch.float64)
    drift = (loss_got - loss_ref).abs() / loss_ref.abs()
    assert drift[:11].max() <= 1e-5, drift
    assert drift.max() <= 3e-4, drift
    # the beams' rms sizes (one offset differed by 1.3e-5)
    torch.testing.assert_close(
        torch.tensor(got.history["rms"]),
        torch.tensor(ref.history["rms"]),
        rtol=3e-4,
        atol=0,
    )


def test_hold_refreshes_in_place_and_counts_layout_changes() -> None:
    hold = MomentHold(1.0, torch.ones(6, dtype=torch.float64), 100)
    q = torch.randn(2, 6, 6, dtype=torch.float64)
    hold.set(q, torch.eye(6))
    layout, ptr = hold.layout, hold.q.data_ptr()
    hold.set(2 * q, 3 * torch.eye(6))
    assert (hold.layout, hold.q.data_ptr()) == (layout, ptr)  # read in place
    torch.testing.assert_close(hold.q, 2 * q)
    torch.testing.assert_close(hold.b, 6 * q.diagonal(dim1=1, dim2=2).sum(-1))
    hold.set(q[:1], torch.eye(6))  # one direction fewer
    assert hold.layout == layout + 1


def test_replays_stop_where_the_holds_layout_changes(eager_graph) -> None:
    flat = torch.zeros(3, requires_grad=True)
    hold = MomentHold(1.0, torch.ones(6, dtype=torch.float64), 100)
    hold.set(torch.zeros(1, 6, 6), torch.eye(6))
    moments = torch.eye(7, dtype=torch.float64)

    def gradient(lam, rng):
        x = torch.randn(3, generator=rng)
        return x, x.sum(), x.sum(), moments + 0 * x.sum(), moments.clone()

    schedule = StepSchedule(10, 1e-2, 1e-4, 10.0, 1e4)
    steps = graphed_step.TrainingSteps(
        gradient,
        FlatAdam(flat),
        schedule,
        torch.Generator().manual_seed(0),
        0,
        10,
        4,
        torch.device("cpu"),
        capture=True,
        hold=hold,
    )
    slot = (torch.zeros(()), torch.zeros(()), torch.zeros(7, 7, dtype=torch.float64))
    held = [steps(s, schedule.lr(s), schedule.penalty(s), slot) for s in range(6)]
    (replay,) = eager_graph.made
    assert replay.calls == [0, 1, 2]  # steps 3, 4, 5 replayed
    assert all(h is not None for h in held)  # replays return what the hold reads
    hold.set(torch.zeros(2, 6, 6), torch.eye(6))  # another number of directions
    for s in range(6, 10):
        steps(s, schedule.lr(s), schedule.penalty(s), slot)
    assert replay.calls == [0, 1, 2]  # eager from then on


class _Stop(Exception):
    pass


def test_resumed_run_captures_again_and_continues_the_run(
    small_scan, eager_graph, tmp_path
) -> None:
    # a run stopped after its checkpoint at step 10 and resumed: eager warm-up
    # steps 10-12, then a new capture whose table starts at step 13 with
    # Adam's count going on from the checkpoint
    cfg = ReconstructionConfig(**FAST)
    run = {**RUN, "report_every": 5, "uncertainty": False}
    ref = reconstruct(small_scan, cfg, **run)
    ck = tmp_path / "ck.pt"

    def stop(info) -> None:
        if info.step == 10:
            raise _Stop

    with pytest.raises(_Stop):
        reconstruct(small_scan, cfg, checkpoint=ck, callback=stop, **run)
    got = reconstruct(small_scan, cfg, checkpoint=ck, resume=True, **run)
    first, _, resumed = (
        eager_graph.made
    )  # the reference run's, the stopped, the resumed
    assert resumed.table.shape[0] == FAST["steps"] - 10 - GRAPH_WARMUP_STEPS
    torch.testing.assert_close(resumed.table, first.table[10:], rtol=1e-12, atol=0)
    assert got.history["loss"] == pytest.approx(ref.history["loss"], rel=1e-4)


def test_no_capture_when_disabled_or_too_short(small_scan, eager_graph) -> None:
    reconstruct(small_scan, ReconstructionConfig(**FAST), cuda_graph=False)
    short = {**FAST, "steps": GRAPH_WARMUP_STEPS, "snapshots": 1}
    reconstruct(small_scan, ReconstructionConfig(**short), uncertainty=False)
    assert eager_graph.made == []


def test_failed_capture_goes_on_eagerly(small_scan, monkeypatch, caplog) -> None:
    def refuse(body, table, generator):
        raise RuntimeError("operation not permitted when stream is capturing")

    monkeypatch.setattr(graphed_step, "graph_capable", lambda device: True)
    monkeypatch.setattr(graphed_step, "GraphedStep", refuse)
    ref = reconstruct(small_scan, ReconstructionConfig(**FAST), cuda_graph=False)
    with caplog.at_level(logging.WARNING, logger="diffaccel.reconstruction"):
        got = reconstruct(small_scan, ReconstructionConfig(**FAST))
    assert "could not capture the training step as a CUDA graph" in caplog.text
    for sa, sb in zip(got.snapshots, ref.snapshots, strict=True):
        for k in sa:
            assert torch.equal(sa[k], sb[k]), k


@pytest.fixture
def captured(monkeypatch) -> list:
    """The real GraphedSteps that a test's runs make."""
    made = []
    real = graphed_step.GraphedStep

    def spy(*args):
        made.append(real(*args))
        return made[-1]

    monkeypatch.setattr(graphed_step, "GraphedStep", spy)
    return made


def _cuda_runs(scan, cfg: dict):
    """The same training on CUDA with eager steps and with the CUDA graph."""
    ref = reconstruct(
        scan,
        ReconstructionConfig(**cfg),
        device="cuda",
        uncertainty=False,
        cuda_graph=False,
    )
    got = reconstruct(
        scan, ReconstructionConfig(**cfg), device="cuda", uncertainty=False
    )
    return ref, got


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_graph_trains_like_eager_cuda_steps(small_scan, captured) -> None:
    ref, got = _cuda_runs(small_scan, FAST)
    assert len(captured) == 1  # the graphed run captured its step once
    # replays draw the same base samples as eager steps (the generator is
    # registered with the graph), so the runs agree up to rounding
    assert got.history["loss"] == pytest.approx(ref.history["loss"], rel=1e-3)
    torch.testing.assert_close(
        torch.tensor(got.history["rms"][-1]),
        torch.tensor(ref.history["rms"][-1]),
        rtol=1e-3,
        atol=0,
    )


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_failed_capture_goes_on_eagerly(small_scan, monkeypatch, caplog) -> None:
    real = graphed_step.GraphedStep

    def with_host_read(body, table, generator):
        def body_reading_host(factors):
            float(factors[0])  # a host read: CUDA refuses it during capture
            return body(factors)

        return real(body_reading_host, table, generator)

    ref = reconstruct(
        small_scan,
        ReconstructionConfig(**FAST),
        cuda_graph=False,
        device="cuda",
        uncertainty=False,
    )
    monkeypatch.setattr(graphed_step, "GraphedStep", with_host_read)
    with caplog.at_level(logging.WARNING, logger="diffaccel.reconstruction"):
        got = reconstruct(
            small_scan, ReconstructionConfig(**FAST), device="cuda", uncertainty=False
        )
    assert "could not capture the training step as a CUDA graph" in caplog.text
    # the random generator goes on from its state before the capture: the
    # eager steps draw what the eager run drew (equal up to the order of
    # CUDA's atomic image sums: 2e-5 measured on an H200; other draws, like
    # another seed, differ by about 1e-2)
    assert got.history["loss"] == pytest.approx(ref.history["loss"], rel=1e-4)


def _step_events(scan, steps: int) -> dict[str, int]:
    cfg = ReconstructionConfig(
        dims=6, n_particles=512, steps=steps, snapshots=1, unseen_weight=0.0
    )
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as p:
        reconstruct(scan, cfg, uncertainty=False)
    names = [e.name for e in p.events()]
    watched = ("aten::_local_scalar_dense", "aten::lift_fresh")
    return {k: names.count(k) for k in watched}


def test_6d_step_reads_nothing_back_on_a_gpu_path(small_awa6d, monkeypatch) -> None:
    # the CPU run made to take the GPU's paths: full-screen images, no cheap
    # host reads, finite checks off for the generated beam. A 6D step then
    # neither reads the device (22 reads per step before) nor copies a value
    # from the host (7), so nothing in it blocks a stream or a CUDA graph
    monkeypatch.setattr(images, "_full_screen_path", lambda x: True)
    monkeypatch.setattr(_kernels, "cheap_reads", lambda t: False)
    monkeypatch.setattr(training_module, "_host_reads_cheap", lambda device: False)
    short, long = _step_events(small_awa6d, 10), _step_events(small_awa6d, 20)
    assert {k: long[k] - short[k] for k in short} == {
        "aten::_local_scalar_dense": 0,
        "aten::lift_fresh": 0,
    }


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("unseen_weight", [0.0, None], ids=["no-prior", "default"])
def test_cuda_graph_6d_steps(
    small_awa6d, captured, monkeypatch, caplog, unseen_weight
) -> None:
    # whether 6D steps capture and train like eager ones, with and without the
    # prior term on the unseen directions: the check to pass before
    # GRAPH_DIMS admits 6 (it fails where the capture does)
    monkeypatch.setattr(graphed_step, "GRAPH_DIMS", (4, 6))
    cfg = {**FAST, "dims": 6, "unseen_weight": unseen_weight}
    with caplog.at_level(logging.WARNING, logger="diffaccel.reconstruction"):
        ref, got = _cuda_runs(small_awa6d, cfg)
    assert "could not capture" not in caplog.text
    assert len(captured) == 1
    assert got.history["loss"] == pytest.approx(ref.history["loss"], rel=1e-3)
