"""Ensemble members trained on different processes (``split="members"``)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
import torch.distributed as tdist
from _gloo import spawn_gloo

from diffaccel.data import write_quad_scan
from diffaccel.data.quad_scan import read_quad_scan
from diffaccel.reconstruction import ReconstructionConfig, reconstruct
from diffaccel.reconstruction.rank_members import (
    MEMBER_SEED_STRIDE,
    gather_members,
    member_checkpoint,
    member_seed,
)

CFG = {"n_particles": 1024, "steps": 12, "snapshots": 2}


def _flat(members: list[dict]) -> list[torch.Tensor]:
    return [torch.cat([v.reshape(-1).double() for v in m.values()]) for m in members]


def _worker(rank: int, world: int, folder: str, resume: bool = False) -> None:
    torch.set_num_threads(1)
    tdist.init_process_group(
        "gloo", init_method=f"file://{folder}/rendezvous", rank=rank, world_size=world
    )
    try:
        ds = read_quad_scan(Path(folder) / "scan.h5")
        r = reconstruct(
            ds,
            ReconstructionConfig(**CFG),
            checkpoint=Path(folder) / "ck.pt",
            resume=resume,
            distributed=True,
            split="members",
        )
        torch.save(
            {
                "members": _flat(r.snapshots),
                "processes": r.info["member_processes"],
                "seed": r.config.seed,
            },
            Path(folder) / f"rank{rank}{'-resumed' if resume else ''}.pt",
        )
    finally:
        tdist.destroy_process_group()


def test_two_processes_train_their_own_members_and_share_all(
    small_scan, tmp_path: Path
) -> None:
    write_quad_scan(small_scan, tmp_path / "scan.h5")
    spawn_gloo(_worker, (2, str(tmp_path)), tmp_path)
    ranks = [torch.load(tmp_path / f"rank{r}.pt") for r in (0, 1)]
    # each process checkpointed its own run
    assert (tmp_path / "ck.pt").is_file() and (tmp_path / "ck.rank1.pt").is_file()
    # every process holds the same ensemble: both processes' members, in order
    assert len(ranks[0]["members"]) == 2 * CFG["snapshots"]
    for a, b in zip(ranks[0]["members"], ranks[1]["members"], strict=True):
        assert torch.equal(a, b)
    assert ranks[0]["processes"] == ranks[1]["processes"] == 2
    assert ranks[0]["seed"] == ranks[1]["seed"] == 0  # the config as given
    # process r's members are a one-process run with seed + 7919 r, and the
    # two runs differ (independent members, not copies)
    ds = read_quad_scan(tmp_path / "scan.h5")
    before = torch.get_num_threads()
    torch.set_num_threads(1)  # as in the workers: the same arithmetic
    try:
        singles = [
            reconstruct(ds, ReconstructionConfig(**CFG, seed=MEMBER_SEED_STRIDE * r))
            for r in (0, 1)
        ]
    finally:
        torch.set_num_threads(before)
    want = _flat(singles[0].snapshots) + _flat(singles[1].snapshots)
    for got, ref in zip(ranks[0]["members"], want, strict=True):
        assert torch.allclose(got, ref, rtol=1e-6, atol=1e-7)
    assert not torch.allclose(want[0], want[CFG["snapshots"]], rtol=1e-2)
    # --resume: each process finds its own checkpoint (process 1's was written
    # with seed 7919) and gives back the same members
    spawn_gloo(_worker, (2, str(tmp_path), True), tmp_path)
    resumed = torch.load(tmp_path / "rank1-resumed.pt")
    for a, b in zip(resumed["members"], ranks[1]["members"], strict=True):
        assert torch.equal(a, b)


def test_member_seed_and_checkpoint_names() -> None:
    cfg = ReconstructionConfig(seed=5)
    assert member_seed(cfg, 0) == cfg
    assert member_seed(cfg, 3).seed == 5 + 3 * MEMBER_SEED_STRIDE
    assert member_checkpoint(None, 2) is None
    assert member_checkpoint("a/b.pt", 0) == Path("a/b.pt")
    assert member_checkpoint("a/b.pt", 2) == Path("a/b.rank2.pt")


@pytest.fixture()
def one_process_group(tmp_path: Path):
    tdist.init_process_group(
        "gloo", init_method=f"file://{tmp_path}/rendezvous", rank=0, world_size=1
    )
    yield
    tdist.destroy_process_group()


def test_gather_members_keeps_keys_shapes_and_dtypes(one_process_group) -> None:
    members = [
        {
            "w": torch.randn(3, 4),
            "b": torch.randn(4, dtype=torch.float64),
            "n": torch.tensor([7]),
        }
        for _ in range(2)
    ]
    out = gather_members(members)
    assert len(out) == 2
    for got, want in zip(out, members, strict=True):
        assert list(got) == list(want)
        for k in want:
            assert got[k].dtype == want[k].dtype and torch.equal(got[k], want[k])


def test_gather_members_refuses_no_members(one_process_group) -> None:
    with pytest.raises(ValueError, match="no ensemble members"):
        gather_members([])


def test_reconstruct_refuses_unknown_split(small_scan) -> None:
    with pytest.raises(ValueError, match="split must be 'particles' or 'members'"):
        reconstruct(small_scan, ReconstructionConfig(**CFG), split="ranks")  # type: ignore[arg-type]
