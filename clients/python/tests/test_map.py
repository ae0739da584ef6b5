"""Random access against real servers: Client.get_samples (GetSamples) and MPIFlowMapDataset —
the same bytes as the stream, any order, a DistributedSampler-style partition over two replicas x
two workers, and failover when a replica is killed. Also the crop rule (refused, never shrunk),
one field-name table for every entry point, and a log without colour codes in a file."""
from __future__ import annotations

import multiprocessing
import os
import pickle
import random
import threading
from collections import Counter

import grpc
import numpy as np
import pytest

import mpiflow

FIELDS = ["image1", "image2", "flow", "valid", "occlusion", "motions"]


def small(kind):
    """Flags of small servers for the multi-replica tests (the rendered frame is the sample)."""
    return ["--size", "96x64", "--workers", "1"] if kind == "real" else []


def content(s):
    """A Sample message's bytes without its timings (measurements, not content)."""
    s = type(s).FromString(s.SerializeToString())
    s.ClearField("timings")
    return s.SerializeToString()


def same_item(a, b):
    assert set(a) == set(b)
    for k in a:
        if isinstance(a[k], dict):
            same_item(a[k], b[k])
        elif isinstance(a[k], np.ndarray):
            assert a[k].dtype == b[k].dtype and np.array_equal(a[k], b[k]), k
        else:
            assert a[k] == b[k], k


def test_get_samples_equals_the_stream_in_request_order(server, client):
    kw = dict(seed=3, crop=server.crop, crop_mode="random", fields=FIELDS)
    stream = {s.index: s for s in client.stream(start_index=4, count=3, raw=True, **kw)}
    got = client.get_samples([6, 4, 5, 4], raw=True, **kw)
    assert [s.index for s in got] == [6, 4, 5, 4]
    for s in got:
        assert content(s) == content(stream[s.index])
    one = client.get_sample(5, raw=True, **kw)
    assert content(one) == content(got[2])
    # "motions" is a name every entry point takes (it adds no tensor)
    assert set(mpiflow.decode_sample(one).keys()) == {"image1", "image2", "flow", "valid", "occlusion"}


def test_map_items_equal_stream_items_byte_for_byte(server):
    kw = dict(seed=5, crop=server.crop, fields=FIELDS, timeout=120)
    ds = mpiflow.MPIFlowMapDataset(server.address, 8, **kw)
    assert len(ds) == 8 and ds.crop_mode == "random"
    stream = {d["index"]: d for d in mpiflow.MPIFlowDataset(server.address, start_index=5, count=2, rank=0,
                                                            world_size=1, prefetch=0, **kw)}
    items = ds.__getitems__([6, 5])
    assert [d["index"] for d in items] == [6, 5]
    for d in items:
        stream[d["index"]].pop("next_index")
        same_item(d, stream[d["index"]])
    # the sequence protocol: negative positions, IndexError past the end (no call made)
    same_item(ds[-2], items[0])
    with pytest.raises(IndexError):
        ds[8]
    # a pickled copy (what a DataLoader worker gets) carries no channel and opens its own
    copy = pickle.loads(pickle.dumps(ds))
    assert copy._client is None
    same_item(copy[5], items[1])
    assert copy._client is not None and copy._client is not ds._client
    ds.close()
    copy.close()


def distributed_sampler(n, rank, world, seed, epoch):
    """torch's DistributedSampler(shuffle=True, drop_last=False) index list, without torch."""
    order = list(range(n))
    random.Random(seed + epoch).shuffle(order)
    total = -(-n // world) * world
    order += order[: total - n]
    return order[rank:total:world]


def test_a_distributed_partition_over_two_replicas_and_two_workers_covers_an_epoch_once(kind, spawn):
    a, b = spawn(extra=small(kind)), spawn(extra=small(kind))
    n, world, workers, batch = 16, 2, 2, 2
    base = mpiflow.MPIFlowMapDataset(f"{a.address},{b.address}", n, seed=9, fields=["flow"], timeout=120)
    got = []
    lock = threading.Lock()
    errors = []

    def worker(rank, w):
        # a DataLoader worker: its own copy of the dataset, batch k of its rank when k % workers == w
        ds = pickle.loads(pickle.dumps(base))
        ds.client()
        ds._prefer = ds.addresses[w % len(ds.addresses)]
        try:
            order = distributed_sampler(n, rank, world, seed=1, epoch=0)
            batches = [order[i:i + batch] for i in range(0, len(order), batch)]
            for k, bt in enumerate(batches):
                if k % workers == w:
                    items = ds.__getitems__(bt)
                    assert [d["index"] for d in items] == bt
                    with lock:
                        got.extend(d["index"] for d in items)
        except BaseException as e:  # reported below
            errors.append(e)
        finally:
            ds.close()

    threads = [threading.Thread(target=worker, args=(r, w)) for r in range(world) for w in range(workers)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors
    assert Counter(got) == Counter(range(n)), sorted(got)


def _fetch_in_a_process(ds, positions):
    """A worker process's share: the dataset arrives pickled, opens its own channel."""
    assert ds._client is None
    items = ds.__getitems__(positions)
    return os.getpid(), [(d["index"], d["flow"].tobytes()) for d in items]


def test_worker_processes_open_their_own_channels(server):
    ds = mpiflow.MPIFlowMapDataset(server.address, 8, seed=4, crop=server.crop, fields=["flow"], timeout=120)
    shares = [[5, 0, 3], [6, 1]]
    ctx = multiprocessing.get_context("spawn")
    with ctx.Pool(2) as pool:
        results = pool.starmap(_fetch_in_a_process, [(ds, p) for p in shares])
    assert all(pid != os.getpid() for pid, _ in results)
    got = dict(x for _, r in results for x in r)
    assert sorted(got) == [0, 1, 3, 5, 6]
    assert ds._client is None, "the parent opened no channel"
    for d in ds.__getitems__([6, 0]):
        assert got[d["index"]] == d["flow"].tobytes()
    ds.close()


def test_a_killed_replica_fails_over_to_the_next(kind, spawn):
    a, b = spawn(extra=small(kind)), spawn(extra=small(kind))
    ds = mpiflow.MPIFlowMapDataset([a.address, b.address], 10, seed=2, fields=["image1", "flow"],
                                   timeout=120, retry_timeout=120)
    first = ds.__getitems__([0, 1, 2])
    assert ds._prefer == a.address
    a.kill()
    again = ds.__getitems__([2, 1, 0, 3])
    assert [d["index"] for d in again] == [2, 1, 0, 3]
    for x, y in zip(again[:3], reversed(first)):
        same_item(x, y)
    # the same index from the surviving replica directly
    c = mpiflow.Client(b.address, timeout=60)
    try:
        ref = c.get_samples([3], seed=2, fields=["image1", "flow"], crop_mode="random")[0]
        np.testing.assert_array_equal(mpiflow.to_raft_dict(ref)["flow"], again[3]["flow"])
    finally:
        c.close()
        ds.close()


def test_a_crop_larger_than_the_frame_is_refused_not_shrunk(server, client):
    s = client.get_sample(0, fields=["flow"])
    w, h = s.width, s.height
    with pytest.raises(grpc.RpcError) as e:
        client.get_sample(0, crop=(w + 1, h), fields=["flow"])
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    msg = e.value.details()
    assert msg.startswith("crop") and f"{w + 1}x{h}" in msg and f"{w}x{h}" in msg, msg


def test_every_entry_point_takes_the_same_field_names(server, client):
    for fields in (["motions"], ["img1", "flow", "motions"], ["FIELD_FLOW", "occ"]):
        mpiflow.spec.build_spec(fields=fields)
    s = client.get_sample(1, crop=server.crop, fields=["flow", "motions"])
    assert set(s.keys()) == {"flow"}
    ss = client.get_samples([1], crop=server.crop, fields=["flow", "motions"])
    np.testing.assert_array_equal(ss[0]["flow"], s["flow"])


def test_the_text_log_in_a_file_has_no_colour_codes(server):
    if server.kind != "real":
        pytest.skip("the real server's log")
    text = open(server.log.name, errors="replace").read()
    assert "listening" in text and "\x1b[" not in text
