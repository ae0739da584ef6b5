"""Python client of mpiflow: optical-flow training samples streamed from an mpiflow server.

    from mpiflow import Client, MPIFlowDataset
    client = Client("127.0.0.1:50051")            # waits for health SERVING
    s = client.get_sample(0, seed=0)              # s["image1"] u8 [H, W, 3], s["flow"] f32 [H, W, 2]
    for s in client.stream(count=10): ...         # one consumer's stream, with failover
    ds = MPIFlowDataset("127.0.0.1:50051")        # RAFT-style dicts; torch IterableDataset
    ss = client.get_samples([7, 3, 7])            # random access, one call, in that order
    mds = MPIFlowMapDataset("127.0.0.1:50051", 1000)  # ds[i] = sample i; torch map-style Dataset
    rgb = flow_to_image(s["flow"])                # the Middlebury colour wheel, u8 [H, W, 3]
    write_flo("0.flo", s["flow"]); read_flo("0.flo")  # Middlebury .flo files, as RAFT reads them

`MPIFlowDataset` and `MPIFlowMapDataset` import torch (when installed) on first use only.
"""
from ._proto import mpiflow_pb2 as pb
from .client import Client, parse_addresses
from .decode import DEFAULT_FIELDS, DecodeError, Sample, decode_sample, decode_tensor, to_raft_dict
from .errors import MpiFlowError, NotReadyError, is_retryable
from .flow import flow_to_image, read_flo, write_flo
from .stream import FlowStream, Prefetcher, ProtocolError, StreamFailed

__version__ = "0.1.0"

__all__ = [
    "Client",
    "DEFAULT_FIELDS",
    "DecodeError",
    "FlowStream",
    "MPIFlowDataset",
    "MPIFlowMapDataset",
    "MpiFlowError",
    "NotReadyError",
    "Prefetcher",
    "ProtocolError",
    "Sample",
    "StreamFailed",
    "decode_sample",
    "decode_tensor",
    "flow_to_image",
    "is_retryable",
    "parse_addresses",
    "pb",
    "read_flo",
    "to_raft_dict",
    "write_flo",
]


def __getattr__(name):
    if name == "MPIFlowDataset":
        from . import dataset

        return dataset.MPIFlowDataset
    if name == "MPIFlowMapDataset":
        from . import map_dataset

        return map_dataset.MPIFlowMapDataset
    raise AttributeError(f"module 'mpiflow' has no attribute {name!r}")
