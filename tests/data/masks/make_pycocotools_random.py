"""Writes pycocotools_random.json: random masks and polygons with pycocotools' results, used by
tests/samples/masks.rs to check the RLE codec, area, bbox and polygon rasterisation bit for bit.

Run with numpy and pycocotools installed (used: pycocotools 2.0.11):
    python make_pycocotools_random.py
Masks are stored as strings of '0'/'1', row-major (row after row).
"""
import json

import numpy as np
import pycocotools.mask as mu

rng = np.random.default_rng(1)
out = {"source": "pycocotools 2.0.11 (maskApi.c) via make_pycocotools_random.py", "masks": [], "polygons": []}
for i in range(80):
    h, w = int(rng.integers(1, 14)), int(rng.integers(1, 14))
    m = (rng.random((h, w)) < rng.random()).astype(np.uint8)
    if i % 5 == 0:  # one rectangle
        m = np.zeros((h, w), np.uint8)
        y0, x0 = rng.integers(0, h), rng.integers(0, w)
        m[y0:y0 + int(rng.integers(1, 8)), x0:x0 + int(rng.integers(1, 8))] = 1
    r = mu.encode(np.asfortranarray(m))
    out["masks"].append({"h": h, "w": w, "mask": "".join(map(str, m.ravel())), "counts": r["counts"].decode(),
                         "area": int(mu.area(r)), "bbox": mu.toBbox(r).tolist()})
for i in range(150):
    h, w = int(rng.integers(1, 24)), int(rng.integers(1, 24))
    polys = []
    for _ in range(int(rng.integers(1, 3))):
        k = int(rng.integers(3, 8))
        span = 1.4 if i % 3 else 1.0  # some vertices outside the image
        xs, ys = rng.uniform(-0.2 * w, span * w, k), rng.uniform(-0.2 * h, span * h, k)
        if i % 4 == 0:  # half-pixel coordinates
            xs, ys = np.round(xs * 2) / 2, np.round(ys * 2) / 2
        poly = np.stack([xs, ys], 1).ravel()
        if i % 7 == 0 and k > 3:  # a repeated vertex
            poly[2:4] = poly[0:2]
        polys.append([round(float(v), 3) for v in poly])
    rles = mu.frPyObjects(polys, h, w)
    out["polygons"].append({"h": h, "w": w, "polygons": polys, "each": [r["counts"].decode() for r in rles],
                            "merged": mu.merge(rles)["counts"].decode()})
with open("pycocotools_random.json", "w") as f:
    json.dump(out, f, separators=(",", ":"))
