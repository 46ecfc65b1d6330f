"""Where a reconstruction runs: device, memory, the processes of a distributed run."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, ExitStack, contextmanager
from typing import Any, TypeVar

import torch
import torch.distributed as tdist

from diffaccel.reconstruction.training import ReconstructionConfig

_E = TypeVar("_E", bound=BaseException)

__all__ = [
    "init_distributed",
    "memory_shortfall",
    "resolve_device",
    "shared_refusal",
]


def resolve_device(device: str) -> torch.device:
    """``device`` (``"cpu"``, ``"cuda:1"``, ``"mps"``...) as a torch device that exists.

    Raises:
        ValueError: one line naming the device and why it cannot be used (not
            a device, CUDA or MPS not available, an index this machine lacks,
            an unsupported type).

    Example:
        >>> resolve_device("cpu:0").type
        'cpu'
    """
    try:
        dev = torch.device(device)
    except (RuntimeError, ValueError) as err:
        raise ValueError(
            f"{device!r} is not a device (cpu, cuda, cuda:1, mps...)"
        ) from err
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(
                f"{device}: CUDA is not available on this machine (torch "
                f"{torch.__version__}); use --device cpu"
            )
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(
                f"{device}: this machine has {torch.cuda.device_count()} CUDA device(s)"
            )
    elif dev.type == "mps" and not torch.backends.mps.is_available():
        raise ValueError(f"{device}: MPS is not available on this machine")
    elif dev.type in ("cpu", "mps") and dev.index not in (None, 0):
        # torch accepts "cpu:1" and ignores the index: refuse what does not exist
        raise ValueError(
            f"{device}: there is one {dev.type} device; use --device {dev.type}"
        )
    elif dev.type not in ("cpu", "cuda", "mps"):
        raise ValueError(f"{device}: unsupported device type {dev.type!r}")
    return dev


def memory_shortfall(config: ReconstructionConfig, n_images: int) -> str | None:
    """Why a run of ``config`` on ``n_images`` images cannot fit in this machine's RAM.

    Compares :meth:`ReconstructionConfig.memory_bytes` with the physical memory
    (POSIX ``sysconf``); None where it fits or the memory is unknown.
    """
    try:
        total = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return None
    need = config.memory_bytes(n_images)
    if total > 0 and need > total:
        return (
            f"{config.n_particles} particles need about {need / 2**30:.3g} GiB "
            f"of memory to train on {n_images} image(s); this machine has "
            f"{total / 2**30:.3g} GiB: use fewer particles"
        )
    return None


def init_distributed(device: str) -> str:
    """Join the process group that torchrun describes; returns this process's device.

    CUDA devices get one GPU per process (``cuda:LOCAL_RANK``, NCCL); others
    use gloo.

    Raises:
        ValueError: the launcher's environment variables are missing.
    """
    needed = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")
    missing = [v for v in needed if v not in os.environ]
    if missing:
        raise ValueError(
            f"--distributed needs a launcher such as torchrun (missing {missing}); "
            "e.g. torchrun --standalone --nproc-per-node 2 -m diffaccel reconstruct "
            "... --distributed"
        )
    if device.startswith("cuda"):
        device = f"cuda:{int(os.environ['LOCAL_RANK'])}"
        torch.cuda.set_device(device)
        backend = "nccl"
    else:
        backend = "gloo"
    tdist.init_process_group(backend)
    return device


@contextmanager
def shared_refusal(
    target: AbstractContextManager[Any],
    distributed: bool,
    *,
    refusal: type[_E],
    text: Callable[[_E], str],
    stopped: Callable[[str], BaseException],
) -> Iterator[Any]:
    """Enter ``target``; in a distributed run every process learns the outcome.

    Only process 0 opens the result folder. If it refuses (an error of type
    ``refusal``: the folder exists, is locked, read-only) the others must not
    wait for it in a collective forever: process 0 broadcasts ``text(error)``
    (or None) and raises its error; every other process leaves the process
    group and raises ``stopped(text)``. The broadcast also orders the staging
    folder's creation before the other processes read it.
    """
    error: _E | None = None
    with ExitStack() as stack:
        try:
            entered = stack.enter_context(target)
        except refusal as err:
            error = err
        if distributed:
            message = [None if error is None else text(error)]
            tdist.broadcast_object_list(message, src=0)
            if message[0] is not None and error is None:
                tdist.destroy_process_group()
                raise stopped(message[0])
        if error is not None:
            if distributed:
                tdist.destroy_process_group()
            raise error
        yield entered
