"""Decoding of mpiflow tensors and samples into numpy arrays, and the RAFT-style sample dict.

Tensors travel raw (little-endian, C order) or lz4-compressed (block format with the
uncompressed size prepended as u32 LE, which `lz4.block.decompress` reads as is). Decoding
wraps the received (or decompressed) bytes with `np.frombuffer`: no copy is made, and the
arrays of an uncompressed tensor are read-only views of the message's bytes.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, Iterable, List, Optional, Sequence, Tuple, Union

import numpy as np

from ._proto import mpiflow_pb2 as pb

__all__ = [
    "DEFAULT_FIELDS",
    "CLIP_NAMES",
    "DecodeError",
    "Sample",
    "decode_sample",
    "decode_tensor",
    "parse_fields",
    "field_name",
    "is_motions",
    "to_raft_dict",
]


class DecodeError(ValueError):
    """A tensor whose bytes do not match its declared shape, dtype or compression."""


_DTYPES = {
    pb.DTYPE_U8: np.dtype("u1"),
    pb.DTYPE_F16: np.dtype("<f2"),
    pb.DTYPE_F32: np.dtype("<f4"),
}

# Field enum <-> tensor name (Tensor.name on the wire).
_FIELD_NAMES = {
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
    pb.FIELD_FLOW_BACKWARD: "flow_backward",
    pb.FIELD_VALID_BACKWARD: "valid_backward",
    pb.FIELD_OCCLUSION_BACKWARD: "occlusion_backward",
    pb.FIELD_DISPARITY: "disparity",
}
_NAME_FIELDS = {v: k for k, v in _FIELD_NAMES.items()}
_ALIASES = {
    "img1": "image1",
    "img2": "image2",
    "occ": "occlusion",
    "flow_bw": "flow_backward",
    "valid_bw": "valid_backward",
    "occ_bw": "occlusion_backward",
}

# A clip (frames > 2) carries stacked tensors under these names instead (docs/outputs.md):
# images [K, H, W, 3], flows / flows_backward [K-1, H, W, 2], valids, occlusions,
# valids_backward, occlusions_backward [K-1, H, W]; the other fields are the first pair's.
CLIP_NAMES = {
    "image1": "images",
    "image2": "images",
    "flow": "flows",
    "valid": "valids",
    "occlusion": "occlusions",
    "flow_backward": "flows_backward",
    "valid_backward": "valids_backward",
    "occlusion_backward": "occlusions_backward",
}

DEFAULT_FIELDS: Tuple[str, ...] = ("image1", "image2", "flow", "valid")


def field_name(f: Union[int, str]) -> str:
    """The tensor name of a Field (enum value or name, e.g. 3, "FIELD_FLOW", "flow", "img1")."""
    if isinstance(f, str):
        key = f.strip().lower()
        if key.startswith("field_"):
            key = key[len("field_"):]
        key = _ALIASES.get(key, key)
        if key not in _NAME_FIELDS:
            raise ValueError(f"unknown field {f!r}; known: {', '.join(_NAME_FIELDS)}")
        return key
    if int(f) not in _FIELD_NAMES:
        raise ValueError(f"unknown field value {f!r}")
    return _FIELD_NAMES[int(f)]


# Not a tensor: every sample carries its camera and object motions; the name asks the dataset
# dicts to include them (accepted, and sent as nothing, by every entry point).
MOTIONS = "motions"


def is_motions(f: Union[int, str]) -> bool:
    """Whether a field name is "motions" (the motions every sample carries, not a tensor)."""
    return isinstance(f, str) and f.strip().lower() == MOTIONS


def parse_fields(fields: Optional[Iterable[Union[int, str]]]) -> List[int]:
    """Field enum values for a request; None = the server's defaults (an empty list). The name
    "motions" is accepted and adds nothing (the motions travel with every sample)."""
    if fields is None:
        return []
    if isinstance(fields, (str, int)):
        fields = [fields]
    out: List[int] = []
    for f in fields:
        if is_motions(f):
            continue
        v = _NAME_FIELDS[field_name(f)]
        if v not in out:
            out.append(v)
    return out


def decode_tensor(t: "pb.Tensor") -> np.ndarray:
    """A numpy array over the tensor's bytes (decompressed first when lz4), without a copy."""
    data = t.data
    if t.compression == pb.COMPRESSION_LZ4:
        import lz4.block

        try:
            data = lz4.block.decompress(data)
        except Exception as e:  # lz4.block.LZ4BlockError and size-prefix errors
            raise DecodeError(f"tensor {t.name!r}: lz4 decompression failed: {e}") from e
    elif t.compression not in (pb.COMPRESSION_UNSPECIFIED, pb.COMPRESSION_NONE):
        raise DecodeError(f"tensor {t.name!r}: unknown compression {t.compression}")
    try:
        dtype = _DTYPES[t.dtype]
    except KeyError:
        raise DecodeError(f"tensor {t.name!r}: unknown dtype {t.dtype}") from None
    shape = tuple(int(s) for s in t.shape)
    expected = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if len(data) != expected:
        raise DecodeError(
            f"tensor {t.name!r}: {len(data)} bytes for shape {list(shape)} {dtype} "
            f"(expected {expected})"
        )
    if t.raw_size and t.raw_size != expected:
        raise DecodeError(f"tensor {t.name!r}: raw_size {t.raw_size} != {expected}")
    return np.frombuffer(data, dtype=dtype).reshape(shape)


@dataclass
class Sample:
    """A decoded sample: its address, its tensors as numpy arrays and its metadata.

    `sample["flow"]` is `sample.tensors["flow"]`. `camera`, `objects`, `intrinsics` and `timings`
    are the protobuf messages as received (see proto/mpiflow/v1/mpiflow.proto).
    """

    index: int
    dataset: str
    fingerprint: int
    seed: int
    source_id: str
    width: int
    height: int
    tensors: Dict[str, np.ndarray]
    camera: Any = None
    objects: Sequence[Any] = field(default_factory=list)
    intrinsics: Any = None
    timings: Any = None
    skipped_sources: int = 0
    # what the server-side augmentation applied (the Sample's `augment` JSON); empty without it
    augment: str = ""
    # frames held: 2 = a pair, more = a clip with stacked tensors (CLIP_NAMES)
    frames: int = 2

    def __getitem__(self, name: str) -> np.ndarray:
        return self.tensors[name]

    def __contains__(self, name: object) -> bool:
        return name in self.tensors

    def keys(self):
        return self.tensors.keys()


def decode_sample(s: "pb.Sample") -> Sample:
    """Decodes every tensor of a Sample message (see decode_tensor)."""
    return Sample(
        index=s.index,
        dataset=s.dataset,
        fingerprint=s.fingerprint,
        seed=s.seed,
        source_id=s.source_id,
        width=s.width,
        height=s.height,
        tensors={t.name: decode_tensor(t) for t in s.tensors},
        camera=s.camera if s.HasField("camera") else None,
        objects=list(s.objects),
        intrinsics=s.intrinsics if s.HasField("intrinsics") else None,
        timings=s.timings if s.HasField("timings") else None,
        skipped_sources=s.skipped_sources,
        augment=s.augment,
        frames=max(2, int(s.frames)),
    )


def _motion_arrays(m: Any) -> Dict[str, np.ndarray]:
    rot = np.asarray(list(m.rotation), dtype=np.float64) if m is not None else np.zeros(0)
    return {
        "rotation": rot.reshape(3, 3) if rot.size == 9 else np.eye(3),
        "translation": _vec3(m.translation if m is not None else ()),
        "axis_angle": _vec3(m.axis_angle if m is not None else ()),
    }


def _vec3(v: Sequence[float]) -> np.ndarray:
    a = np.zeros(3, dtype=np.float64)
    vals = list(v)[:3]
    a[: len(vals)] = vals
    return a


def to_raft_dict(
    s: Sample,
    *,
    next_index: Optional[int] = None,
    motions: bool = False,
    pad_objects: int = 8,
) -> Dict[str, Any]:
    """The dict RAFT's FlowDataset yields, from a decoded sample.

    `img1`, `img2`: float32 [3, H, W] in 0..255; `flow`: float32 [2, H, W]; `valid`: float32
    [H, W] (the server's mask, or RAFT's |flow| < 1000 rule when it was not requested);
    `index`; `next_index` (this consumer's cursor after the sample, when given); `occlusion`
    float32 [H, W], `mask1`/`mask2` uint8 [H, W], `depth1`/`depth2` float32 [H, W], `holes`
    float32 [H, W] (1 = image2 filled by 2-D inpainting) and `disparity` float32 [H, W] (stereo
    pairs: d = x1 - x2 >= 0, the flow is (-d, 0) as RAFT-Stereo's datasets make it) when requested; with `motions`: `camera` {rotation [3,3], translation [3], axis_angle [3]},
    `intrinsics` [fx, fy, cx, cy] and `objects` padded to `pad_objects` entries (label 0 = none)
    so that torch's default collate can stack them. Every array is new and writable.
    """
    t = s.tensors
    out: Dict[str, Any] = {}
    for src, dst in (("image1", "img1"), ("image2", "img2")):
        if src in t:
            a = t[src]
            if a.ndim == 2:
                a = a[:, :, None]
            # One pass: HWC u8 -> CHW f32 (the cast writes the transposed copy).
            out[dst] = np.ascontiguousarray(a.transpose(2, 0, 1), dtype=np.float32)
    if "flow" in t:
        out["flow"] = np.ascontiguousarray(t["flow"].transpose(2, 0, 1), dtype=np.float32)
    if "valid" in t:
        out["valid"] = t["valid"].astype(np.float32)
    elif "flow" in out:
        f = out["flow"]
        out["valid"] = ((np.abs(f[0]) < 1000) & (np.abs(f[1]) < 1000)).astype(np.float32)
    if "occlusion" in t:
        out["occlusion"] = t["occlusion"].astype(np.float32)
    if "holes" in t:
        out["holes"] = t["holes"].astype(np.float32)
    if "disparity" in t:
        out["disparity"] = t["disparity"].astype(np.float32)
    for name in ("mask1", "mask2"):
        if name in t:
            out[name] = t[name].copy()
    for name in ("depth1", "depth2"):
        if name in t:
            out[name] = t[name].astype(np.float32)
    out["index"] = int(s.index)
    if next_index is not None:
        out["next_index"] = int(next_index)
    if motions:
        out["camera"] = _motion_arrays(s.camera)
        k = s.intrinsics
        out["intrinsics"] = np.array(
            [k.fx, k.fy, k.cx, k.cy] if k is not None else [0.0] * 4, dtype=np.float64
        )
        n = len(s.objects)
        if n > pad_objects:
            raise ValueError(
                f"sample {s.index} has {n} moving objects, more than pad_objects={pad_objects}"
            )
        objs = {
            "label": np.zeros(pad_objects, dtype=np.int64),
            "instance": np.zeros(pad_objects, dtype=np.int64),
            "score": np.zeros(pad_objects, dtype=np.float32),
            "area": np.zeros(pad_objects, dtype=np.float64),
            "rotation": np.tile(np.eye(3), (pad_objects, 1, 1)),
            "translation": np.zeros((pad_objects, 3), dtype=np.float64),
            "axis_angle": np.zeros((pad_objects, 3), dtype=np.float64),
        }
        for i, o in enumerate(s.objects):
            objs["label"][i] = o.label
            objs["instance"][i] = o.instance
            objs["score"][i] = o.score
            objs["area"][i] = o.area
            m = _motion_arrays(o.motion if o.HasField("motion") else None)
            objs["rotation"][i] = m["rotation"]
            objs["translation"][i] = m["translation"]
            objs["axis_angle"][i] = m["axis_angle"]
        out["objects"] = objs
        out["num_objects"] = n
    return out
