"""Fused Adam on one flat parameter vector (the training optimiser).

The generator's parameters live in one flat vector
(:class:`~diffaccel.reconstruction.generator.FlatGenerator`), so one Adam step
is a handful of whole-vector kernels; :meth:`FlatAdam.step_factored` takes the
step's factors as device scalars, the form a CUDA-graph step reads
(:mod:`~diffaccel.reconstruction.graphed_step`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


class FlatAdam:
    """Adam on one flat parameter vector, with ``torch.optim.Adam``'s arithmetic.

    The step count and learning rate live on the host, so a step is six
    whole-vector kernels and never reads the device (``torch.optim.Adam`` reads
    each parameter's step count back, one host synchronisation per parameter,
    unless ``capturable``, which CPUs do not support).

    Args:
        param: The flat parameter vector (updated in place).
        betas: Decay rates of the first and second moments.
        eps: Added to the root of the second moment.
    """

    def __init__(
        self,
        param: Tensor,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
    ) -> None:
        self.param = param
        self.betas = betas
        self.eps = eps
        self.steps = 0
        self.exp_avg = torch.zeros_like(param, memory_format=torch.preserve_format)
        self.exp_avg_sq = torch.zeros_like(param, memory_format=torch.preserve_format)
        # factors as 0-d tensors of the parameter's dtype: a Python float is
        # wrapped and cast at every call (one more ATen op each; same values,
        # as the kernels compute in that dtype)
        kw = {"dtype": param.dtype, "device": param.device}
        self._beta2 = torch.tensor(betas[1], **kw)
        self._eps = torch.tensor(eps, **kw)
        self._bc2_sqrt = torch.zeros((), **kw)

    @torch.no_grad()
    def step(self, grad: Tensor, lr: float) -> None:
        """One update with gradient ``grad`` at learning rate ``lr``."""
        self.steps += 1
        b1, b2 = self.betas
        bc1 = 1 - b1**self.steps
        bc2 = 1 - b2**self.steps
        self.exp_avg.lerp_(grad, 1 - b1)
        self.exp_avg_sq.mul_(self._beta2).addcmul_(grad, grad, value=1 - b2)
        denom = self.exp_avg_sq.sqrt().div_(self._bc2_sqrt.fill_(math.sqrt(bc2)))
        denom.add_(self._eps)
        self.param.addcdiv_(self.exp_avg, denom, value=-lr / bc1)

    @torch.no_grad()
    def step_factored(self, grad: Tensor, step_size: Tensor, bc2_sqrt: Tensor) -> None:
        """:meth:`step` with the step's factors as device scalars (CUDA graphs).

        ``step_size`` is ``-lr / (1 - beta1**t)``, ``bc2_sqrt`` is
        ``sqrt(1 - beta2**t)`` (:func:`~diffaccel.reconstruction.graphed_step.
        step_factors`); the caller counts :attr:`steps`.
        """
        b1, b2 = self.betas
        self.exp_avg.lerp_(grad, 1 - b1)
        self.exp_avg_sq.mul_(self._beta2).addcmul_(grad, grad, value=1 - b2)
        denom = self.exp_avg_sq.sqrt().div_(bc2_sqrt).add_(self._eps)
        self.param.addcmul_(self.exp_avg.div(denom), step_size)

    def state_dict(self) -> dict:
        """``torch.optim``-shaped state (one parameter), for checkpoints."""
        return {
            "state": {
                0: {
                    "step": torch.tensor(float(self.steps)),
                    "exp_avg": self.exp_avg.detach().to("cpu").clone(),
                    "exp_avg_sq": self.exp_avg_sq.detach().to("cpu").clone(),
                }
            },
            "param_groups": [{"betas": list(self.betas), "eps": self.eps}],
        }

    def load_state_dict(self, d: dict) -> None:
        """Inverse of :meth:`state_dict`."""
        s = d["state"][0]
        self.steps = int(s["step"])
        self.exp_avg.copy_(s["exp_avg"])
        self.exp_avg_sq.copy_(s["exp_avg_sq"])
