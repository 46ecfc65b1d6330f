"""A training step captured once as a CUDA graph and replayed every step.

On a GPU a default 4D training step is a few hundred small kernels; launched one
by one from Python the step takes several milliseconds however few particles it
tracks (the GPU computes for a fraction of that). Captured as a CUDA graph
(``torch.cuda.CUDAGraph``) the whole step, generator forward, tracking, images,
losses, the hand-written backward and the Adam update, is launched at once.

What changes from step to step (the learning rate, the image-penalty weight
and Adam's bias corrections) is precomputed for every remaining step into one
device table (:func:`step_factors`); before each replay one row is copied into
the tensor that the captured step reads. The random generator of the base
samples is registered with the graph, so each replay draws fresh samples.

:class:`TrainingSteps` runs the steps of one training run: a few eager steps
on a side stream, then the capture and its replays where the step can be
captured, eager steps otherwise.
"""

from __future__ import annotations

import logging
import math
import warnings
from collections.abc import Callable, Sequence
from contextlib import nullcontext

import torch
from torch import Tensor

from diffaccel.reconstruction.hold import MomentHold, held_moments
from diffaccel.reconstruction.losses import StepSchedule
from diffaccel.reconstruction.optimiser import FlatAdam

logger = logging.getLogger(__name__)

#: Columns of the per-step factor table.
LAM, STEP_SIZE, BC2_SQRT = 0, 1, 2

#: Eager steps (on a side stream) before the step is captured as a CUDA graph.
GRAPH_WARMUP_STEPS = 3
#: Generator dimensions whose training steps are captured (``cuda_graph``).
#: 6D steps, their prior term on the unseen directions included, read nothing
#: back from the device (the CPU tests replay the captured body), but they have
#: not been captured on a GPU yet (docs/gpu.md; ``test_cuda_graph_6d_steps``
#: checks it).
GRAPH_DIMS = (4,)

#: One step's loss gradient: called with the image-penalty weight (a float, or
#: the captured step's device scalar) and the random generator to draw the
#: particles from; returns the gradient of the flat parameter vector, the
#: image penalty, ``H - C``, the plain moments of the entropy and the moments
#: a hold reads (None without a hold).
Gradient = Callable[
    [float | Tensor, torch.Generator],
    tuple[Tensor, Tensor, Tensor, Tensor, Tensor | None],
]


def step_factors(
    lrs: Sequence[float],
    lams: Sequence[float],
    first_adam_step: int,
    betas: tuple[float, float],
    device: torch.device,
) -> Tensor:
    """Per-step factors of the captured step, one row per remaining step.

    Args:
        lrs: Learning rate of each remaining step.
        lams: Image-penalty weight of each remaining step.
        first_adam_step: Adam's step count at the first of them (1-based).
        betas: Adam's decay rates.
        device: Where the table lives.

    Returns:
        ``(S, 3)`` float64: the penalty weight, ``-lr / (1 - beta1**t)`` and
        ``sqrt(1 - beta2**t)`` (columns :data:`LAM`, :data:`STEP_SIZE`,
        :data:`BC2_SQRT`).
    """
    b1, b2 = betas
    rows = [
        (lam, -lr / (1 - b1**t), math.sqrt(1 - b2**t))
        for t, (lr, lam) in enumerate(zip(lrs, lams, strict=True), first_adam_step)
    ]
    return torch.tensor(rows, dtype=torch.float64).to(device)


class GraphedStep:
    """Capture ``body(factors)`` as a CUDA graph; each call replays it.

    ``body`` must be one training step with fixed shapes and no host reads,
    reading its per-step factors only from the ``(3,)`` tensor it is given; it
    returns the tensors the caller reads after each replay (they are the
    graph's static outputs, overwritten by every replay).

    Args:
        body: The step; called once, during capture (it is not executed then).
        table: Factors of every remaining step, from :func:`step_factors`.
        generator: CUDA random generator the step draws from (registered with
            the graph so that each replay advances it).

    Shapes:
        ``table (S, 3)``; ``graphed(i)`` replays with row ``i``.
    """

    def __init__(
        self,
        body: Callable[[Tensor], Sequence[Tensor]],
        table: Tensor,
        generator: torch.Generator,
    ) -> None:
        self.table = table
        self.factors = table[0].clone()
        self.graph = torch.cuda.CUDAGraph()
        self.graph.register_generator_state(generator)
        # on the table's GPU, which need not be the current one (cuda:1)
        with torch.cuda.device(table.device), torch.cuda.graph(self.graph):
            self.outputs = tuple(body(self.factors))

    def __call__(self, i: int) -> tuple[Tensor, ...]:
        """Run the step with row ``i`` of the table; the step's outputs."""
        with torch.cuda.device(self.table.device):
            self.factors.copy_(self.table[i])
            self.graph.replay()
        return self.outputs


def graph_capable(device: torch.device) -> bool:
    """Whether steps on ``device`` can be captured (CUDA devices)."""
    return device.type == "cuda"


def warm_stream(device: torch.device) -> torch.cuda.Stream | None:
    """A side stream for the eager steps before capture (CUDA's advice).

    None off CUDA devices (the eager steps then run where they always do).
    """
    if device.type != "cuda":
        return None
    stream = torch.cuda.Stream(device)
    stream.wait_stream(torch.cuda.current_stream(device))
    return stream


def join_stream(side: torch.cuda.Stream | None, device: torch.device) -> None:
    """Make ``device``'s current stream wait for the work queued on ``side``."""
    if side is not None:
        torch.cuda.current_stream(device).wait_stream(side)


class TrainingSteps:
    """The optimiser steps of one training run, eager or replayed as a CUDA graph.

    Where the step can be captured (``capture``, ``dims`` in
    :data:`GRAPH_DIMS`, a CUDA device and more than
    :data:`GRAPH_WARMUP_STEPS` steps to go), the first
    :data:`GRAPH_WARMUP_STEPS` steps run eagerly on a side stream (lazy
    initialisations happen there), then the step is captured
    (:class:`GraphedStep`, its factors from :func:`step_factors`) and replayed
    for every remaining step. Where the capture fails, the run goes on
    eagerly. Everywhere else every step runs eagerly: ``gradient``, the sum of
    the gradient over processes (``all_reduce``), then
    :meth:`FlatAdam.step`.

    Args:
        gradient: The step's loss gradient (:data:`Gradient`).
        opt: Adam of the flat parameter vector (its step count goes on from a
            resumed run's).
        schedule: Learning rate and penalty weight of every step.
        rng: Random generator the steps draw their particles from.
        start: First step to run (0-based; a resumed run's step).
        total: Steps of the whole run.
        dims: Generator dimensions (4 or 6).
        device: Device of the training.
        capture: Whether this run may capture its step at all.
        all_reduce: Sums a tensor over processes in place (distributed
            training), or None.
        hold: The quadratic hold of the loss, or None. A replay returns the
            moments it reads (float32-rounded, as an eager step's); where the
            number of held directions changes (:attr:`MomentHold.layout`) the
            captured step no longer fits and the run goes on eagerly.

    Attributes:
        rng: The random generator the steps draw from: after a failed capture
            a fresh one with the state from before it (a generator registered
            with a failed capture cannot draw outside it), after a change of
            the hold's layout a fresh one with its current state; a checkpoint
            stores its state.
    """

    def __init__(
        self,
        gradient: Gradient,
        opt: FlatAdam,
        schedule: StepSchedule,
        rng: torch.Generator,
        start: int,
        total: int,
        dims: int,
        device: torch.device,
        capture: bool,
        all_reduce: Callable[[Tensor], object] | None = None,
        hold: MomentHold | None = None,
    ) -> None:
        self.gradient, self.opt, self.schedule = gradient, opt, schedule
        self.hold = hold
        self.layout = None  # the hold's layout the captured step was made for
        self.rng, self.total, self.device = rng, total, device
        self.all_reduce = all_reduce
        self.use_graph = (
            capture
            and dims in GRAPH_DIMS
            and graph_capable(device)
            and total - start > GRAPH_WARMUP_STEPS
        )
        self.side = warm_stream(device) if self.use_graph else None
        self.graph_start = start + GRAPH_WARMUP_STEPS
        self.graphed: GraphedStep | None = None

    def __call__(
        self, step: int, lr: float, lam: float, slot: Sequence[Tensor]
    ) -> Tensor | None:
        """Run step ``step`` at learning rate ``lr`` and penalty weight ``lam``.

        Its image penalty, ``H - C`` and plain moments are copied into
        ``slot`` (device tensors ``()``, ``()``, ``(dims + 1, dims + 1)``);
        returns the moments a hold reads (None after a replay or without a
        hold).
        """
        if self.use_graph and self.graphed is None and step == self.graph_start:
            self.layout = None if self.hold is None else self.hold.layout
            self.graphed = self._capture(step)
            self.use_graph, self.side = self.graphed is not None, None
        if self.graphed is not None and self.hold is not None:
            if self.hold.layout != self.layout:  # other shapes: step eagerly
                self.graphed = None
                self.rng = _unregistered(self.rng, self.device)
        if self.graphed is not None:
            values = self.graphed(step - self.graph_start)
            self.opt.steps += 1  # the captured Adam step's count
            with torch.no_grad():
                for target, value in zip(slot, values, strict=True):
                    target.copy_(value)
            if self.hold is None:
                return None
            return held_moments(values[2])
        side = self.side
        with torch.cuda.stream(side) if side is not None else nullcontext():
            grad, dist, rel, moments, held = self.gradient(lam, self.rng)
            if self.all_reduce is not None:  # each process holds its share's
                self.all_reduce(grad)
            self.opt.step(grad, lr)
            with torch.no_grad():
                for target, value in zip(slot, (dist, rel, moments), strict=True):
                    target.copy_(value)
        join_stream(side, self.device)
        return held

    def _body(self, factors: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The step as captured: factors from the table, outputs to read."""
        grad, dist, rel, moments, _ = self.gradient(factors[LAM], self.rng)
        self.opt.step_factored(grad, factors[STEP_SIZE], factors[BC2_SQRT])
        return dist, rel, moments

    def _capture(self, start: int) -> GraphedStep | None:
        """Steps ``start`` to ``total - 1`` as a CUDA graph; None where the
        capture fails (:attr:`rng` then restarts from its state before it)."""
        join_stream(self.side, self.device)
        remaining = range(start, self.total)
        table = step_factors(
            [self.schedule.lr(s) for s in remaining],
            [self.schedule.penalty(s) for s in remaining],
            self.opt.steps + 1,
            self.opt.betas,
            self.device,
        )
        before = self.rng.get_state()
        try:
            with warnings.catch_warnings():
                # the generator's parameter vector was first used on the
                # warm-up stream; autograd notes the other stream of the
                # capture (harmless)
                warnings.filterwarnings(
                    "ignore", message="The AccumulateGrad node's stream does not match"
                )
                return GraphedStep(self._body, table, self.rng)
        except RuntimeError as err:  # e.g. an operation CUDA cannot capture
            logger.warning(
                "could not capture the training step as a CUDA graph (%s); "
                "training goes on step by step",
                str(err).splitlines()[0] if str(err) else type(err).__name__,
            )
            self.rng = _unregistered(self.rng, self.device, before)
            return None


def _unregistered(
    rng: torch.Generator, device: torch.device, state: Tensor | None = None
) -> torch.Generator:
    """A generator not registered with any CUDA graph, at ``state`` (default:
    ``rng``'s current state)."""
    fresh = torch.Generator(device=device)
    fresh.set_state(rng.get_state() if state is None else state)
    return fresh
