"""Particles split across two gloo processes give the single-process reconstruction."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
import torch.distributed as tdist
import torch.multiprocessing as mp

from diffaccel.data import write_quad_scan
from diffaccel.data.quad_scan import read_quad_scan
from diffaccel.reconstruction import ReconstructionConfig, reconstruct

CFG = {"n_particles": 1024, "steps": 12, "snapshots": 2, "report_every": 1}


def _worker(rank: int, world: int, folder: str, dims: int) -> None:
    torch.set_num_threads(1)
    tdist.init_process_group(
        "gloo", init_method=f"file://{folder}/rendezvous", rank=rank, world_size=world
    )
    try:
        ds = read_quad_scan(Path(folder) / "scan.h5")
        cfg = ReconstructionConfig(dims=dims, **CFG)
        r = reconstruct(ds, cfg, distributed=True)
        torch.save(
            {"loss": r.history["loss"], "rms": r.history["rms"]},
            Path(folder) / f"rank{rank}.pt",
        )
    finally:
        tdist.destroy_process_group()


@pytest.mark.parametrize(
    "dims",
    [4, pytest.param(6, marks=pytest.mark.slow)],  # two spawned interpreters each
    ids=["4d-linear-maps", "6d-tracking"],
)
def test_two_gloo_processes_equal_one(small_scan, tmp_path: Path, dims: int) -> None:
    write_quad_scan(small_scan, tmp_path / "scan.h5")
    mp.spawn(_worker, args=(2, str(tmp_path), dims), nprocs=2, join=True)
    ranks = [torch.load(tmp_path / f"rank{r}.pt") for r in (0, 1)]
    # every process computes the whole-beam loss; gloo may sum the all-reduced
    # float32 images in another order on each rank, so allow rounding (1 ulp
    # of float32 ~ 6e-8 relative) but nothing more
    assert ranks[0]["loss"] == pytest.approx(ranks[1]["loss"], rel=1e-6)
    single = reconstruct(
        read_quad_scan(tmp_path / "scan.h5"), ReconstructionConfig(dims=dims, **CFG)
    )
    # the same particles (two blocks of one Sobol sample), so step 0 agrees to
    # float32 rounding of the summed images and float64 moments...
    assert ranks[0]["loss"][0] == pytest.approx(single.history["loss"][0], rel=1e-5)
    # ...and training drifts only by rounding over 12 steps
    got = torch.tensor(ranks[0]["rms"][-1])[:dims]
    want = torch.tensor(single.history["rms"][-1])[:dims]
    assert torch.allclose(got, want, rtol=0.02)
