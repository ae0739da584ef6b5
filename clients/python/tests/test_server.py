"""The client against a running server: the real `mpiflow serve` and the Python stand-in.

Sizes are kept small (a crop, a few samples) so the whole run stays well under 3 minutes on two
cores with the real server (~6 full samples/s there).
"""
from __future__ import annotations

import signal
import threading
import time

import grpc
import numpy as np
import pytest

import mpiflow
from mpiflow import pb


def dataset(server, **kw):
    kw.setdefault("crop", server.crop)
    kw.setdefault("prefetch", 2)
    kw.setdefault("timeout", 120)
    return mpiflow.MPIFlowDataset(server.address, **kw)


def test_health_and_info(server, client):
    assert client.health(server.address) == "SERVING"
    assert client.health(server.address, service="") == "SERVING"
    info = client.info()
    assert info.datasets, info
    assert any(d.is_default for d in info.datasets)
    assert info.limits.max_message_bytes > 0
    if server.kind == "real":
        assert info.simd in ("sse2", "avx2", "avx512"), info.simd


def test_shapes_and_dtypes(server, client):
    s = client.get_sample(0)
    h, w = s.height, s.width
    assert (h, w) == (480, 640) if server.kind == "real" else (48, 64)
    assert s["image1"].shape == (h, w, 3) and s["image1"].dtype == np.uint8
    assert s["image2"].shape == (h, w, 3) and s["image2"].dtype == np.uint8
    assert s["flow"].shape == (h, w, 2) and s["flow"].dtype == np.float32
    assert s["valid"].shape == (h, w) and s["valid"].dtype == np.uint8
    assert set(s.keys()) == {"image1", "image2", "flow", "valid"}
    assert np.isfinite(s["flow"]).all()
    assert s.fingerprint != 0 and s.dataset

    cw, ch = server.crop
    fields = ["image1", "image2", "flow", "valid", "occlusion", "mask1", "mask2", "motions"]
    d = next(iter(dataset(server, count=1, fields=fields, flow_dtype="f16", rank=0, world_size=1)))
    assert d["img1"].shape == (3, ch, cw) and d["img1"].dtype == np.float32
    assert 0 <= d["img1"].min() and d["img1"].max() <= 255
    assert d["img2"].shape == (3, ch, cw) and d["flow"].shape == (2, ch, cw)
    assert d["flow"].dtype == np.float32 and d["valid"].dtype == np.float32
    assert set(np.unique(d["valid"])) <= {0.0, 1.0}
    assert d["valid"].shape == d["occlusion"].shape == d["mask1"].shape == (ch, cw)
    assert d["mask2"].dtype == np.uint8 and d["occlusion"].dtype == np.float32
    assert d["index"] == 0 and d["next_index"] == 1
    assert d["camera"]["rotation"].shape == (3, 3)
    assert np.allclose(d["camera"]["rotation"] @ d["camera"]["rotation"].T, np.eye(3), atol=1e-6)
    assert d["intrinsics"].shape == (4,)
    assert d["objects"]["label"].shape == (8,)


def test_depth_fields(server, client):
    s = client.get_sample(2, crop=server.crop, fields=["depth1", "depth2"])
    cw, ch = server.crop
    assert s["depth1"].shape == s["depth2"].shape == (ch, cw)
    assert s["depth1"].dtype == np.float32 and np.isfinite(s["depth1"]).all()
    assert np.isfinite(s["depth2"]).all() and (s["depth2"] >= 0).all() and (s["depth1"] > 0).all()


def test_holes_field(server, client):
    # holes: u8 0/1, the pixels image2 got from 2-D inpainting; nothing rendered there, so the
    # merged depth is 0 at every hole
    s = client.get_sample(2, crop=server.crop, fields=["holes", "depth2"])
    cw, ch = server.crop
    assert s["holes"].shape == (ch, cw) and s["holes"].dtype == np.uint8
    assert set(np.unique(s["holes"])) <= {0, 1}
    assert (s["depth2"][s["holes"] == 1] == 0).all()
    d = mpiflow.to_raft_dict(s)
    assert d["holes"].dtype == np.float32 and d["holes"].shape == (ch, cw)


def test_stream_equals_get_sample(server, client):
    kw = dict(seed=7, crop=server.crop, fields=["image1", "image2", "flow", "valid", "occlusion"])
    got = list(client.stream(rank=1, world_size=2, start_index=5, count=3, **kw))
    assert [s.index for s in got] == [6, 8, 10]
    for s in got:
        ref = client.get_sample(s.index, **kw)
        assert ref.fingerprint == s.fingerprint and ref.seed == 7
        assert set(ref.keys()) == set(s.keys())
        for name in s.keys():
            assert s[name].dtype == ref[name].dtype
            np.testing.assert_array_equal(s[name], ref[name], err_msg=f"{name} of {s.index}")


def test_lz4_on_and_off_are_equal(server, client):
    kw = dict(seed=3, crop=server.crop, fields=["image1", "image2", "flow", "valid", "occlusion", "mask1"])
    raw = client.get_sample(4, raw=True, lz4=True, **kw)
    assert all(t.compression == pb.COMPRESSION_LZ4 for t in raw.tensors)
    a = mpiflow.decode_sample(raw)
    b = client.get_sample(4, lz4=False, **kw)
    for name in b.keys():
        np.testing.assert_array_equal(a[name], b[name])
    plain = list(client.stream(count=2, start_index=10, **kw))
    packed = list(client.stream(count=2, start_index=10, lz4=True, **kw))
    assert [s.index for s in packed] == [10, 11]
    for p, q in zip(plain, packed):
        for name in p.keys():
            np.testing.assert_array_equal(p[name], q[name])


def test_f16_flow(server, client):
    a = client.get_sample(1, crop=server.crop, fields=["flow"], flow_dtype="f16")
    b = client.get_sample(1, crop=server.crop, fields=["flow"])
    assert a["flow"].dtype == np.float16
    np.testing.assert_allclose(a["flow"].astype(np.float32), b["flow"], rtol=1e-3, atol=1e-2)


def test_bad_requests_fail_without_retry(server, client):
    t0 = time.monotonic()
    with pytest.raises(grpc.RpcError) as e:
        client.get_sample(0, dataset="no-such-dataset")
    assert e.value.code() == grpc.StatusCode.NOT_FOUND
    with pytest.raises(mpiflow.MpiFlowError, match="FAILED_PRECONDITION"):
        list(client.stream(count=1, fingerprint=0x1111))
    assert time.monotonic() - t0 < 30


def test_coverage_2_ranks_x_3_workers(server):
    n = 12
    seen = {}
    for rank in range(2):
        for worker in range(3):
            ds = dataset(server, count=n, rank=rank, world_size=2, worker_id=worker, num_workers=3,
                         fields=["flow"])
            seen[(rank, worker)] = [d["index"] for d in ds]
    everything = [i for v in seen.values() for i in v]
    assert sorted(everything) == list(range(n)), seen
    assert len(everything) == len(set(everything))
    for (rank, worker), idx in seen.items():
        c = rank * 3 + worker
        assert idx == list(range(c, n, 6))


def test_resume_after_interrupted_iteration(server):
    n = 12
    kw = dict(count=n, start_index=100, fields=["flow"], seed=5)
    # Three consumers, each interrupted after a different number of samples.
    got = []
    states = []
    for w, stop_after in zip(range(3), (1, 2, 0)):
        ds = dataset(server, worker_id=w, num_workers=3, rank=0, world_size=1, **kw)
        it = iter(ds)
        for _ in range(stop_after):
            got.append(next(it)["index"])
        it.close()  # interrupted: the prefetcher had more in hand, which must not count
        states.append(ds.state_dict())
    state = mpiflow.MPIFlowDataset.merge_states(states)
    rest = []
    for w in range(3):
        ds = dataset(server, worker_id=w, num_workers=3, rank=0, world_size=1, **kw)
        ds.load_state_dict(state)
        rest += [d["index"] for d in ds]
    assert len(got) == 3
    assert sorted(got + rest) == list(range(100, 100 + n))
    assert not set(got) & set(rest)


def test_resume_single_stream_state(server):
    ds = dataset(server, count=6, fields=["flow"], rank=0, world_size=1, seed=9)
    first = []
    for d in ds:
        first.append(d["index"])
        if len(first) == 4:
            break
    st = ds.state_dict()
    assert st["cursors"] == {0: 4}
    ds2 = dataset(server, count=6, fields=["flow"], rank=0, world_size=1, seed=9)
    ds2.load_state_dict(st)
    assert [d["index"] for d in ds2] == [4, 5]


def _take_then(stream_iter, n_before, action, n_total):
    got = []
    for s in stream_iter:
        got.append(s)
        if len(got) == n_before:
            action()
        if len(got) == n_total:
            break
    return got


def test_failover_when_a_server_is_killed(server, spawn):
    a, b = spawn(), spawn()
    n = 16
    c = mpiflow.Client([a.address, b.address], timeout=60)
    st = c.stream(count=n, crop=server.crop, fields=["flow"], retry_timeout=60)
    assert st.address == a.address
    got = _take_then(st, 4, a.kill, n)  # SIGKILL mid-stream
    assert [s.index for s in got] == list(range(n))
    assert st.failovers >= 1 and st.address == b.address
    c.close()


def test_failover_in_the_dataset_and_back_to_a_restarted_replica(server, spawn):
    a, b = spawn(), spawn()
    n = 18
    ds = mpiflow.MPIFlowDataset([a.address, b.address], count=n, crop=server.crop, fields=["flow"],
                                rank=0, world_size=1, prefetch=2, timeout=60, retry_timeout=120)
    got = []
    for d in ds:
        got.append(d["index"])
        if len(got) == 3:
            a.kill()
        if len(got) == 6:
            a.start()  # same port
        if len(got) == 9:
            b.kill()  # only the restarted replica is left
    assert got == list(range(n))


def test_drain_on_sigterm_resumes_elsewhere(server, spawn):
    a, b = spawn(), spawn()
    n = 12
    c = mpiflow.Client([a.address, b.address], timeout=60)
    st = c.stream(count=n, crop=server.crop, fields=["flow"], retry_timeout=60)
    got = _take_then(st, 3, lambda: threading.Thread(target=a.kill, args=(signal.SIGTERM,)).start(), n)
    assert [s.index for s in got] == list(range(n))
    c.close()


def test_single_replica_restart(server, spawn):
    a = spawn()
    c = mpiflow.Client(a.address, timeout=60)
    st = c.stream(count=8, start_index=20, crop=server.crop, fields=["flow"], retry_timeout=120)
    got = _take_then(st, 2, a.restart, 8)
    assert [s.index for s in got] == list(range(20, 28))
    c.close()


def test_pull_numpy_example_runs(server, tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[3] / "examples" / "pull_numpy.py"
    r = subprocess.run(
        [sys.executable, str(script), "--addr", server.address, "--count", "2", "--out", str(tmp_path)],
        capture_output=True, text=True, timeout=120,
    )
    assert r.returncode == 0, r.stderr
    names = sorted(p.name for p in tmp_path.iterdir())
    assert "00000000_flow.npy" in names and "preview.png" in names, names
    flow = np.load(tmp_path / "00000000_flow.npy")
    assert flow.dtype == np.float32 and flow.ndim == 3 and flow.shape[2] == 2
