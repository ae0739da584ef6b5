"""Optical-flow helpers next to torchvision's: `flow_to_image` (the Middlebury colour wheel, as
PyPI `flow-vis` and RAFT's `flow_viz.py` draw it) and the Middlebury `.flo` file format
(`read_flo`, `write_flo`, as RAFT's `frame_utils` and the server's `pull --out` read and write it).
"""
from __future__ import annotations

import os
from typing import Optional, Union

import numpy as np

#: The `.flo` magic number: the float32 202021.25, the bytes "PIEH" in little-endian order.
FLO_MAGIC = 202021.25

#: Hues per segment of the wheel: red-yellow, yellow-green, green-cyan, cyan-blue, blue-magenta,
#: magenta-red.
_SEGMENTS = (15, 6, 4, 11, 13, 6)


def make_colorwheel() -> np.ndarray:
    """The 55 x 3 palette of the Middlebury wheel (float64 RGB values 0..255), as `flow-vis`."""
    ry, yg, gc, cb, bm, mr = _SEGMENTS
    wheel = np.zeros((sum(_SEGMENTS), 3))
    col = 0
    for n, fixed, rising, falling in (
        (ry, 0, 1, None), (yg, 1, None, 0), (gc, 1, 2, None), (cb, 2, None, 1), (bm, 2, 0, None), (mr, 0, None, 2),
    ):
        ramp = np.floor(255 * np.arange(n) / n)
        wheel[col:col + n, fixed] = 255
        if rising is not None:
            wheel[col:col + n, rising] = ramp
        if falling is not None:
            wheel[col:col + n, falling] = 255 - ramp
        col += n
    return wheel


def flow_uv_to_colors(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Colours (uint8 [..., 3]) of flow components already normalised so that magnitude 1 is the
    wheel's rim; magnitudes above 1 at 75% brightness; a non-finite vector is black."""
    wheel = make_colorwheel()
    ncols = wheel.shape[0]
    finite = np.isfinite(u) & np.isfinite(v)
    u = np.where(finite, u, 0)
    v = np.where(finite, v, 0)
    rad = np.sqrt(np.square(u) + np.square(v))
    a = np.arctan2(-v, -u) / np.pi
    fk = (a + 1) / 2 * (ncols - 1)
    k0 = np.floor(fk).astype(np.int32)
    k1 = k0 + 1
    k1[k1 == ncols] = 0
    f = fk - k0
    out = np.zeros(u.shape + (3,), np.uint8)
    for i in range(3):
        col0 = wheel[k0, i] / 255.0
        col1 = wheel[k1, i] / 255.0
        col = (1 - f) * col0 + f * col1
        inside = rad <= 1
        col[inside] = 1 - rad[inside] * (1 - col[inside])
        col[~inside] = col[~inside] * 0.75
        out[..., i] = np.where(finite, np.floor(255 * col), 0)
    return out


def flow_to_image(flow: np.ndarray, max_flow: Optional[float] = None) -> np.ndarray:
    """Draws a flow as an RGB uint8 image with the Middlebury colour wheel.

    `flow` is [H, W, 2] (as `Client` gives `sample["flow"]`; returns [H, W, 3]) or [2, H, W]
    (as `to_raft_dict` and torchvision give it; returns [3, H, W]). The flow is divided by
    `max_flow`, default the largest finite magnitude plus 1e-5 (as `flow-vis`'s `flow_to_color`
    and torchvision's `flow_to_image` normalise), so the fastest pixel is fully saturated.
    """
    flow = np.asarray(flow)
    channels_first = flow.ndim == 3 and flow.shape[0] == 2 and flow.shape[-1] != 2
    if channels_first:
        flow = np.moveaxis(flow, 0, -1)
    if flow.ndim != 3 or flow.shape[-1] != 2:
        raise ValueError(f"flow_to_image: expected a [H, W, 2] or [2, H, W] flow, got shape {flow.shape}")
    u, v = flow[..., 0], flow[..., 1]
    if max_flow is None:
        rad = np.sqrt(np.square(u) + np.square(v))
        finite = rad[np.isfinite(rad)]
        max_flow = (float(finite.max()) if finite.size else 0.0) + 1e-5
    elif not max_flow > 0:
        raise ValueError(f"flow_to_image: max_flow must be positive, got {max_flow}")
    scale = np.asarray(max_flow, dtype=flow.dtype)
    image = flow_uv_to_colors(u / scale, v / scale)
    return np.moveaxis(image, -1, 0) if channels_first else image


PathLike = Union[str, "os.PathLike[str]"]


def write_flo(path: PathLike, flow: np.ndarray) -> None:
    """Writes a [H, W, 2] (or [2, H, W]) flow as a Middlebury `.flo` file: the magic, int32
    width and height, then H x W x (u, v) float32, little-endian."""
    flow = np.asarray(flow)
    if flow.ndim == 3 and flow.shape[0] == 2 and flow.shape[-1] != 2:
        flow = np.moveaxis(flow, 0, -1)
    if flow.ndim != 3 or flow.shape[-1] != 2:
        raise ValueError(f"write_flo: expected a [H, W, 2] or [2, H, W] flow, got shape {flow.shape}")
    h, w = flow.shape[:2]
    with open(path, "wb") as f:
        f.write(np.array([FLO_MAGIC], "<f4").tobytes())
        f.write(np.array([w, h], "<i4").tobytes())
        f.write(np.ascontiguousarray(flow, dtype="<f4").tobytes())


def read_flo(path: PathLike) -> np.ndarray:
    """Reads a Middlebury `.flo` file as a float32 [H, W, 2] flow; a wrong magic, a size that
    does not match the data, or a truncated file is a ValueError naming the file."""
    with open(path, "rb") as f:
        data = f.read()
    if len(data) < 12:
        raise ValueError(f"{path}: not a .flo file: {len(data)} bytes, shorter than its 12-byte header")
    magic = np.frombuffer(data[:4], "<f4")[0]
    if magic != np.float32(FLO_MAGIC):
        raise ValueError(f"{path}: not a .flo file: magic {magic!r}, expected {FLO_MAGIC} ('PIEH')")
    w, h = (int(x) for x in np.frombuffer(data[4:12], "<i4"))
    if w < 0 or h < 0:
        raise ValueError(f"{path}: .flo size {w} x {h} is negative")
    need = 12 + 8 * w * h
    if len(data) != need:
        raise ValueError(f"{path}: a {w} x {h} .flo file holds {need} bytes, this one {len(data)}")
    return np.frombuffer(data[12:], "<f4").reshape(h, w, 2).astype(np.float32)
