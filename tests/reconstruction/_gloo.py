"""Two-process gloo runs for the distributed tests."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import torch.multiprocessing as mp


def spawn_gloo(fn: Callable, args: tuple, folder: str | Path, nprocs: int = 2) -> None:
    """``mp.spawn(fn, args, nprocs)``, once more where gloo could not connect
    its processes.

    On a loaded machine gloo's TCP connections between the processes can be
    refused or time out while the group forms (``connectFullMesh``), before any
    work is done: a failure of the machine, not of the code under test. The
    retry starts from a fresh rendezvous file (``folder/rendezvous``, the
    workers' ``file://`` init method); any other failure is raised.
    """
    for attempt in (0, 1):
        try:
            mp.spawn(fn, args=args, nprocs=nprocs, join=True)
            return
        except mp.ProcessRaisedException as err:
            if attempt or "connectFullMesh" not in str(err):
                raise
            (Path(folder) / "rendezvous").unlink(missing_ok=True)
