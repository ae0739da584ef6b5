#!/usr/bin/env python3
"""A stand-in mpiflow server in Python for the client's own tests (not the real thing).

It speaks the same API and command-line contract as `mpiflow serve` (prints
`mpiflow serving on HOST:PORT` once bound; grpc.health.v1 NOT_SERVING during `--warmup`, then
SERVING; SIGTERM drains: open streams end with UNAVAILABLE and the trailer
`mpiflow-next-index`), and makes cheap deterministic samples: every pixel of a sample is a
function of (seed, index, y, x), so the client's addressing, sharding, resume, failover,
decoding and lz4 paths are checked end to end without the Rust build.

    python tests/fake_server.py serve --addr 127.0.0.1:0 [--delay 0.01] [--warmup 0.5]
"""
from __future__ import annotations

import argparse
import signal
import sys
import threading
import time
from concurrent import futures
from pathlib import Path

import grpc
import lz4.block
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from mpiflow import _health  # noqa: E402
from mpiflow._proto import mpiflow_pb2 as pb  # noqa: E402
from mpiflow._proto import mpiflow_pb2_grpc as pb_grpc  # noqa: E402

WIDTH, HEIGHT = 64, 48
FINGERPRINT = 0x1234_5678_9ABC_DEF0
DATASET = "builtin"
DEFAULT_FIELDS = [pb.FIELD_IMAGE1, pb.FIELD_IMAGE2, pb.FIELD_FLOW, pb.FIELD_VALID]
NAMES = {
    pb.FIELD_IMAGE1: "image1",
    pb.FIELD_IMAGE2: "image2",
    pb.FIELD_FLOW: "flow",
    pb.FIELD_VALID: "valid",
    pb.FIELD_OCCLUSION: "occlusion",
    pb.FIELD_MASK1: "mask1",
    pb.FIELD_MASK2: "mask2",
    pb.FIELD_DEPTH1: "depth1",
    pb.FIELD_DEPTH2: "depth2",
    pb.FIELD_HOLES: "holes",
}


def make_arrays(seed: int, index: int, fields, flow_f16: bool, crop) -> dict:
    rng = np.random.default_rng([seed, index])
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH]
    out = {}
    base = (x * 3 + y * 5 + index * 7 + seed) % 256
    for f in fields:
        if f == pb.FIELD_IMAGE1:
            out["image1"] = np.stack([base, (base + 85) % 256, (base + 170) % 256], -1).astype(np.uint8)
        elif f == pb.FIELD_IMAGE2:
            out["image2"] = rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)
        elif f == pb.FIELD_FLOW:
            fl = np.stack([x * 0.25 + index, y * -0.5 + seed], -1).astype(np.float32)
            out["flow"] = fl.astype(np.float16) if flow_f16 else fl
        elif f in (pb.FIELD_VALID, pb.FIELD_OCCLUSION, pb.FIELD_MASK1, pb.FIELD_MASK2, pb.FIELD_HOLES):
            out[NAMES[f]] = ((x + y + index + f) % 3 == 0).astype(np.uint8)
        elif f in (pb.FIELD_DEPTH1, pb.FIELD_DEPTH2):
            out[NAMES[f]] = (1.0 + 0.01 * (x + y) + index).astype(np.float32)
    if crop is not None and (crop.width or crop.height):
        w, h = crop.width or WIDTH, crop.height or HEIGHT
        if w > WIDTH or h > HEIGHT:  # refused as the real server does, never shrunk
            raise CropTooLarge(f"crop: {w}x{h} is larger than the rendered frame {WIDTH}x{HEIGHT}")
        if crop.mode == pb.CROP_MODE_RANDOM:
            x0 = int(rng.integers(0, WIDTH - w + 1))
            y0 = int(rng.integers(0, HEIGHT - h + 1))
        else:
            x0, y0 = (WIDTH - w) // 2, (HEIGHT - h) // 2
        out = {k: np.ascontiguousarray(v[y0:y0 + h, x0:x0 + w]) for k, v in out.items()}
    return out


class CropTooLarge(ValueError):
    pass


def make_sample(seed, index, fields, flow_dtype, compression, crop, with_motion=True) -> pb.Sample:
    fields = list(fields) or DEFAULT_FIELDS
    for f in fields:
        if f not in NAMES:
            raise ValueError(f"fields: unknown field {f}")
    arrays = make_arrays(seed, index, fields, flow_dtype == pb.FLOW_DTYPE_F16, crop)
    s = pb.Sample(index=index, dataset=DATASET, fingerprint=FINGERPRINT, seed=seed,
                  source_id=f"src{index % 4}")
    for f in fields:
        a = arrays[NAMES[f]]
        raw = a.astype(a.dtype.newbyteorder("<"), copy=False).tobytes()
        dtype = {np.dtype("u1"): pb.DTYPE_U8, np.dtype("f2"): pb.DTYPE_F16, np.dtype("f4"): pb.DTYPE_F32}[a.dtype]
        t = pb.Tensor(name=NAMES[f], shape=list(a.shape), dtype=dtype, raw_size=len(raw))
        if compression == pb.COMPRESSION_LZ4:
            t.compression = pb.COMPRESSION_LZ4
            t.data = lz4.block.compress(raw, store_size=True)
        else:
            t.compression = pb.COMPRESSION_NONE
            t.data = raw
        s.tensors.append(t)
        s.height, s.width = a.shape[0], a.shape[1]
    if with_motion:
        s.camera.law = "fake"
        s.camera.translation.extend([0.01 * index, 0.0, -0.1])
        s.camera.axis_angle.extend([0.0, 0.001 * index, 0.0])
        s.camera.rotation.extend([1, 0, 0, 0, 1, 0, 0, 0, 1])
        s.intrinsics.fx = s.intrinsics.fy = 50.0
        s.intrinsics.cx, s.intrinsics.cy = WIDTH / 2, HEIGHT / 2
        for k in range(index % 3):
            o = s.objects.add(label=k + 1, instance=k, score=0.9, area=0.05)
            o.motion.translation.extend([0.0, 0.0, 0.01 * k])
            o.motion.axis_angle.extend([0.0, 0.0, 0.0])
            o.motion.rotation.extend([1, 0, 0, 0, 1, 0, 0, 0, 1])
    return s


class Service(pb_grpc.MpiFlowServicer):
    def __init__(self, delay: float, draining: threading.Event):
        self.delay = delay
        self.draining = draining

    def _check(self, req, context):
        spec = req.spec
        if spec.dataset not in ("", DATASET):
            context.abort(grpc.StatusCode.NOT_FOUND, f"dataset {spec.dataset!r} not found")
        if spec.fingerprint not in (0, FINGERPRINT):
            context.abort(grpc.StatusCode.FAILED_PRECONDITION, "fingerprint differs")

    def _make(self, context, spec, index):
        try:
            return make_sample(spec.seed, index, spec.fields, spec.flow_dtype, spec.compression,
                               spec.crop if spec.HasField("crop") else None)
        except CropTooLarge as e:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, str(e))

    def StreamSamples(self, req, context):
        self._check(req, context)
        w = req.world_size or 1
        if req.rank >= w:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, "rank: must be < world_size")
        bs = max(1, req.batch_size)
        i = req.start_index + req.rank
        sent = 0
        batch = pb.SampleBatch()
        while context.is_active() and (req.count == 0 or sent < req.count):
            if self.draining.is_set():
                context.set_trailing_metadata((("mpiflow-next-index", str(i)),))
                context.abort(grpc.StatusCode.UNAVAILABLE, "server draining")
            if self.delay:
                time.sleep(self.delay)
            batch.samples.append(self._make(context, req.spec, i))
            i += w
            sent += 1
            if len(batch.samples) == bs or (req.count and sent == req.count):
                batch.next_index = i
                batch.resume_start_index = i - req.rank
                yield batch
                batch = pb.SampleBatch()

    def GetSample(self, req, context):
        self._check(req, context)
        return self._make(context, req.spec, req.index)

    def GetSamples(self, req, context):
        self._check(req, context)
        if not 1 <= len(req.indices) <= 256:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"indices: {len(req.indices)} (1 to 256)")
        for i in req.indices:
            if self.draining.is_set():
                context.abort(grpc.StatusCode.UNAVAILABLE, "server draining")
            if self.delay:
                time.sleep(self.delay)
            yield self._make(context, req.spec, i)

    def GetInfo(self, req, context):
        return pb.InfoResponse(
            version="fake-0",
            datasets=[pb.DatasetInfo(name=DATASET, fingerprint=FINGERPRINT, sources=4, is_default=True)],
            limits=pb.Limits(max_message_bytes=64 << 20, max_streams=64, max_batch_size=16, max_indices=256),
            workers=1,
            serving=not self.draining.is_set(),
        )


def health_handler(ready: threading.Event, draining: threading.Event):
    def check(request: bytes, context):
        ok = ready.is_set() and not draining.is_set()
        return b"\x08" + (b"\x01" if ok else b"\x02")

    return grpc.method_handlers_generic_handler(
        "grpc.health.v1.Health",
        {"Check": grpc.unary_unary_rpc_method_handler(check, request_deserializer=None,
                                                      response_serializer=None)},
    )


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("cmd", choices=["serve"])
    ap.add_argument("--addr", default="127.0.0.1:0")
    ap.add_argument("--delay", type=float, default=0.0, help="seconds per sample")
    ap.add_argument("--warmup", type=float, default=0.2, help="seconds NOT_SERVING after start")
    ap.add_argument("--size", default=None, help="WxH of the samples (default 64x48)")
    ap.add_argument("--metrics-addr", default=None)
    ap.add_argument("--source", default=None)
    a = ap.parse_args()
    if a.size:
        global WIDTH, HEIGHT
        WIDTH, HEIGHT = (int(v) for v in a.size.lower().split("x"))
    ready, draining, done = threading.Event(), threading.Event(), threading.Event()
    server = grpc.server(futures.ThreadPoolExecutor(max_workers=32),
                         options=[("grpc.max_send_message_length", 64 << 20)])
    pb_grpc.add_MpiFlowServicer_to_server(Service(a.delay, draining), server)
    server.add_generic_rpc_handlers((health_handler(ready, draining),))
    port = server.add_insecure_port(a.addr)
    if port == 0:
        print(f"cannot bind {a.addr}", file=sys.stderr)
        return 1
    server.start()
    host = a.addr.rsplit(":", 1)[0]
    print(f"mpiflow serving on {host}:{port}", flush=True)

    def on_term(*_):
        draining.set()
        done.set()

    signal.signal(signal.SIGTERM, on_term)
    signal.signal(signal.SIGINT, on_term)
    if done.wait(a.warmup):
        pass
    ready.set()
    done.wait()
    server.stop(grace=2).wait()
    return 0


if __name__ == "__main__":
    sys.exit(main())
