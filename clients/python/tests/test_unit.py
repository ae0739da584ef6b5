"""Client pieces that need no server: decoding, health encoding, shard math, state, prefetch."""
from __future__ import annotations

import itertools
import os
import subprocess
import sys
import threading
import time

import grpc
import lz4.block
import numpy as np
import pytest

import mpiflow
from mpiflow import _health, pb
from mpiflow.client import parse_addresses
from mpiflow.spec import build_spec
from mpiflow.dataset import (
    _MPIFlowDatasetImpl,
    consumer_count,
    consumer_id,
    consumer_indices,
    resolve_consumer,
)
from mpiflow.decode import decode_tensor, field_name, parse_fields, to_raft_dict

from conftest import CLIENT_ROOT


def tensor(name, a, lz4_=False):
    raw = a.tobytes()
    t = pb.Tensor(name=name, shape=list(a.shape), raw_size=len(raw),
                  dtype={np.uint8: pb.DTYPE_U8, np.float16: pb.DTYPE_F16, np.float32: pb.DTYPE_F32}[a.dtype.type])
    if lz4_:
        t.compression = pb.COMPRESSION_LZ4
        t.data = lz4.block.compress(raw, store_size=True)
    else:
        t.compression = pb.COMPRESSION_NONE
        t.data = raw
    return t


# -- decoding -------------------------------------------------------------------------------------


@pytest.mark.parametrize("use_lz4", [False, True])
@pytest.mark.parametrize("dtype,shape", [(np.uint8, (5, 7, 3)), (np.float32, (5, 7, 2)),
                                         (np.float16, (5, 7, 2)), (np.uint8, (5, 7))])
def test_decode_tensor_roundtrip(use_lz4, dtype, shape):
    rng = np.random.default_rng(1)
    a = (rng.random(shape) * 200).astype(dtype)
    out = decode_tensor(tensor("x", a, use_lz4))
    assert out.dtype == np.dtype(dtype) and out.shape == shape
    np.testing.assert_array_equal(out, a)


def test_decode_tensor_is_a_view_of_the_bytes():
    a = np.arange(24, dtype=np.float32).reshape(2, 3, 4)
    t = tensor("flow", a)
    out = decode_tensor(t)
    assert not out.flags.owndata and not out.flags.writeable  # np.frombuffer over the bytes


def test_decode_tensor_little_endian_c_order():
    t = pb.Tensor(name="flow", shape=[1, 2, 2], dtype=pb.DTYPE_F32,
                  data=np.array([1, 2, 3, 4], dtype="<f4").tobytes())
    np.testing.assert_array_equal(decode_tensor(t), [[[1, 2], [3, 4]]])


def test_lz4_wire_format_is_size_prefixed_block():
    raw = bytes(range(256)) * 10
    comp = lz4.block.compress(raw, store_size=True)
    assert int.from_bytes(comp[:4], "little") == len(raw)
    assert lz4.block.decompress(comp) == raw


def test_decode_errors():
    a = np.zeros((2, 2, 3), np.uint8)
    t = tensor("image1", a)
    t.shape[:] = [2, 2, 4]
    with pytest.raises(mpiflow.DecodeError, match="expected"):
        decode_tensor(t)
    t = tensor("image1", a, True)
    t.data = b"\x10\x00\x00\x00garbage"
    with pytest.raises(mpiflow.DecodeError):
        decode_tensor(t)
    t = tensor("image1", a)
    t.dtype = pb.DTYPE_UNSPECIFIED
    with pytest.raises(mpiflow.DecodeError, match="dtype"):
        decode_tensor(t)
    t = tensor("image1", a)
    t.raw_size = 5
    with pytest.raises(mpiflow.DecodeError, match="raw_size"):
        decode_tensor(t)


def fake_sample(index=3, h=4, w=6, fields=("image1", "image2", "flow", "valid"), flow_dtype=np.float32):
    s = pb.Sample(index=index, dataset="d", fingerprint=9, seed=1, width=w, height=h)
    rng = np.random.default_rng(index)
    arrays = {
        "image1": rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
        "image2": rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
        "flow": (rng.standard_normal((h, w, 2)) * 5).astype(flow_dtype),
        "valid": (rng.random((h, w)) > 0.3).astype(np.uint8),
        "occlusion": (rng.random((h, w)) > 0.8).astype(np.uint8),
        "mask1": rng.integers(0, 3, (h, w), dtype=np.uint8),
        "mask2": rng.integers(0, 3, (h, w), dtype=np.uint8),
        "depth1": rng.random((h, w)).astype(np.float32),
        "depth2": rng.random((h, w)).astype(np.float32),
        "holes": (rng.random((h, w)) > 0.7).astype(np.uint8),
    }
    for f in fields:
        s.tensors.append(tensor(f, arrays[f]))
    s.camera.rotation.extend([1, 0, 0, 0, 1, 0, 0, 0, 1])
    s.camera.translation.extend([0.1, 0.2, -0.3])
    s.camera.axis_angle.extend([0.0, 0.01, 0.0])
    s.intrinsics.fx = 10
    o = s.objects.add(label=2, instance=5, score=0.5, area=0.1)
    o.motion.translation.extend([1, 2, 3])
    return s, {f: arrays[f] for f in fields}


def test_to_raft_dict_layout():
    s, arrays = fake_sample()
    d = to_raft_dict(mpiflow.decode_sample(s), next_index=7)
    assert d["img1"].shape == (3, 4, 6) and d["img1"].dtype == np.float32
    assert d["img2"].shape == (3, 4, 6) and d["flow"].shape == (2, 4, 6)
    assert d["valid"].shape == (4, 6) and d["valid"].dtype == np.float32
    np.testing.assert_array_equal(d["img1"], arrays["image1"].transpose(2, 0, 1).astype(np.float32))
    np.testing.assert_array_equal(d["flow"], arrays["flow"].transpose(2, 0, 1))
    np.testing.assert_array_equal(d["valid"], arrays["valid"].astype(np.float32))
    assert d["index"] == 3 and d["next_index"] == 7
    for k in ("img1", "img2", "flow", "valid"):
        assert d[k].flags.writeable and d[k].flags.c_contiguous
    assert 0 <= d["img1"].min() and d["img1"].max() <= 255


def test_to_raft_dict_optional_fields_and_motions():
    fields = ("image1", "flow", "occlusion", "mask1", "mask2", "depth1", "depth2", "holes")
    s, arrays = fake_sample(fields=fields, flow_dtype=np.float16)
    d = to_raft_dict(mpiflow.decode_sample(s), motions=True, pad_objects=4)
    assert d["flow"].dtype == np.float32
    # No valid requested: RAFT's own rule.
    np.testing.assert_array_equal(d["valid"], np.ones((4, 6), np.float32))
    assert d["occlusion"].dtype == np.float32 and d["mask1"].dtype == np.uint8
    assert d["depth1"].dtype == np.float32 and d["depth2"].shape == (4, 6)
    assert d["holes"].dtype == np.float32
    np.testing.assert_array_equal(d["holes"], arrays["holes"].astype(np.float32))
    assert d["camera"]["rotation"].shape == (3, 3)
    np.testing.assert_allclose(d["camera"]["translation"], [0.1, 0.2, -0.3])
    assert d["objects"]["label"].tolist() == [2, 0, 0, 0] and d["num_objects"] == 1
    np.testing.assert_allclose(d["objects"]["translation"][0], [1, 2, 3])
    assert d["intrinsics"][0] == 10
    with pytest.raises(ValueError, match="pad_objects"):
        to_raft_dict(mpiflow.decode_sample(s), motions=True, pad_objects=0)


def test_fields_and_addresses():
    assert parse_fields(None) == []
    assert parse_fields(["img1", "FIELD_FLOW", pb.FIELD_VALID, "flow"]) == [
        pb.FIELD_IMAGE1, pb.FIELD_FLOW, pb.FIELD_VALID]
    assert field_name("occ") == "occlusion"
    with pytest.raises(ValueError):
        parse_fields(["nope"])
    assert parse_addresses("a:1, grpc://b:2/,a:1") == ["a:1", "b:2"]
    with pytest.raises(ValueError):
        parse_addresses("")
    spec = build_spec(seed=3, crop=(160, 120), crop_mode="random", lz4=True, flow_dtype="f16",
                      max_objects=0, fields=["image1"])
    req = pb.StreamRequest(rank=1, world_size=2, spec=spec).spec
    assert req.seed == 3 and list(req.fields) == [pb.FIELD_IMAGE1]
    assert req.crop.width == 160 and req.crop.height == 120 and req.crop.mode == pb.CROP_MODE_RANDOM
    assert req.compression == pb.COMPRESSION_LZ4 and req.flow_dtype == pb.FLOW_DTYPE_F16
    assert req.HasField("max_objects") and req.max_objects == 0
    assert not req.HasField("motions_per_image")


# -- health ---------------------------------------------------------------------------------------


def test_health_wire_format():
    assert _health.encode_request("") == b""
    assert _health.encode_request("mpiflow.v1.MpiFlow") == b"\x0a\x12mpiflow.v1.MpiFlow"
    assert _health.decode_response(b"") == "UNKNOWN"
    assert _health.decode_response(b"\x08\x01") == "SERVING"
    assert _health.decode_response(b"\x08\x02") == "NOT_SERVING"
    assert _health.decode_response(b"\x12\x02hi\x08\x01") == "SERVING"
    long = "x" * 300
    enc = _health.encode_request(long)
    assert enc[1:3] == bytes([0xAC, 0x02]) and enc[3:] == long.encode()


def test_health_matches_grpc_health_checking_if_installed():
    h = pytest.importorskip("grpc_health.v1.health_pb2")
    assert _health.encode_request("svc") == h.HealthCheckRequest(service="svc").SerializeToString()
    raw = h.HealthCheckResponse(status=h.HealthCheckResponse.SERVING).SerializeToString()
    assert _health.decode_response(raw) == "SERVING"


# -- shard math -----------------------------------------------------------------------------------


def test_consumer_id():
    assert consumer_id(0, 1, 0, 1) == (0, 1)
    assert consumer_id(1, 2, 2, 3) == (5, 6)
    with pytest.raises(ValueError):
        consumer_id(2, 2, 0, 1)
    with pytest.raises(ValueError):
        consumer_id(0, 2, 3, 3)
    assert resolve_consumer(1, 2, 0, 3) == (3, 6)
    assert resolve_consumer() == (0, 1)
    with pytest.raises(ValueError):
        resolve_consumer(rank=1)


@pytest.mark.parametrize("start,count", [(0, 12), (5, 13), (7, 1), (3, 0), (0, 100)])
@pytest.mark.parametrize("world,workers", [(1, 1), (2, 3), (3, 1), (1, 4), (4, 4)])
def test_every_index_goes_to_exactly_one_consumer(start, count, world, workers):
    seen = []
    for r, w in itertools.product(range(world), range(workers)):
        c, num = consumer_id(r, world, w, workers)
        idx = list(consumer_indices(start, c, num, count))
        # The server's sequence for rank c of num from start: start + c + k * num.
        assert idx == [start + c + k * num for k in range(len(idx))]
        assert len(idx) == consumer_count(start + c, start + count, num)
        seen += idx
    assert sorted(seen) == list(range(start, start + count))
    assert len(seen) == len(set(seen))


def test_consumer_count_from_a_cursor():
    assert consumer_count(10, None, 3) is None
    assert consumer_count(10, 10, 3) == 0
    assert consumer_count(12, 10, 3) == 0
    assert consumer_count(4, 10, 3) == 2  # 4, 7
    assert consumer_count(4, 11, 3) == 3  # 4, 7, 10


# -- dataset state (no server: the streams are not opened) ---------------------------------------


def make_ds(**kw):
    return _MPIFlowDatasetImpl("127.0.0.1:1", **kw)


def test_state_track_and_resume_math():
    ds = make_ds(count=20, start_index=100)
    # 2 ranks x 3 workers: consumer c gets 100 + c + 6k; the loop saw some of them.
    batch = {"index": np.array([101, 107, 113]), "next_index": np.array([107, 113, 119])}
    ds.track(batch)
    ds.track({"index": 104, "next_index": 110})
    st = ds.state_dict()
    assert st["cursors"] == {1: 119, 4: 110} and st["num_consumers"] == 6
    ds2 = make_ds(count=20, start_index=100)
    ds2.load_state_dict(st)
    class _C:
        addresses = ["127.0.0.1:1"]
    s1 = ds2.make_stream(_C(), 1, 6)
    assert s1.next_index == 119 and s1.count == 1  # only 119 < 120 left
    assert ds2.make_stream(_C(), 4, 6).next_index == 110
    s0 = ds2.make_stream(_C(), 0, 6)
    assert s0.next_index == 100 and s0.count == 4  # untouched consumer: 100, 106, 112, 118
    with pytest.raises(ValueError, match="same ranks"):
        ds2.make_stream(_C(), 0, 4)
    with pytest.raises(ValueError, match="seed"):
        make_ds(count=20, start_index=100, seed=1).load_state_dict(st)
    with pytest.raises(ValueError):
        ds.track({"index": 105, "next_index": 108})  # another topology mixed in


def test_state_done_consumer_and_epochs():
    ds = make_ds(count=6)
    ds.track({"index": [4, 5], "next_index": [7, 8]})
    class _C:
        addresses = ["x:1"]
    assert ds.make_stream(_C(), 1, 3) is None  # 1, 4 done
    ds.set_epoch(2)
    s = ds.make_stream(_C(), 1, 3)
    assert s.next_index == 13 and s.count == 2  # epoch 2 covers 12..17: 13, 16
    with pytest.raises(ValueError):
        make_ds().set_epoch(1)


def test_merge_states():
    a = make_ds(count=12)
    b = make_ds(count=12)
    a.track({"index": [0, 1], "next_index": [4, 5]})
    b.track({"index": [6, 3], "next_index": [10, 7]})
    m = _MPIFlowDatasetImpl.merge_states([a.state_dict(), b.state_dict()])
    assert m["cursors"] == {0: 4, 1: 5, 2: 10, 3: 7}


# -- prefetch -------------------------------------------------------------------------------------


def test_prefetcher_order_and_bound():
    produced = []

    def gen():
        for i in range(50):
            produced.append(i)
            yield i

    pf = mpiflow.Prefetcher(gen(), maxsize=4)
    time.sleep(0.2)
    assert len(produced) <= 4 + 2  # the queue plus the item in hand
    assert list(pf) == list(range(50))


def test_prefetcher_forwards_errors():
    def gen():
        yield 1
        raise KeyError("boom")

    pf = mpiflow.Prefetcher(gen(), maxsize=2)
    assert next(pf) == 1
    with pytest.raises(KeyError):
        next(pf)


def test_prefetcher_close_stops_a_blocked_producer():
    unblock = threading.Event()

    def gen():
        i = 0
        while True:
            if unblock.wait(0.01):
                return
            yield i
            i += 1

    pf = mpiflow.Prefetcher(gen(), maxsize=2, on_close=unblock.set)
    assert next(pf) == 0
    t0 = time.monotonic()
    pf.close()
    assert not pf._thread.is_alive() and time.monotonic() - t0 < 2
    with pytest.raises(StopIteration):
        next(pf)


# -- packaging ------------------------------------------------------------------------------------


def _run_py(code, **env):
    e = dict(os.environ, PYTHONPATH=str(CLIENT_ROOT), **env)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=e, timeout=120)


def test_import_does_not_import_torch():
    r = _run_py("import sys, mpiflow; mpiflow.Client; mpiflow.FlowStream; print('torch' in sys.modules)")
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "False"


def test_dataset_without_torch_is_a_plain_iterable():
    r = _run_py(
        "import mpiflow, collections.abc as a; D = mpiflow.MPIFlowDataset; "
        "print(D.__mro__[1].__name__, len(D.__mro__), issubclass(D, a.Iterable))",
        MPIFLOW_NO_TORCH="1",
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["_MPIFlowDatasetImpl", "3", "True"]


def test_dataset_is_torch_iterable_dataset_when_torch_present():
    torch_data = pytest.importorskip("torch.utils.data")
    assert issubclass(mpiflow.MPIFlowDataset, torch_data.IterableDataset)
    import pickle

    ds = mpiflow.MPIFlowDataset("127.0.0.1:1", count=4)
    ds2 = pickle.loads(pickle.dumps(ds))
    assert type(ds2) is mpiflow.MPIFlowDataset and ds2.count == 4


def test_client_refuses_pickling():
    import pickle

    c = mpiflow.Client("127.0.0.1:1", wait=False)
    with pytest.raises(TypeError, match="pickled"):
        pickle.dumps(c)
    c.close()


def test_client_not_ready_times_out():
    port = __import__("conftest").free_port()
    c = mpiflow.Client(f"127.0.0.1:{port}", wait=False)
    t0 = time.monotonic()
    with pytest.raises(mpiflow.NotReadyError):
        c.wait_ready(1.0)
    assert time.monotonic() - t0 < 5
    c.close()


def test_motions_is_a_field_name_of_every_entry_point():
    from mpiflow.decode import parse_fields

    assert parse_fields(["motions"]) == []
    assert parse_fields(["img1", "Motions", "flow"]) == [pb.FIELD_IMAGE1, pb.FIELD_FLOW]
    spec = build_spec(fields=["flow", "motions"])
    assert list(spec.fields) == [pb.FIELD_FLOW]
    with pytest.raises(ValueError):
        parse_fields(["motion"])


class _Err(grpc.RpcError):
    """A gRPC error value as a call raises it (code, details and trailing metadata)."""

    def __init__(self, code, details, reason=None):
        self._code, self._details = code, details
        self._trailers = (("mpiflow-reason", reason),) if reason else ()

    def code(self):
        return self._code

    def details(self):
        return self._details

    def trailing_metadata(self):
        return self._trailers


def test_retries_are_decided_by_the_servers_reason_not_the_text():
    from mpiflow.errors import is_retryable

    code = grpc.StatusCode
    # the same words, another reason: the reason decides
    too_large = _Err(code.RESOURCE_EXHAUSTED, "too many GetSample/GetSamples calls", "sample-too-large")
    busy = _Err(code.RESOURCE_EXHAUSTED, "sample too large", "too-many-calls")
    assert not is_retryable(too_large)
    assert is_retryable(busy)
    assert not is_retryable(_Err(code.INVALID_ARGUMENT, "indices: [1] = 2^64 - 1", "invalid-argument"))
    assert not is_retryable(_Err(code.INTERNAL, "sample 3: failed", "sample-failed"))
    assert is_retryable(_Err(code.UNAVAILABLE, "the server is shutting down", "draining"))
    # no reason: the transport (a reset stream) or the client's own receive limit
    assert is_retryable(_Err(code.INTERNAL, "Received RST_STREAM"))
    assert is_retryable(_Err(code.UNAVAILABLE, "failed to connect"))
    assert not is_retryable(_Err(code.RESOURCE_EXHAUSTED, "Received message larger than max"))


def test_a_misspelt_sample_option_is_refused_by_name_before_any_call():
    # the sample options of get_sample, get_samples and stream are build_spec's, checked once
    c = mpiflow.Client("127.0.0.1:1", wait=False)
    for call in (lambda: c.get_sample(0, sed=3), lambda: c.get_samples([0, 1], sed=3), lambda: c.stream(sed=3)):
        with pytest.raises(TypeError, match="sed"):
            call()
    s = c.stream(seed=5, fields=["image1"], crop=(64, 48))
    assert s._spec.seed == 5 and s._spec.crop.width == 64
