#!/usr/bin/env python3
"""Pulls a few samples from an mpiflow server into numpy (no torch) and saves them.

    python examples/pull_numpy.py --addr 127.0.0.1:50051 --count 4 --out out/pull_numpy

Writes, per sample I (the global index, 8 digits): I_img1.png, I_img2.png, I_flow.npy
(float32 [H, W, 2]), I_valid.png, and preview.png (one row per sample: image1 | image2 | flow
colour | valid). PNGs are written with the standard library only.
"""
from __future__ import annotations

import argparse
import struct
import sys
import time
import zlib
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "clients" / "python"))  # run from the repo without installing
import mpiflow  # noqa: E402


def write_png(path: Path, img: np.ndarray) -> None:
    """8-bit grey [H, W] or RGB [H, W, 3] PNG, stdlib only."""
    img = np.ascontiguousarray(img, dtype=np.uint8)
    h, w = img.shape[:2]
    color = 2 if img.ndim == 3 else 0
    rows = img.reshape(h, -1)
    raw = b"".join(b"\x00" + rows[y].tobytes() for y in range(h))

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))

    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, color, 0, 0, 0))
    png += chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b"")
    path.write_bytes(png)


def flow_to_rgb(flow: np.ndarray, max_mag: float | None = None) -> np.ndarray:
    """Flow [H, W, 2] as colour: hue = direction, saturation = magnitude (white = still)."""
    u, v = flow[..., 0].astype(np.float32), flow[..., 1].astype(np.float32)
    mag = np.hypot(u, v)
    max_mag = max_mag or max(float(np.percentile(mag, 99)), 1e-6)
    hue = (np.arctan2(-v, -u) / np.pi + 1.0) / 2.0  # 0..1
    sat = np.clip(mag / max_mag, 0, 1)
    # HSV (value 1) -> RGB
    h6 = hue * 6.0
    i = np.floor(h6).astype(int) % 6
    f = h6 - np.floor(h6)
    p, q, t = 1 - sat, 1 - sat * f, 1 - sat * (1 - f)
    one = np.ones_like(sat)
    r = np.choose(i, [one, q, p, p, t, one])
    g = np.choose(i, [t, one, one, q, p, p])
    b = np.choose(i, [p, p, t, one, one, q])
    return (np.stack([r, g, b], -1) * 255).astype(np.uint8)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--addr", default="127.0.0.1:50051", help="server address(es), comma-separated")
    ap.add_argument("--count", type=int, default=4)
    ap.add_argument("--start-index", type=int, default=0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--crop", default=None, help="WxH, e.g. 320x240")
    ap.add_argument("--lz4", action="store_true")
    ap.add_argument("--out", default="out/pull_numpy")
    a = ap.parse_args()
    crop = tuple(int(v) for v in a.crop.lower().split("x")) if a.crop else None
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)

    with mpiflow.Client(a.addr, timeout=120) as client:
        info = client.info()
        default = next((d for d in info.datasets if d.is_default), None)
        print(f"server {info.version}: datasets {[d.name for d in info.datasets]}"
              + (f", default {default.name} ({default.sources} sources, fingerprint {default.fingerprint:016x})" if default else ""))
        rows = []
        t0 = time.perf_counter()
        for s in client.stream(count=a.count, start_index=a.start_index, seed=a.seed, crop=crop, lz4=a.lz4):
            stem = f"{s.index:08d}"
            write_png(out / f"{stem}_img1.png", s["image1"])
            write_png(out / f"{stem}_img2.png", s["image2"])
            np.save(out / f"{stem}_flow.npy", s["flow"])
            write_png(out / f"{stem}_valid.png", s["valid"] * 255)
            valid = np.repeat((s["valid"] * 255)[..., None], 3, -1)
            rows.append(np.concatenate([s["image1"], s["image2"], flow_to_rgb(s["flow"]), valid], 1))
            fl = s["flow"][s["valid"] > 0]
            mag = float(np.hypot(fl[:, 0], fl[:, 1]).mean()) if fl.size else 0.0
            print(f"sample {s.index}: {s.width}x{s.height} from {s.source_id}, valid "
                  f"{s['valid'].mean():.1%}, mean |flow| {mag:.2f} px")
        dt = time.perf_counter() - t0
    write_png(out / "preview.png", np.concatenate(rows, 0))
    print(f"{len(rows)} samples in {dt:.2f} s ({len(rows) / dt:.2f} samples/s); wrote {out}/ and {out}/preview.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
