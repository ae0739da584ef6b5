"""FlowStream: one consumer's stream of samples, resumed across failures and replicas; and a
background prefetcher with a bounded buffer."""
from __future__ import annotations

import logging
import queue
import threading
import time
from typing import Any, Callable, Iterable, Iterator, List, Optional, Protocol

import grpc

from ._proto import mpiflow_pb2 as pb
from .decode import decode_sample
from .errors import MpiFlowError, is_retryable
from .spec import build_spec

__all__ = ["FlowStream", "Prefetcher", "ProtocolError", "StreamFailed"]

log = logging.getLogger("mpiflow")

NEXT_INDEX_TRAILER = "mpiflow-next-index"


class ProtocolError(MpiFlowError):
    """The server sent an index out of the stream's sequence (a gap), or a wrong cursor."""


class StreamFailed(MpiFlowError):
    """The stream could not be resumed on any replica within the retry time."""


class _Interrupted(Exception):
    pass


class Replicas(Protocol):
    """What a FlowStream needs of its client (`mpiflow.Client` is one): the replicas' addresses,
    a SERVING replica to fail over to, the raw StreamSamples call, and the replica book-keeping."""

    addresses: List[str]

    def pick_replica(
        self,
        *,
        prefer: Optional[str] = None,
        avoid: Optional[str] = None,
        deadline: Optional[float] = None,
        stop: Optional[threading.Event] = None,
    ) -> str: ...

    def open_stream(self, address: str, request: "pb.StreamRequest", *, timeout: Optional[float] = None) -> Any: ...

    def _mark_up(self, address: str) -> None: ...

    def _mark_down(self, address: str) -> None: ...


class FlowStream:
    """The samples of one consumer: indices start_index + rank + k * world_size, in order.

    Iterating yields decoded `Sample`s (`raw=True`: the Sample messages; `transform`: whatever
    `transform(sample, next_index)` returns). `next_index` is the cursor: the index of the next
    sample this stream will yield, and `resume_start_index` (= next_index - rank) the
    `start_index` that continues it exactly.

    When the stream breaks (UNAVAILABLE, a reset connection, a killed or draining server, a stream
    that ends before `count`), it is reopened from the cursor on a SERVING replica — another one
    first, the same one once it is back — with backoff, for up to `retry_timeout` seconds without
    progress. The consumer sees every index once, with no gap and no repeat. After the first
    sample the dataset name and fingerprint are pinned, so a replica serving different data is
    refused (FAILED_PRECONDITION) rather than silently mixed in.

    `spec`: the sample options (seed, dataset, fields, crop, ...), the same for every request of
    the stream (`spec.build_spec`).
    """

    def __init__(
        self,
        client: Replicas,
        *,
        rank: int = 0,
        world_size: int = 1,
        start_index: int = 0,
        count: Optional[int] = None,
        batch_size: int = 1,
        server_prefetch: int = 0,
        retry_timeout: float = 120.0,
        raw: bool = False,
        transform: Optional[Callable[[Any, int], Any]] = None,
        address: Optional[str] = None,
        **spec: Any,
    ):
        world_size = max(1, int(world_size))
        if not 0 <= int(rank) < world_size:
            raise ValueError(f"rank {rank} is not in 0..{world_size - 1}")
        if int(start_index) < 0:
            raise ValueError("start_index must be >= 0")
        self.client = client
        self.rank = int(rank)
        self.world_size = world_size
        self.next_index = int(start_index) + self.rank
        self.count = int(count) if count else 0
        self.delivered = 0
        self.retry_timeout = float(retry_timeout)
        self.batch_size = int(batch_size)
        self.server_prefetch = int(server_prefetch)
        self.raw = raw
        self.transform = transform
        self.failovers = 0
        self.address = address or client.addresses[self.rank % len(client.addresses)]
        self._spec = build_spec(**spec)
        self._call = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._started = False

    @property
    def resume_start_index(self) -> int:
        return self.next_index - self.rank

    @property
    def remaining(self) -> Optional[int]:
        """Samples still to come (None: endless)."""
        return self.count - self.delivered if self.count else None

    def request(self) -> "pb.StreamRequest":
        """The StreamRequest that continues this stream exactly from its cursor."""
        return pb.StreamRequest(
            rank=self.rank,
            world_size=self.world_size,
            start_index=self.resume_start_index,
            count=self.count - self.delivered if self.count else 0,
            batch_size=self.batch_size,
            prefetch=self.server_prefetch,
            spec=self._spec,
        )

    def close(self) -> None:
        """Ends the stream (from any thread): the open call is cancelled, iteration stops."""
        self._stop.set()
        with self._lock:
            call, self._call = self._call, None
        if call is not None:
            call.cancel()

    def __iter__(self) -> Iterator[Any]:
        if self._started:
            raise RuntimeError("a FlowStream can be iterated once (make a new one to resume)")
        self._started = True
        return self._run()

    def _pin(self, s: "pb.Sample") -> None:
        if not self._spec.dataset and s.dataset:
            self._spec.dataset = s.dataset
        if not self._spec.fingerprint and s.fingerprint:
            self._spec.fingerprint = s.fingerprint

    def _run(self) -> Iterator[Any]:
        failing_since: Optional[float] = None
        cause: Optional[BaseException] = None
        addr = self.address
        try:
            while not self._stop.is_set() and (not self.count or self.delivered < self.count):
                if failing_since is not None:
                    deadline = failing_since + self.retry_timeout
                    try:
                        addr = self.client.pick_replica(
                            prefer=addr, avoid=addr, deadline=deadline, stop=self._stop
                        )
                    except MpiFlowError as e:
                        if self._stop.is_set():
                            return
                        raise StreamFailed(
                            f"stream rank {self.rank}/{self.world_size} stopped at index "
                            f"{self.next_index}: {e}; last error: {_describe(cause)}"
                        ) from cause
                    self.failovers += 1
                    log.info("mpiflow: resuming rank %d at index %d on %s",
                             self.rank, self.next_index, addr)
                self.address = addr
                try:
                    call = self.client.open_stream(addr, self.request())
                    with self._lock:
                        if self._stop.is_set():
                            call.cancel()
                            return
                        self._call = call
                    for batch in call:
                        progressed = False
                        for s in batch.samples:
                            if s.index < self.next_index:
                                # Already delivered (never expected: the request starts at the
                                # cursor); dropped so that nothing repeats.
                                log.warning("mpiflow: dropped repeated index %d", s.index)
                                continue
                            if s.index != self.next_index:
                                raise ProtocolError(
                                    f"expected index {self.next_index}, got {s.index} "
                                    f"(rank {self.rank}/{self.world_size} on {addr})"
                                )
                            self._pin(s)
                            self.next_index += self.world_size
                            self.delivered += 1
                            progressed = True
                            if self.raw:
                                item: Any = s
                            else:
                                item = decode_sample(s)
                            if self.transform is not None:
                                item = self.transform(item, self.next_index)
                            yield item
                            if self.count and self.delivered >= self.count:
                                return
                        if batch.samples and batch.next_index and batch.next_index != self.next_index:
                            raise ProtocolError(
                                f"batch next_index {batch.next_index} != cursor {self.next_index}"
                            )
                        if progressed:
                            failing_since = None
                            self.client._mark_up(addr)
                    if self._stop.is_set():
                        return
                    # A clean end before `count` (or of an endless stream): the server stopped
                    # early (draining); go on elsewhere.
                    raise _Interrupted(f"stream ended at index {self.next_index} on {addr}")
                except grpc.RpcError as e:
                    if self._stop.is_set():
                        return
                    if not is_retryable(e):
                        raise MpiFlowError(
                            f"StreamSamples on {addr} failed: {_describe(e)}"
                        ) from e
                    self._check_trailer(e)
                    cause = e
                except _Interrupted as e:
                    cause = e
                finally:
                    with self._lock:
                        call, self._call = self._call, None
                    if call is not None:
                        call.cancel()
                log.warning("mpiflow: stream rank %d on %s broke at index %d: %s",
                            self.rank, addr, self.next_index, _describe(cause))
                self.client._mark_down(addr)
                if failing_since is None:
                    failing_since = time.monotonic()
        finally:
            self._stop.set()

    def _check_trailer(self, e: grpc.RpcError) -> None:
        try:
            md = e.trailing_metadata() or ()
        except Exception:
            return
        for k, v in md:
            if k == NEXT_INDEX_TRAILER:
                try:
                    cursor = int(v)
                except (TypeError, ValueError):
                    return
                if cursor != self.next_index:
                    # The server's cursor counts what it sent; ours what we received. Ours wins.
                    log.info("mpiflow: server cursor %d, client cursor %d", cursor, self.next_index)


def _describe(e: Optional[BaseException]) -> str:
    if e is None:
        return "none"
    if isinstance(e, grpc.RpcError) and hasattr(e, "code"):
        return f"{e.code().name}: {e.details()}"
    return str(e)


_END = object()


class _Error:
    __slots__ = ("exc",)

    def __init__(self, exc: BaseException):
        self.exc = exc


class Prefetcher:
    """Runs an iterator in a background thread, `maxsize` items ahead (a bounded queue).

    Iterating yields the items in order; an exception in the thread is raised in the consumer.
    `close()` (also at the end of a `with` block or when the iterator is dropped) stops the
    thread: `on_close` is called first (e.g. FlowStream.close, which cancels the gRPC call the
    thread may be blocked in).
    """

    def __init__(self, it: Iterable[Any], maxsize: int = 8, on_close: Optional[Callable[[], None]] = None,
                 name: str = "mpiflow-prefetch"):
        self._q: "queue.Queue[Any]" = queue.Queue(maxsize=max(1, int(maxsize)))
        self._stop = threading.Event()
        self._on_close = on_close
        self._it = iter(it)
        self._done = False
        self._thread = threading.Thread(target=self._work, name=name, daemon=True)
        self._thread.start()

    def _put(self, item: Any) -> bool:
        while not self._stop.is_set():
            try:
                self._q.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def _work(self) -> None:
        try:
            for item in self._it:
                if not self._put(item):
                    return
            self._put(_END)
        except BaseException as e:  # forwarded to the consumer
            self._put(_Error(e))
        finally:
            close = getattr(self._it, "close", None)
            if close is not None:
                try:
                    close()
                except Exception:
                    pass

    def __iter__(self) -> "Prefetcher":
        return self

    def __next__(self) -> Any:
        if self._done:
            raise StopIteration
        while True:
            try:
                item = self._q.get(timeout=0.5)
                break
            except queue.Empty:
                if not self._thread.is_alive() and self._q.empty():
                    self._done = True
                    raise StopIteration
        if item is _END:
            self._done = True
            raise StopIteration
        if isinstance(item, _Error):
            self._done = True
            raise item.exc
        return item

    def qsize(self) -> int:
        """Items ready in the buffer."""
        return self._q.qsize()

    def close(self, timeout: float = 5.0) -> None:
        self._done = True
        self._stop.set()
        if self._on_close is not None:
            try:
                self._on_close()
            except Exception:
                pass
        # Unblock a producer waiting on a full queue.
        while True:
            try:
                self._q.get_nowait()
            except queue.Empty:
                break
        if self._thread is not threading.current_thread():
            self._thread.join(timeout)

    def __enter__(self) -> "Prefetcher":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            if not self._done:
                self._stop.set()
                if self._on_close is not None:
                    self._on_close()
        except Exception:
            pass
