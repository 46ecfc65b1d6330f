"""Particles split across two gloo processes give the single-process reconstruction."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
import torch.distributed as tdist
from _gloo import spawn_gloo

from diffaccel.data import read_scans, write_quad_scan, write_scans
from diffaccel.data.quad_scan import read_quad_scan
from diffaccel.reconstruction import ReconstructionConfig, pipeline, reconstruct

CFG = {"n_particles": 1024, "steps": 12, "snapshots": 2}


def _worker(rank: int, world: int, folder: str, dims: int) -> None:
    torch.set_num_threads(1)
    tdist.init_process_group(
        "gloo", init_method=f"file://{folder}/rendezvous", rank=rank, world_size=world
    )
    try:
        ds = read_quad_scan(Path(folder) / "scan.h5")
        cfg = ReconstructionConfig(dims=dims, **CFG)
        r = reconstruct(ds, cfg, distributed=True, report_every=1)
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
    spawn_gloo(_worker, (2, str(tmp_path), dims), tmp_path)
    ranks = [torch.load(tmp_path / f"rank{r}.pt") for r in (0, 1)]
    # every process computes the whole-beam loss; gloo may sum the all-reduced
    # float32 images in another order on each rank, so allow rounding (1 ulp
    # of float32 ~ 6e-8 relative) but nothing more
    assert ranks[0]["loss"] == pytest.approx(ranks[1]["loss"], rel=1e-6)
    single = reconstruct(
        read_quad_scan(tmp_path / "scan.h5"),
        ReconstructionConfig(dims=dims, **CFG),
        report_every=1,
    )
    # the same particles (two blocks of one Sobol sample), so step 0 agrees to
    # float32 rounding of the summed images and float64 moments...
    assert ranks[0]["loss"][0] == pytest.approx(single.history["loss"][0], rel=1e-5)
    # ...and training drifts only by rounding over 12 steps
    got = torch.tensor(ranks[0]["rms"][-1])[:dims]
    want = torch.tensor(single.history["rms"][-1])[:dims]
    assert torch.allclose(got, want, rtol=0.02)


# AWA 6D (cavity and dipole): two directions unseen, the prior term active
CFG_AWA = {"n_particles": 1024, "steps": 6, "snapshots": 2}


def _awa_worker(rank: int, world: int, folder: str) -> None:
    torch.set_num_threads(1)
    tdist.init_process_group(
        "gloo", init_method=f"file://{folder}/rendezvous", rank=rank, world_size=world
    )
    calls: list[bool] = []
    train = pipeline.train_generator

    def recording(*args, **kwargs):  # which steps split their particles
        calls.append(bool(kwargs.get("distributed", False)))
        return train(*args, **kwargs)

    pipeline.train_generator = recording
    try:
        cfg = ReconstructionConfig(dims=6, **CFG_AWA)
        r = reconstruct(
            read_scans(Path(folder) / "awa.h5"),
            cfg,
            distributed=True,
            uncertainty=False,
        )
        torch.save(
            {"calls": calls, "cov": torch.cov(r.sample(20_000, seed=1).T)},
            Path(folder) / f"rank{rank}.pt",
        )
    finally:
        pipeline.train_generator = train
        tdist.destroy_process_group()


@pytest.mark.slow  # two spawned interpreters tracking 6D
def test_two_gloo_processes_train_6d_with_the_prior_term(
    small_awa6d, tmp_path: Path
) -> None:
    """6D training with the prior term on the unseen directions splits its
    particles across the processes (one training call, nothing after it) and
    gives the single-process members to rounding."""
    write_scans(small_awa6d, tmp_path / "awa.h5")
    spawn_gloo(_awa_worker, (2, str(tmp_path)), tmp_path)
    ranks = [torch.load(tmp_path / f"rank{r}.pt") for r in (0, 1)]
    single = reconstruct(
        small_awa6d, ReconstructionConfig(dims=6, **CFG_AWA), uncertainty=False
    )
    assert ranks[0]["calls"] == ranks[1]["calls"] == [True]
    want = torch.cov(single.sample(20_000, seed=1).T)
    for got in (ranks[0]["cov"], ranks[1]["cov"]):
        # the same particles in two blocks: float32 rounding of the
        # all-reduced images, moments and gradients over 6 steps
        scale = want.diagonal().sqrt()
        diff = (got - want) / (scale[:, None] * scale[None, :])
        assert float(diff.abs().max()) < 1e-4
