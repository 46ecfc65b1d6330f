"""Ensemble members trained on different processes of a ``torch.distributed`` group.

With ``reconstruct(..., distributed=True, split="members")`` each process trains
its own, independent snapshot ensemble on the whole beam (process ``r`` with seed
``config.seed + MEMBER_SEED_STRIDE * r``, its own checkpoint) and the members of
all processes are then gathered into one ensemble, in process order, on every
process. Process 0 trains exactly the single-process run of ``config``, so one
process gives the plain result; ``P`` processes give ``P`` times the members in
the time of one run.

Example:
    >>> member_seed(ReconstructionConfig(seed=3), rank=2).seed
    15841
    >>> member_checkpoint("run/checkpoint.pt", rank=1).name
    'checkpoint.rank1.pt'
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from pathlib import Path

import torch
import torch.distributed as tdist

from diffaccel.reconstruction.training import ReconstructionConfig

#: Process ``r`` trains with seed ``config.seed + MEMBER_SEED_STRIDE * r``.
MEMBER_SEED_STRIDE = 7919


def member_seed(config: ReconstructionConfig, rank: int) -> ReconstructionConfig:
    """The settings process ``rank`` trains its members with (its own seed)."""
    return dataclasses.replace(config, seed=config.seed + MEMBER_SEED_STRIDE * rank)


def member_checkpoint(checkpoint: str | os.PathLike | None, rank: int) -> Path | None:
    """Process ``rank``'s checkpoint file: ``checkpoint`` itself on process 0,
    ``<stem>.rank<r><suffix>`` beside it on the others (``None`` stays ``None``)."""
    if checkpoint is None:
        return None
    path = Path(checkpoint)
    if rank == 0:
        return path
    return path.with_name(f"{path.stem}.rank{rank}{path.suffix}")


def gather_members(snapshots: Sequence[dict]) -> list[dict]:
    """Every process's members, in process order, on every process.

    Each process holds the same number of generator state dicts of the same
    architecture (same config but the seed); they travel as one flat float64
    tensor per process (``all_gather`` of tensors: no pickling) and come back
    with the keys, shapes and dtypes of this process's members, on the CPU.

    Raises:
        ValueError: if the processes hold different numbers of members or
            differently shaped ones (named with the counts).
    """
    if not snapshots:
        raise ValueError("gather_members: this process has no ensemble members.")
    world = tdist.get_world_size()
    template = snapshots[0]
    keys = list(template)
    sizes = [template[k].numel() for k in keys]
    flat = torch.cat(
        [m[k].detach().reshape(-1).double() for m in snapshots for k in keys]
    )
    device = _collective_device()
    counts = [torch.zeros(1, dtype=torch.int64, device=device) for _ in range(world)]
    tdist.all_gather(counts, torch.tensor([flat.numel()], device=device))
    if len({int(c.item()) for c in counts}) != 1:
        raise ValueError(
            "ensemble members differ between processes (values per process: "
            f"{[int(c.item()) for c in counts]}); every process must train the "
            "same settings."
        )
    parts = [torch.empty_like(flat, device=device) for _ in range(world)]
    tdist.all_gather(parts, flat.to(device))
    return [
        {
            k: v.view(template[k].shape).to(template[k].dtype)
            for k, v in zip(keys, row.split(sizes), strict=True)
        }
        for part in parts
        for row in part.cpu().view(len(snapshots), -1)
    ]


def _collective_device() -> torch.device:
    """Where the default group's collectives run: the current GPU for NCCL."""
    if tdist.get_backend() == "nccl":
        return torch.device("cuda", torch.cuda.current_device())
    return torch.device("cpu")
