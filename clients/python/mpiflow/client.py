"""The gRPC client of an mpiflow server or of several replicas of it."""
from __future__ import annotations

import logging
import random
import threading
import time
from typing import Any, Dict, Iterable, List, Optional, Sequence, Tuple, Union

import grpc

from . import _health
from ._proto import mpiflow_pb2 as pb
from ._proto import mpiflow_pb2_grpc as pb_grpc
from .decode import Sample, decode_sample
from .errors import MpiFlowError, NotReadyError, is_retryable
from .spec import build_spec
from .stream import FlowStream

__all__ = ["Client", "parse_addresses"]

log = logging.getLogger("mpiflow")

SERVICE_NAME = "mpiflow.v1.MpiFlow"
DEFAULT_MAX_RECEIVE = 256 << 20
# Indices one GetSamples call may carry when the server's Limits.max_indices is not known yet.
DEFAULT_MAX_INDICES = 256


class _ShortAnswer(Exception):
    """A GetSamples call that ended cleanly before its last index."""


def parse_addresses(addresses: Union[str, Iterable[str]]) -> List[str]:
    """["host:port", ...] from a list or a comma-separated string; "grpc://" prefixes dropped."""
    if isinstance(addresses, str):
        addresses = addresses.split(",")
    out = []
    for a in addresses:
        a = a.strip()
        for prefix in ("grpc://", "http://"):
            if a.startswith(prefix):
                a = a[len(prefix):]
        a = a.rstrip("/")
        if a and a not in out:
            out.append(a)
    if not out:
        raise ValueError("no server address given")
    return out


def _pem(v: Union[str, bytes, None]) -> Optional[bytes]:
    """PEM bytes as given, or read from a file path."""
    if v is None or isinstance(v, bytes):
        return v
    with open(v, "rb") as f:
        return f.read()


class _Replica:
    __slots__ = ("address", "channel", "stub", "health", "failures", "down_until")

    def __init__(self, address: str):
        self.address = address
        self.channel = None
        self.stub = None
        self.health = None
        self.failures = 0
        self.down_until = 0.0


class Client:
    """A client of one mpiflow server or of several replicas serving the same datasets.

    `Client("127.0.0.1:50051")` or `Client(["host-a:50051", "host-b:50051"])` (or a
    comma-separated string). The constructor waits up to `timeout` seconds until at least one
    replica's `grpc.health.v1` status is SERVING (`wait=False` skips this), then raises the
    receive-message limit to the server's `Limits.max_message_bytes` when that is larger than
    `max_receive_message_bytes` (256 MiB by default). `token` is sent as
    `authorization: Bearer TOKEN` on every call.

    TLS: `tls_ca` (the CA that signed the servers' certificates, a PEM file path or PEM bytes)
    turns TLS on; `tls_cert` and `tls_key` add a client certificate for servers that require one;
    `tls_domain` is the name to verify when the addresses are not names the certificate carries.

    Unary calls (`get_sample`, `info`) fail over to another replica on transport errors, and so
    does `get_samples` (random access in batches), which continues with the indices not yet
    received;
    `stream()` returns a FlowStream, which resumes a broken stream on a healthy replica from its
    cursor. Channels are made in the process that first uses them: create the Client after
    forking (e.g. inside a DataLoader worker), not before.
    """

    def __init__(
        self,
        addresses: Union[str, Iterable[str]],
        *,
        token: Optional[str] = None,
        timeout: float = 60.0,
        rpc_timeout: float = 120.0,
        max_receive_message_bytes: int = DEFAULT_MAX_RECEIVE,
        wait: bool = True,
        channel_options: Sequence[Tuple[str, Any]] = (),
        tls_ca: Union[str, bytes, None] = None,
        tls_cert: Union[str, bytes, None] = None,
        tls_key: Union[str, bytes, None] = None,
        tls_domain: Optional[str] = None,
    ):
        self.addresses = parse_addresses(addresses)
        if (tls_cert is None) != (tls_key is None):
            raise ValueError("tls_cert and tls_key go together")
        if tls_ca is None and (tls_cert is not None or tls_domain is not None):
            raise ValueError("tls_cert, tls_key and tls_domain need tls_ca (the server's CA)")
        self._tls: Optional[Tuple[bytes, Optional[bytes], Optional[bytes]]] = (
            (_pem(tls_ca), _pem(tls_key), _pem(tls_cert)) if tls_ca is not None else None
        )
        self._tls_domain = tls_domain
        self.timeout = float(timeout)
        self.rpc_timeout = float(rpc_timeout)
        self.metadata: Tuple[Tuple[str, str], ...] = (
            (("authorization", f"Bearer {token}"),) if token else ()
        )
        self._max_receive = int(max_receive_message_bytes)
        self._extra_options = tuple(channel_options)
        self._lock = threading.Lock()
        self._replicas = {a: _Replica(a) for a in self.addresses}
        self._info: Optional[pb.InfoResponse] = None
        self._closed = False
        if wait:
            self.connect(self.timeout)

    # -- channels -----------------------------------------------------------------------------

    def _options(self) -> List[Tuple[str, Any]]:
        return [
            ("grpc.max_receive_message_length", self._max_receive),
            ("grpc.max_send_message_length", 64 << 20),
            ("grpc.keepalive_time_ms", 30_000),
            ("grpc.keepalive_timeout_ms", 10_000),
            ("grpc.http2.max_pings_without_data", 0),
            # Come back quickly to a replica that restarted.
            ("grpc.initial_reconnect_backoff_ms", 100),
            ("grpc.min_reconnect_backoff_ms", 100),
            ("grpc.max_reconnect_backoff_ms", 1000),
            # Each Client has its own connections (streams of one Client share them).
            ("grpc.use_local_subchannel_pool", 1),
            *((("grpc.ssl_target_name_override", self._tls_domain),) if self._tls_domain else ()),
            *self._extra_options,
        ]

    def _channel(self, address: str) -> grpc.Channel:
        if self._tls is None:
            return grpc.insecure_channel(address, options=self._options())
        ca, key, cert = self._tls
        creds = grpc.ssl_channel_credentials(root_certificates=ca, private_key=key, certificate_chain=cert)
        return grpc.secure_channel(address, creds, options=self._options())

    def _replica(self, address: str) -> _Replica:
        r = self._replicas[address]
        if r.channel is None:
            with self._lock:
                if self._closed:
                    raise MpiFlowError("client is closed")
                if r.channel is None:
                    r.channel = self._channel(address)
                    r.stub = pb_grpc.MpiFlowStub(r.channel)
                    r.health = r.channel.unary_unary(
                        _health.CHECK_METHOD,
                        request_serializer=None,
                        response_deserializer=None,
                    )
        return r

    def stub(self, address: str) -> "pb_grpc.MpiFlowStub":
        """The generated stub of one replica (for calls this class does not wrap)."""
        return self._replica(address).stub

    def _adopt_limits(self, info: "pb.InfoResponse") -> None:
        want = int(info.limits.max_message_bytes) if info.HasField("limits") else 0
        # Some slack over the server's limit for framing.
        if want and want + (1 << 20) > self._max_receive:
            with self._lock:
                self._max_receive = want + (1 << 20)
                old = [r.channel for r in self._replicas.values() if r.channel is not None]
                for r in self._replicas.values():
                    r.channel = r.stub = r.health = None
            for ch in old:
                ch.close()

    def close(self) -> None:
        """Closes every channel (active streams end with CANCELLED)."""
        with self._lock:
            self._closed = True
            chans = [r.channel for r in self._replicas.values() if r.channel is not None]
            for r in self._replicas.values():
                r.channel = r.stub = r.health = None
        for ch in chans:
            ch.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __getstate__(self):
        raise TypeError(
            "mpiflow.Client holds gRPC channels and cannot be pickled; create it in the process "
            "that uses it (MPIFlowDataset does this for you)"
        )

    # -- health and replica choice ------------------------------------------------------------

    def health(self, address: str, timeout: float = 2.0, service: str = SERVICE_NAME) -> str:
        """The grpc.health.v1 status of one replica: SERVING, NOT_SERVING, SERVICE_UNKNOWN,
        UNKNOWN, or UNREACHABLE when the call itself failed."""
        try:
            raw = self._replica(address).health(
                _health.encode_request(service), timeout=timeout, metadata=self.metadata
            )
        except grpc.RpcError as e:
            if e.code() == grpc.StatusCode.UNIMPLEMENTED:
                return "UNIMPLEMENTED"
            if e.code() == grpc.StatusCode.NOT_FOUND and service:
                # A health service that only knows the server as a whole ("").
                return self.health(address, timeout, service="")
            return "UNREACHABLE"
        return _health.decode_response(raw)

    def serving(self, timeout: float = 2.0) -> List[str]:
        """The replicas whose health is SERVING now."""
        return [a for a in self.addresses if self.health(a, timeout) == _health.SERVING]

    def connect(self, timeout: Optional[float] = None) -> List[str]:
        """wait_ready(), then GetInfo to raise the receive limit to the server's message limit."""
        ok = self.wait_ready(timeout)
        try:
            self._adopt_limits(self.info())
        except (grpc.RpcError, MpiFlowError) as e:  # a server without GetInfo still streams
            log.warning("mpiflow: GetInfo failed (%s); keeping the default limits", e)
        return ok

    def wait_ready(self, timeout: Optional[float] = None, *, all_replicas: bool = False) -> List[str]:
        """Waits until one replica (every one with `all_replicas`) is SERVING; returns those that
        are. Raises NotReadyError after `timeout` seconds (default: the client's)."""
        timeout = self.timeout if timeout is None else float(timeout)
        deadline = time.monotonic() + timeout
        delay = 0.05
        last: Dict[str, str] = {}
        while True:
            ok = []
            for a in self.addresses:
                left = max(0.05, min(2.0, deadline - time.monotonic()))
                last[a] = self.health(a, left)
                if last[a] == _health.SERVING:
                    ok.append(a)
                    self._mark_up(a)
            if ok and (not all_replicas or len(ok) == len(self.addresses)):
                return ok
            if time.monotonic() >= deadline:
                states = ", ".join(f"{a}: {s}" for a, s in last.items())
                raise NotReadyError(f"no mpiflow server SERVING after {timeout:.0f} s ({states})")
            time.sleep(min(delay, max(0.0, deadline - time.monotonic())))
            delay = min(delay * 2, 0.5)

    def _mark_down(self, address: str) -> None:
        r = self._replicas[address]
        r.failures += 1
        backoff = min(0.1 * (2 ** (r.failures - 1)), 2.0) * (0.75 + 0.5 * random.random())
        r.down_until = time.monotonic() + backoff

    def _mark_up(self, address: str) -> None:
        r = self._replicas[address]
        r.failures = 0
        r.down_until = 0.0

    def _candidates(self, prefer: Optional[str] = None, avoid: Optional[str] = None) -> List[str]:
        """Replicas in the order to try: `prefer` first, then round-robin after it, those
        marked down (recent failures) last, `avoid` (the one that just failed) very last."""
        n = len(self.addresses)
        start = self.addresses.index(prefer) if prefer in self._replicas else 0
        order = [self.addresses[(start + i) % n] for i in range(n)]
        now = time.monotonic()
        up = [a for a in order if self._replicas[a].down_until <= now and a != avoid]
        down = sorted(
            (a for a in order if a not in up and a != avoid),
            key=lambda a: self._replicas[a].down_until,
        )
        rest = [avoid] if avoid in self._replicas else []
        return up + down + rest

    def pick_replica(
        self,
        *,
        prefer: Optional[str] = None,
        avoid: Optional[str] = None,
        deadline: Optional[float] = None,
        stop: Optional[threading.Event] = None,
    ) -> str:
        """A replica that is SERVING now, waiting (with backoff) up to `deadline` (monotonic)."""
        delay = 0.1
        while True:
            for a in self._candidates(prefer, avoid):
                if stop is not None and stop.is_set():
                    raise MpiFlowError("stopped")
                r = self._replicas[a]
                wait = r.down_until - time.monotonic()
                if wait > 0 and len(self.addresses) > 1 and a != avoid:
                    continue  # a fresher replica may come first next round
                status = self.health(a, 2.0)
                if status == _health.SERVING or status == "UNIMPLEMENTED":
                    return a
                self._mark_down(a)
            now = time.monotonic()
            if deadline is not None and now >= deadline:
                raise MpiFlowError(
                    f"no mpiflow replica SERVING ({', '.join(self.addresses)}) within the retry time"
                )
            pause = delay if deadline is None else min(delay, max(0.0, deadline - now))
            if stop is not None:
                if stop.wait(pause):
                    raise MpiFlowError("stopped")
            else:
                time.sleep(pause)
            delay = min(delay * 2, 1.0)

    def _unary(self, name: str, request: Any, timeout: Optional[float], address: Optional[str]):
        timeout = self.rpc_timeout if timeout is None else timeout
        deadline = time.monotonic() + timeout
        last: Optional[BaseException] = None
        tried = 0
        addr = address
        while True:
            if address is None:
                try:
                    addr = self.pick_replica(prefer=addr, avoid=addr if last else None, deadline=deadline)
                except MpiFlowError as e:
                    raise MpiFlowError(f"{name}: {e}") from last
            left = max(0.1, deadline - time.monotonic())
            try:
                resp = getattr(self._replica(addr).stub, name)(
                    request, timeout=left, metadata=self.metadata
                )
                self._mark_up(addr)
                return resp
            except grpc.RpcError as e:
                tried += 1
                if not is_retryable(e) or address is not None or time.monotonic() >= deadline:
                    raise
                if e.code() == grpc.StatusCode.DEADLINE_EXCEEDED:
                    raise
                log.warning("mpiflow: %s on %s failed (%s); trying again", name, addr, e.code())
                self._mark_down(addr)
                last = e

    # -- calls ----------------------------------------------------------------------------------

    def info(self, *, timeout: Optional[float] = None, address: Optional[str] = None) -> "pb.InfoResponse":
        """GetInfo: datasets (name, fingerprint, sources), models, limits, version."""
        info = self._unary("GetInfo", pb.InfoRequest(), timeout, address)
        if address is None:
            self._info = info
        return info

    def get_sample(
        self,
        index: int,
        *,
        raw: bool = False,
        timeout: Optional[float] = None,
        address: Optional[str] = None,
        **spec: Any,
    ) -> Union[Sample, "pb.Sample"]:
        """GetSample: one sample by its address, decoded (`raw=True`: the Sample message).
        `spec`: the sample options (seed, dataset, fields, crop, ...: `spec.build_spec`)."""
        req = pb.SampleRequest(
            index=int(index),
            spec=build_spec(**spec),
        )
        s = self._unary("GetSample", req, timeout, address)
        return s if raw else decode_sample(s)

    def max_indices(self) -> int:
        """Indices one GetSamples call may carry: the server's Limits.max_indices once GetInfo
        was called (connect() does), else 256."""
        info = self._info
        if info is not None and info.HasField("limits") and info.limits.max_indices:
            return int(info.limits.max_indices)
        return DEFAULT_MAX_INDICES

    def get_samples(
        self,
        indices: Iterable[int],
        *,
        raw: bool = False,
        timeout: Optional[float] = None,
        address: Optional[str] = None,
        prefer: Optional[str] = None,
        **spec: Any,
    ) -> List[Union[Sample, "pb.Sample"]]:
        """GetSamples: the samples of `indices` (any order, duplicates allowed) in that order,
        each the same bytes as get_sample of its index. A list longer than `max_indices()` is
        sent as several calls. A call broken by a retryable error (UNAVAILABLE, a killed or
        draining replica) goes on with the indices not yet received on another SERVING replica
        (`prefer` is tried first, without a health check), within `timeout` seconds per call;
        after the first sample the dataset and fingerprint are pinned, so a replica serving
        other data is refused rather than mixed in. `address` uses that replica only. `spec`: the
        sample options (seed, dataset, fields, crop, ...: `spec.build_spec`)."""
        idx = [int(i) for i in indices]
        if any(i < 0 for i in idx):
            raise ValueError("indices must be >= 0")
        common = build_spec(**spec)
        limit = max(1, self.max_indices())
        out: List[Any] = []
        for at in range(0, len(idx), limit):
            out.extend(self._get_samples(common, idx[at:at + limit], timeout, address, prefer))
        return out if raw else [decode_sample(s) for s in out]

    def _get_samples(
        self,
        common: "pb.SampleSpec",
        idx: List[int],
        timeout: Optional[float],
        address: Optional[str],
        prefer: Optional[str],
    ) -> List["pb.Sample"]:
        timeout = self.rpc_timeout if timeout is None else timeout
        deadline = time.monotonic() + timeout
        got: List[Any] = []
        addr = address or (prefer if prefer in self._replicas else None) or self.addresses[0]
        last: Optional[BaseException] = None
        while True:
            if last is not None and address is None:
                try:
                    addr = self.pick_replica(prefer=addr, avoid=addr, deadline=deadline)
                except MpiFlowError as e:
                    raise MpiFlowError(f"GetSamples: {e}") from last
            req = pb.SamplesRequest(indices=idx[len(got):], spec=common)
            left = max(0.1, deadline - time.monotonic())
            try:
                call = self._replica(addr).stub.GetSamples(req, timeout=left, metadata=self.metadata)
                for s in call:
                    want = idx[len(got)]
                    if s.index != want:
                        call.cancel()
                        raise MpiFlowError(f"GetSamples on {addr}: expected index {want}, got {s.index}")
                    if not common.dataset and s.dataset:
                        common.dataset = s.dataset
                    if not common.fingerprint and s.fingerprint:
                        common.fingerprint = s.fingerprint
                    got.append(s)
                    if len(got) == len(idx):
                        break
                if len(got) < len(idx):
                    # a clean end before the last index (never expected): go on elsewhere
                    raise _ShortAnswer(f"GetSamples on {addr} ended after {len(got)} of {len(idx)}")
                self._mark_up(addr)
                return got
            except (grpc.RpcError, _ShortAnswer) as e:
                retry = isinstance(e, _ShortAnswer) or (
                    is_retryable(e) and e.code() != grpc.StatusCode.DEADLINE_EXCEEDED
                )
                if not retry or address is not None or time.monotonic() >= deadline:
                    raise
                log.warning("mpiflow: GetSamples on %s failed after %d of %d (%s); going on elsewhere",
                            addr, len(got), len(idx), getattr(e, "code", lambda: e)())
                self._mark_down(addr)
                last = e

    def stream(self, **kwargs: Any) -> FlowStream:
        """A FlowStream on this client (see FlowStream for the arguments)."""
        return FlowStream(self, **kwargs)

    def open_stream(self, address: str, request: "pb.StreamRequest", *, timeout: Optional[float] = None):
        """The raw StreamSamples call on one replica (an iterator of SampleBatch and a grpc.Call)."""
        return self._replica(address).stub.StreamSamples(
            request, timeout=timeout, metadata=self.metadata
        )
