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
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

#: Columns of the per-step factor table.
LAM, STEP_SIZE, BC2_SQRT = 0, 1, 2


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
