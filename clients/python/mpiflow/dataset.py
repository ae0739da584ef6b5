"""MPIFlowDataset: RAFT-style samples from mpiflow servers, sharded over ranks and workers,
with exact resume and failover. A torch IterableDataset when torch is importable."""
from __future__ import annotations

import copy
from typing import Any, Dict, Iterable, Iterator, List, Mapping, Optional, Sequence, Tuple, Union

from ._torch import dataset_class
from .client import Client, parse_addresses
from .decode import DEFAULT_FIELDS, field_name, is_motions, to_raft_dict
from .stream import FlowStream, Prefetcher

__all__ = [
    "MPIFlowDataset",
    "consumer_count",
    "consumer_id",
    "consumer_indices",
    "resolve_consumer",
]

STATE_VERSION = 1


# -- shard math (pure functions) -----------------------------------------------------------------


def consumer_id(rank: int, world_size: int, worker_id: int, num_workers: int) -> Tuple[int, int]:
    """(c, C): the global consumer id rank * num_workers + worker_id among world_size * num_workers."""
    world_size, num_workers = max(1, int(world_size)), max(1, int(num_workers))
    if not 0 <= rank < world_size:
        raise ValueError(f"rank {rank} is not in 0..{world_size - 1}")
    if not 0 <= worker_id < num_workers:
        raise ValueError(f"worker_id {worker_id} is not in 0..{num_workers - 1}")
    return rank * num_workers + worker_id, world_size * num_workers


def consumer_count(cursor: int, end: Optional[int], num_consumers: int) -> Optional[int]:
    """How many of one consumer's indices cursor, cursor + C, ... lie below `end` (None: endless)."""
    if end is None:
        return None
    if cursor >= end:
        return 0
    return (end - cursor + num_consumers - 1) // num_consumers


def consumer_indices(start_index: int, c: int, num_consumers: int, count: Optional[int]) -> range:
    """The indices consumer c of C receives out of [start_index, start_index + count)."""
    if count is None:
        raise ValueError("an endless stream has no finite index list")
    first = start_index + c
    return range(first, start_index + count, num_consumers) if first < start_index + count else range(0)


def _torch_dist() -> Tuple[int, int]:
    try:
        import torch.distributed as dist
    except Exception:
        return 0, 1
    try:
        if dist.is_available() and dist.is_initialized():
            return dist.get_rank(), dist.get_world_size()
    except Exception:
        pass
    return 0, 1


def _torch_worker() -> Tuple[int, int]:
    try:
        from torch.utils.data import get_worker_info
    except Exception:
        return 0, 1
    info = get_worker_info()
    if info is None:
        return 0, 1
    return info.id, info.num_workers


def resolve_consumer(
    rank: Optional[int] = None,
    world_size: Optional[int] = None,
    worker_id: Optional[int] = None,
    num_workers: Optional[int] = None,
) -> Tuple[int, int]:
    """(c, C) for the calling process: rank/world_size from the arguments, else from
    torch.distributed (when initialized), else 0/1; worker_id/num_workers likewise from the
    arguments, else from torch's get_worker_info() inside a DataLoader worker, else 0/1."""
    if (rank is None) != (world_size is None):
        raise ValueError("give both rank and world_size, or neither")
    if (worker_id is None) != (num_workers is None):
        raise ValueError("give both worker_id and num_workers, or neither")
    if rank is None:
        rank, world_size = _torch_dist()
    if worker_id is None:
        worker_id, num_workers = _torch_worker()
    return consumer_id(int(rank), int(world_size), int(worker_id), int(num_workers))


# -- the dataset ----------------------------------------------------------------------------------


class _MPIFlowDatasetImpl:
    """Optical-flow training samples from mpiflow servers, shaped like RAFT's FlowDataset.

    Iterating yields dicts: `img1`, `img2` float32 [3, H, W] in 0..255, `flow` float32
    [2, H, W], `valid` float32 [H, W], `index` (the sample's address), `next_index` (this
    consumer's cursor after it), and `occlusion`, `mask1`, `mask2`, `depth1`, `depth2`, `holes` when in
    `fields`, plus `camera`, `intrinsics`, `objects`, `num_objects` when `fields` holds
    "motions". Arrays are numpy (torch's default collate makes tensors of them).

    Sharding: the consumer id c = rank * num_workers + worker_id of C = world_size * num_workers
    (rank/world_size from torch.distributed, worker_id/num_workers from the DataLoader's
    get_worker_info(), unless given) receives start_index + c + k * C, k = 0, 1, ...: every index
    goes to exactly one consumer. `count` makes the stream finite: the indices
    [start_index, start_index + count) split over the consumers (None: endless).

    Resume: `state_dict()` holds each consumer's next index; a dataset given it through
    `load_state_dict()` (before the DataLoader iterator is made) yields exactly the samples not
    yet received, with the same ranks and workers. Iterated in the main process the dataset
    tracks itself; with DataLoader workers, call `track(batch)` on every batch the loop receives
    (the workers' own copies run ahead by their prefetch).

    Failover: with several addresses, a broken stream resumes on another SERVING replica from its
    cursor (no gap, no repeat), with backoff, for up to `retry_timeout` seconds.
    `prefetch` samples are decoded ahead in a background thread (0: none).
    `crop` (W, H) cuts every sample at a position drawn from the sample's own random stream
    (`crop_mode="random"`, the default: reproducible, part of the address) or at the centre
    (`crop_mode="center"`, the Client's default); a crop larger than the rendered frame is
    refused (INVALID_ARGUMENT naming `crop`), never shrunk, unless `augment` is given.
    `augment` is a server-side training augmentation (docs/augment.md): a preset reproducing a
    RAFT training stage ("raft-chairs", "raft-things", "raft-sintel", "raft-kitti") or its
    parameters as JSON text or a dict; it is part of the address (same bytes every time), makes
    its own random crop (the preset's size, or `crop` when given) and resizes the frame to fit it.
    `resample` picks the colour kernel of the target render ("bilinear", "bicubic", "bspline3",
    "bspline5", "lanczos3", "omoms3"; None = the dataset's), part of the fingerprint.
    `token`, `tls_ca`, `tls_cert`, `tls_key` and `tls_domain` are passed to each worker's Client.
    """

    def __init__(
        self,
        addresses: Union[str, Sequence[str]],
        *,
        seed: int = 0,
        dataset: Optional[str] = None,
        start_index: int = 0,
        count: Optional[int] = None,
        rank: Optional[int] = None,
        world_size: Optional[int] = None,
        worker_id: Optional[int] = None,
        num_workers: Optional[int] = None,
        fields: Iterable[str] = DEFAULT_FIELDS,
        lz4: bool = False,
        flow_dtype: str = "f32",
        crop: Any = None,
        crop_mode: str = "random",
        motion_preset: Optional[str] = None,
        motion_ranges_json: Optional[str] = None,
        max_objects: Optional[int] = None,
        motions_per_image: Optional[int] = None,
        augment: Any = None,
        resample: Optional[str] = None,
        batch_size: int = 1,
        prefetch: int = 8,
        server_prefetch: int = 0,
        token: Optional[str] = None,
        tls_ca: Union[str, bytes, None] = None,
        tls_cert: Union[str, bytes, None] = None,
        tls_key: Union[str, bytes, None] = None,
        tls_domain: Optional[str] = None,
        timeout: float = 120.0,
        retry_timeout: float = 120.0,
        fingerprint: int = 0,
        pad_objects: int = 8,
    ):
        super().__init__()
        self.addresses = parse_addresses(addresses)
        self.seed = int(seed)
        self.dataset = dataset or None
        self.start_index = int(start_index)
        self.count = int(count) if count is not None else None
        if self.start_index < 0 or (self.count is not None and self.count < 0):
            raise ValueError("start_index and count must be >= 0")
        self.rank, self.world_size = rank, world_size
        self.worker_id, self.num_workers = worker_id, num_workers
        if (rank is None) != (world_size is None) or (worker_id is None) != (num_workers is None):
            raise ValueError("give rank with world_size and worker_id with num_workers")
        fields = [fields] if isinstance(fields, str) else list(fields)
        self.motions = any(is_motions(f) for f in fields)
        self.fields = [field_name(f) for f in fields if not is_motions(f)]
        self.lz4 = bool(lz4)
        self.flow_dtype = flow_dtype
        self.crop = crop
        self.crop_mode = crop_mode
        self.motion_preset = motion_preset
        self.motion_ranges_json = motion_ranges_json
        self.max_objects = max_objects
        self.motions_per_image = motions_per_image
        self.augment = augment
        self.resample = resample
        self.batch_size = int(batch_size)
        self.prefetch = int(prefetch)
        self.server_prefetch = int(server_prefetch)
        self.token = token
        # paths or PEM bytes (picklable: the Client is made in each worker)
        self.tls = dict(tls_ca=tls_ca, tls_cert=tls_cert, tls_key=tls_key, tls_domain=tls_domain)
        self.timeout = float(timeout)
        self.retry_timeout = float(retry_timeout)
        self.fingerprint = int(fingerprint or 0)
        self.pad_objects = int(pad_objects)
        self.epoch = 0
        self._cursors: Dict[int, int] = {}
        self._num_consumers: Optional[int] = None

    # -- sharding ------------------------------------------------------------------------------

    @property
    def epoch_start(self) -> int:
        """The first index of the current epoch: start_index + epoch * count."""
        return self.start_index + self.epoch * (self.count or 0)

    def consumer(self) -> Tuple[int, int]:
        """(c, C) in the calling process (see resolve_consumer)."""
        return resolve_consumer(self.rank, self.world_size, self.worker_id, self.num_workers)

    def set_epoch(self, epoch: int) -> None:
        """With `count`: epoch e covers [start_index + e * count, start_index + (e + 1) * count)
        (new samples every epoch). Resets the cursors; call it before making the iterator."""
        if self.count is None:
            raise ValueError("set_epoch needs a finite count")
        self.epoch = int(epoch)
        self._cursors = {}

    # -- state ---------------------------------------------------------------------------------

    def track(self, batch: Mapping[str, Any]) -> None:
        """Records what the training loop received: a sample dict or a collated batch (uses its
        `index` and `next_index`). Needed for state_dict() only with DataLoader workers."""
        idx, nxt = batch["index"], batch["next_index"]
        if hasattr(idx, "tolist"):
            idx, nxt = idx.tolist(), nxt.tolist()
        if isinstance(idx, int):
            idx, nxt = [idx], [nxt]
        for i, n in zip(idx, nxt):
            i, n = int(i), int(n)
            num = n - i
            if num <= 0:
                raise ValueError(f"bad next_index {n} for index {i}")
            if self._num_consumers is not None and self._num_consumers != num:
                raise ValueError(
                    f"samples from {num} consumers after {self._num_consumers}: "
                    "one dataset's batches only"
                )
            self._num_consumers = num
            c = (i - self.epoch_start) % num
            if n > self._cursors.get(c, -1):
                self._cursors[c] = n

    def state_dict(self) -> Dict[str, Any]:
        """The resume state: the request's address (seed, dataset, fingerprint, start, count,
        epoch) and each consumer's next index ({c: index}, for the consumers seen here)."""
        return {
            "version": STATE_VERSION,
            "seed": self.seed,
            "dataset": self.dataset,
            "fingerprint": self.fingerprint,
            "start_index": self.start_index,
            "count": self.count,
            "epoch": self.epoch,
            "num_consumers": self._num_consumers,
            "cursors": dict(sorted(self._cursors.items())),
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Resumes from a state_dict() (before making the iterator / DataLoader iterator)."""
        if int(state.get("version", 0)) != STATE_VERSION:
            raise ValueError(f"unsupported state version {state.get('version')}")
        for key in ("seed", "start_index", "count"):
            if state.get(key) != getattr(self, key):
                raise ValueError(
                    f"state was saved with {key}={state.get(key)!r}, dataset has {getattr(self, key)!r}"
                )
        if state.get("dataset") and self.dataset and state["dataset"] != self.dataset:
            raise ValueError(f"state is of dataset {state['dataset']!r}, not {self.dataset!r}")
        self.dataset = state.get("dataset") or self.dataset
        self.fingerprint = int(state.get("fingerprint") or self.fingerprint or 0)
        self.epoch = int(state.get("epoch", 0))
        self._num_consumers = state.get("num_consumers")
        self._cursors = {int(c): int(n) for c, n in (state.get("cursors") or {}).items()}

    @staticmethod
    def merge_states(states: Iterable[Mapping[str, Any]]) -> Dict[str, Any]:
        """One state from every rank's state_dict() (e.g. after all_gather_object): the cursors
        of all consumers, loadable on every rank."""
        states = list(states)
        if not states:
            raise ValueError("no states")
        out = copy.deepcopy(dict(states[0]))
        cursors: Dict[int, int] = {}
        for s in states:
            for k in ("seed", "start_index", "count", "epoch"):
                if s.get(k) != out.get(k):
                    raise ValueError(f"states differ in {k}")
            if s.get("num_consumers") is not None:
                if out.get("num_consumers") not in (None, s["num_consumers"]):
                    raise ValueError("states differ in num_consumers")
                out["num_consumers"] = s["num_consumers"]
            for c, n in (s.get("cursors") or {}).items():
                cursors[int(c)] = max(int(n), cursors.get(int(c), 0))
        out["cursors"] = dict(sorted(cursors.items()))
        return out

    # -- iteration -----------------------------------------------------------------------------

    def _transform(self, sample: Any, next_index: int) -> Dict[str, Any]:
        if not self.fingerprint and sample.fingerprint:
            self.fingerprint = int(sample.fingerprint)
        if not self.dataset and sample.dataset:
            self.dataset = sample.dataset
        return to_raft_dict(sample, next_index=next_index, motions=self.motions, pad_objects=self.pad_objects)

    def make_stream(self, client: Client, c: int, num: int) -> Optional[FlowStream]:
        """The FlowStream of consumer c of num from its cursor (None when it has nothing left)."""
        if self._num_consumers is not None and self._cursors and self._num_consumers != num:
            raise ValueError(
                f"the resume state has {self._num_consumers} consumers (world_size * num_workers), "
                f"this run {num}: resume with the same ranks and DataLoader workers"
            )
        cursor = self._cursors.get(c, self.epoch_start + c)
        if (cursor - self.epoch_start) % num != c:
            raise ValueError(f"cursor {cursor} is not on consumer {c}'s sequence")
        end = self.epoch_start + self.count if self.count is not None else None
        n = consumer_count(cursor, end, num)
        if n == 0:
            return None
        return FlowStream(
            client,
            seed=self.seed,
            dataset=self.dataset,
            fingerprint=self.fingerprint,
            rank=c,
            world_size=num,
            start_index=cursor - c,
            count=n,
            fields=self.fields,
            lz4=self.lz4,
            flow_dtype=self.flow_dtype,
            crop=self.crop,
            crop_mode=self.crop_mode,
            motion_preset=self.motion_preset,
            motion_ranges_json=self.motion_ranges_json,
            max_objects=self.max_objects,
            motions_per_image=self.motions_per_image,
            augment=self.augment,
            resample=self.resample,
            batch_size=self.batch_size,
            server_prefetch=self.server_prefetch,
            retry_timeout=self.retry_timeout,
            transform=self._transform,
        )

    def __iter__(self) -> Iterator[Dict[str, Any]]:
        c, num = self.consumer()
        client = Client(self.addresses, token=self.token, timeout=self.timeout, wait=False, **self.tls)
        pf = None
        try:
            stream = self.make_stream(client, c, num)
            if stream is None:
                return
            client.connect(self.timeout)
            it: Iterator[Dict[str, Any]]
            if self.prefetch > 0:
                pf = Prefetcher(stream, self.prefetch, on_close=stream.close,
                                name=f"mpiflow-prefetch-{c}")
                it = pf
            else:
                it = iter(stream)
            for item in it:
                self._num_consumers = num
                self._cursors[c] = item["next_index"]
                yield item
        finally:
            if pf is not None:
                pf.close()
            client.close()

    def __getstate__(self) -> Dict[str, Any]:
        return dict(self.__dict__)

    def __repr__(self) -> str:
        return (
            f"MPIFlowDataset({self.addresses!r}, seed={self.seed}, dataset={self.dataset!r}, "
            f"start_index={self.start_index}, count={self.count}, fields={self.fields})"
        )


def _build_class():
    return dataset_class(_MPIFlowDatasetImpl, "MPIFlowDataset", __name__, "IterableDataset")


def __getattr__(name: str):
    # Lazily: torch is imported only when the dataset class is first used.
    if name == "MPIFlowDataset":
        cls = _build_class()
        globals()["MPIFlowDataset"] = cls
        return cls
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
