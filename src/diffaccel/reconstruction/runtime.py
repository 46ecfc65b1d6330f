"""Where a reconstruction runs: the device asked for, and whether it fits in memory."""

from __future__ import annotations

import os

import torch

from diffaccel.reconstruction.training import ReconstructionConfig

__all__ = ["memory_shortfall", "resolve_device"]


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
