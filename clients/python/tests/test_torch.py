"""MPIFlowDataset under torch's DataLoader with worker processes (skipped where torch is absent)."""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
from torch.utils.data import DataLoader  # noqa: E402

import mpiflow  # noqa: E402


def make(server, **kw):
    kw.setdefault("crop", server.crop)
    kw.setdefault("fields", ["image1", "image2", "flow", "valid"])
    kw.setdefault("prefetch", 2)
    kw.setdefault("timeout", 120)
    return mpiflow.MPIFlowDataset(server.address, **kw)


def indices(batch):
    return batch["index"].tolist()


def test_collated_batches_are_raft_tensors(server):
    ds = make(server, count=4, rank=0, world_size=1)
    assert isinstance(ds, torch.utils.data.IterableDataset)
    batches = list(DataLoader(ds, batch_size=2, num_workers=0))
    cw, ch = server.crop
    b = batches[0]
    assert b["img1"].shape == (2, 3, ch, cw) and b["img1"].dtype == torch.float32
    assert b["flow"].shape == (2, 2, ch, cw) and b["valid"].shape == (2, ch, cw)
    assert sum((indices(b) for b in batches), []) == [0, 1, 2, 3]
    # Iterated in this process the dataset tracked itself.
    assert ds.state_dict()["cursors"] == {0: 4}


def test_dataloader_workers_cover_every_index_once(server):
    n = 12
    ds = make(server, count=n, fields=["flow"], rank=0, world_size=1)
    dl = DataLoader(ds, batch_size=2, num_workers=3)
    got = sum((indices(b) for b in dl), [])
    assert sorted(got) == list(range(n)) and len(got) == n


def test_two_ranks_times_three_workers(server):
    n = 12
    got = []
    for rank in range(2):
        ds = make(server, count=n, fields=["flow"], rank=rank, world_size=2)
        per_rank = sum((indices(b) for b in DataLoader(ds, batch_size=1, num_workers=3)), [])
        assert all((i % 6) // 3 == rank for i in per_rank)  # consumer c = rank * 3 + worker
        got += per_rank
    assert sorted(got) == list(range(n)) and len(got) == n


def test_resume_with_workers_via_track(server):
    n = 12
    ds = make(server, count=n, fields=["flow"], rank=0, world_size=1, seed=11)
    dl = DataLoader(ds, batch_size=2, num_workers=3)
    first = []
    it = iter(dl)
    for _ in range(2):
        b = next(it)
        ds.track(b)
        first += indices(b)
    del it  # interrupted: the workers had more in flight
    state = ds.state_dict()
    assert state["num_consumers"] == 3

    ds2 = make(server, count=n, fields=["flow"], rank=0, world_size=1, seed=11)
    ds2.load_state_dict(state)
    rest = sum((indices(b) for b in DataLoader(ds2, batch_size=2, num_workers=3)), [])
    assert sorted(first + rest) == list(range(n))
    assert len(first + rest) == n


def test_resume_with_other_worker_count_is_refused(server):
    ds = make(server, count=6, fields=["flow"], rank=0, world_size=1)
    ds.track({"index": torch.tensor([0, 3]), "next_index": torch.tensor([3, 6])})
    ds2 = make(server, count=6, fields=["flow"], rank=0, world_size=1)
    ds2.load_state_dict(ds.state_dict())
    with pytest.raises(Exception, match="same ranks"):
        list(DataLoader(ds2, batch_size=1, num_workers=2))


def test_map_dataset_under_shuffle_and_a_distributed_sampler(server):
    from torch.utils.data.distributed import DistributedSampler

    n = 12
    ds = mpiflow.MPIFlowMapDataset(server.address, n, crop=server.crop, fields=["flow"], timeout=120)
    assert isinstance(ds, torch.utils.data.Dataset) and len(ds) == n
    got = sum((indices(b) for b in DataLoader(ds, batch_size=3, shuffle=True, num_workers=2)), [])
    assert sorted(got) == list(range(n))
    got = []
    for rank in range(2):
        sampler = DistributedSampler(ds, num_replicas=2, rank=rank, shuffle=True, seed=3)
        want = list(sampler)
        per_rank = sum((indices(b) for b in DataLoader(ds, batch_size=2, sampler=sampler, num_workers=2)), [])
        assert per_rank == want  # each batch in the sampler's order
        got += per_rank
    assert sorted(got) == list(range(n))
