"""MPIFlowMapDataset: random access to mpiflow samples by index, for samplers of any order (a
torch map-style Dataset when torch is importable, a plain Python sequence otherwise)."""
from __future__ import annotations

import operator
import os
from typing import Any, Dict, Iterable, Iterator, List, Optional, Sequence, Tuple, Union

from ._torch import dataset_class
from .client import Client, parse_addresses
from .decode import DEFAULT_FIELDS, field_name, is_motions, to_raft_dict

__all__ = ["MPIFlowMapDataset"]


def _worker() -> Tuple[int, int]:
    try:
        from torch.utils.data import get_worker_info
    except Exception:
        return 0, 1
    info = get_worker_info()
    return (0, 1) if info is None else (info.id, info.num_workers)


class _MPIFlowMapDatasetImpl:
    """Optical-flow training samples by index: `ds[i]` is sample `start_index + i` of the address
    (seed, dataset, fingerprint, options), the same bytes as index `start_index + i` of a stream
    or of `Client.get_sample`, whichever replica serves it.

    `len(ds)` is `length`. Items are the dicts of MPIFlowDataset (`img1`, `img2`, `flow`,
    `valid`, `index`, the optional fields, and the motions with "motions" in `fields`), without
    `next_index` (there is no stream cursor). `ds.__getitems__(indices)` (which torch's
    DataLoader calls for a whole batch) fetches the list with one GetSamples call per
    `max_indices` (256) indices, made in parallel on the server's workers.

    Any sampler works (torch's DistributedSampler, `DataLoader(shuffle=True)`, any order,
    repeats): the sampler shards, not the dataset. Each process (every DataLoader worker) opens
    its own channels lazily on its first item, after the fork; a pickled dataset carries no
    channel. With several `addresses` (a list or a comma-separated string) worker w prefers
    replica w % len(addresses); a call that fails with a retryable error (UNAVAILABLE, a killed or
    draining replica) goes on with the indices not yet received on the next SERVING replica, for
    up to `retry_timeout` seconds.

    Options as MPIFlowDataset: `seed`, `dataset`, `fingerprint`, `fields`, `lz4`, `flow_dtype`,
    `crop` with `crop_mode` ("random" by default, each sample's own reproducible position; a crop
    larger than the rendered frame is refused by the server), `motion_preset`,
    `motion_ranges_json`, `max_objects`, `motions_per_image`, `augment`, `resample`, `pad_objects`,
    `token`, `tls_ca`, `tls_cert`, `tls_key`, `tls_domain`, `timeout` (the wait for a SERVING replica).
    """

    def __init__(
        self,
        addresses: Union[str, Sequence[str]],
        length: int,
        *,
        seed: int = 0,
        dataset: Optional[str] = None,
        start_index: int = 0,
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
        self.length = int(length)
        self.start_index = int(start_index)
        if self.length < 0 or self.start_index < 0:
            raise ValueError("length and start_index must be >= 0")
        self.seed = int(seed)
        self.dataset = dataset or None
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
        self.token = token
        self.tls = dict(tls_ca=tls_ca, tls_cert=tls_cert, tls_key=tls_key, tls_domain=tls_domain)
        self.timeout = float(timeout)
        self.retry_timeout = float(retry_timeout)
        self.fingerprint = int(fingerprint or 0)
        self.pad_objects = int(pad_objects)
        self._client: Optional[Client] = None
        self._pid: Optional[int] = None
        self._prefer: Optional[str] = None

    # -- the sequence --------------------------------------------------------------------------

    def __len__(self) -> int:
        return self.length

    def _position(self, i: Any) -> int:
        i = operator.index(i)
        if i < 0:
            i += self.length
        if not 0 <= i < self.length:
            raise IndexError(f"index {i} out of range for an MPIFlowMapDataset of length {self.length}")
        return i

    def __getitem__(self, i: Any) -> Any:
        if isinstance(i, slice):
            return self.__getitems__(range(*i.indices(self.length)))
        return self.__getitems__([i])[0]

    def __getitems__(self, indices: Iterable[Any]) -> List[Dict[str, Any]]:
        """The items of `indices` (positions, any order, repeats allowed), in that order."""
        addrs = [self.start_index + self._position(i) for i in indices]
        if not addrs:
            return []
        client = self.client()
        samples = client.get_samples(
            addrs,
            seed=self.seed,
            dataset=self.dataset,
            fingerprint=self.fingerprint,
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
            timeout=self.retry_timeout,
            prefer=self._prefer,
        )
        out = []
        for s in samples:
            # pinned after the first sample: later calls are refused by a replica of other data
            if not self.fingerprint and s.fingerprint:
                self.fingerprint = int(s.fingerprint)
            if not self.dataset and s.dataset:
                self.dataset = s.dataset
            out.append(to_raft_dict(s, motions=self.motions, pad_objects=self.pad_objects))
        return out

    def __iter__(self) -> Iterator[Dict[str, Any]]:
        for i in range(self.length):
            yield self[i]

    # -- channels ------------------------------------------------------------------------------

    def client(self) -> Client:
        """This process's Client, made on first use (again after a fork)."""
        pid = os.getpid()
        if self._client is None or self._pid != pid:
            # a client inherited over a fork belongs to the parent: left alone, not closed
            self._client = Client(self.addresses, token=self.token, timeout=self.timeout, wait=False, **self.tls)
            self._pid = pid
            w, _ = _worker()
            self._prefer = self.addresses[w % len(self.addresses)]
            self._client.connect(self.timeout)
        return self._client

    def close(self) -> None:
        """Closes this process's channels (they are opened again on the next item)."""
        if self._client is not None and self._pid == os.getpid():
            self._client.close()
        self._client = None

    def __getstate__(self) -> Dict[str, Any]:
        # no channel travels: each process opens its own
        state = dict(self.__dict__)
        state.update(_client=None, _pid=None, _prefer=None)
        return state

    def __repr__(self) -> str:
        return (
            f"MPIFlowMapDataset({self.addresses!r}, {self.length}, seed={self.seed}, "
            f"dataset={self.dataset!r}, start_index={self.start_index}, fields={self.fields})"
        )


def _build_class():
    return dataset_class(_MPIFlowMapDatasetImpl, "MPIFlowMapDataset", __name__, "Dataset")


def __getattr__(name: str):
    # Lazily: torch is imported only when the dataset class is first used.
    if name == "MPIFlowMapDataset":
        cls = _build_class()
        globals()["MPIFlowMapDataset"] = cls
        return cls
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
