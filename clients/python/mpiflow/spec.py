"""The SampleSpec of a request from keyword arguments: the sample options that StreamRequest,
SampleRequest and SamplesRequest share."""
from __future__ import annotations

import json
from typing import Any, Dict, Iterable, Optional, Union

from ._proto import mpiflow_pb2 as pb
from .decode import parse_fields

__all__ = ["build_spec"]


def _crop(crop: Any, mode: Union[str, int, None]) -> Optional["pb.OutputCrop"]:
    if crop is None:
        return None
    if isinstance(crop, pb.OutputCrop):
        return crop
    if isinstance(crop, int):
        w = h = crop
    else:
        w, h = (int(v) for v in crop)
    if isinstance(mode, str) or mode is None:
        modes = {None: pb.CROP_MODE_CENTER, "center": pb.CROP_MODE_CENTER, "random": pb.CROP_MODE_RANDOM}
        key = mode.lower() if isinstance(mode, str) else None
        if key not in modes:
            raise ValueError(f"crop_mode must be 'center' or 'random', not {mode!r}")
        mode = modes[key]
    return pb.OutputCrop(width=w, height=h, mode=mode)


def _augment(v: Any) -> str:
    """The request's `augment`: a preset name or JSON text as is, a dict as JSON (docs/augment.md)."""
    if v is None:
        return ""
    if isinstance(v, dict):
        return json.dumps(v, sort_keys=True)
    if isinstance(v, str):
        return v
    raise TypeError(f"augment must be a preset name, JSON text or a dict, not {type(v).__name__}")


def _flow_dtype(v: Union[str, int, None]) -> int:
    if v is None:
        return pb.FLOW_DTYPE_F32
    if isinstance(v, int):
        return v
    key = str(v).lower().replace("float", "f")
    if key in ("f32", "32"):
        return pb.FLOW_DTYPE_F32
    if key in ("f16", "16", "half"):
        return pb.FLOW_DTYPE_F16
    raise ValueError(f"flow_dtype must be 'f32' or 'f16', not {v!r}")


def build_spec(
    *,
    dataset: Optional[str] = None,
    fingerprint: int = 0,
    seed: int = 0,
    fields: Optional[Iterable[Union[int, str]]] = None,
    lz4: bool = False,
    flow_dtype: Union[str, int, None] = None,
    crop: Any = None,
    crop_mode: Union[str, int, None] = None,
    motion_preset: Optional[str] = None,
    motion_ranges_json: Optional[str] = None,
    max_objects: Optional[int] = None,
    motions_per_image: Optional[int] = None,
    augment: Any = None,
    frames: Optional[int] = None,
    resample: Optional[str] = None,
) -> "pb.SampleSpec":
    """The SampleSpec of a request: the sample options StreamRequest, SampleRequest and
    SamplesRequest share. `frames` = K (2 to 8): K > 2 asks for a clip (stacked tensors, see
    decode.CLIP_NAMES)."""
    kw: Dict[str, Any] = dict(
        dataset=dataset or "",
        fingerprint=int(fingerprint or 0),
        seed=int(seed),
        fields=parse_fields(fields),
        flow_dtype=_flow_dtype(flow_dtype),
        compression=pb.COMPRESSION_LZ4 if lz4 else pb.COMPRESSION_NONE,
        motion_preset=motion_preset or "",
        motion_ranges_json=motion_ranges_json or "",
        augment=_augment(augment),
        resample=resample or "",
    )
    c = _crop(crop, crop_mode)
    if c is not None:
        kw["crop"] = c
    if max_objects is not None:
        kw["max_objects"] = int(max_objects)
    if motions_per_image is not None:
        kw["motions_per_image"] = int(motions_per_image)
    if frames is not None:
        kw["frames"] = int(frames)
    return pb.SampleSpec(**kw)
