#!/usr/bin/env python3
"""Writes a folder of RGB-D photos of mixed sizes in the reference layout (images/, depths/,
masks/), made from the repository's real RGB-D photos (tests/data/rgbd: Cones and Chelsea) by
cropping, flipping and resizing: what a user's folder of phone and camera photos with depth looks
like to mpiflow, for the folder benchmarks (docs/performance.md).

    python tools/make_rgbd_folder.py OUTDIR [--count 48] [--largest 4032x3024] [--sources cones]
                                            [--no-masks] [--blur PX]

Every photo is a random crop (at least half of each side) of one source, flipped at random,
resized to one of the sizes below (the largest is --largest); its depth and mask follow it. The
depth is resized bilinearly over its known pixels (unknown ones, NaN or <= 0, stay out of every
blend and stay unknown where no known pixel is near), as a depth network's output is smooth
across edges; `--blur PX` also blurs it by a Gaussian of PX pixels (at the photo's final size),
a network's soft edges. Masks are resized by nearest neighbour. Deterministic: the same arguments
write the same files. Needs numpy and pillow.
"""

import argparse
import os

import numpy as np
from PIL import Image

HERE = os.path.dirname(os.path.abspath(__file__))
RGBD = os.path.join(HERE, "..", "tests", "data", "rgbd")
SIZES = [(640, 480), (800, 600), (1024, 768), (1280, 720), (1920, 1080), (1600, 1200), (768, 1024)]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out")
    ap.add_argument("--count", type=int, default=48)
    ap.add_argument("--largest", default="4032x3024", help="WxH of the largest photos (every 8th photo)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sources", default="cones,chelsea", help="the photos of tests/data/rgbd to crop, in turn")
    ap.add_argument("--no-masks", action="store_true", help="write no masks/ (the photos have no objects)")
    ap.add_argument("--blur", type=float, default=0.0, help="blur each depth by a Gaussian of this sigma in pixels")
    a = ap.parse_args()
    lw, lh = (int(v) for v in a.largest.lower().split("x"))
    rng = np.random.default_rng(a.seed)
    sources = []
    for name in a.sources.split(","):
        img = np.asarray(Image.open(os.path.join(RGBD, name, "images", name + ".png")).convert("RGB"))
        depth = np.load(os.path.join(RGBD, name, "depths", name + ".npy")).astype(np.float32)
        mask = np.asarray(Image.open(os.path.join(RGBD, name, "masks", name + ".png")))
        sources.append((name, img, depth, mask))
    for sub in ("images", "depths") if a.no_masks else ("images", "depths", "masks"):
        os.makedirs(os.path.join(a.out, sub), exist_ok=True)
    for i in range(a.count):
        name, img, depth, mask = sources[i % len(sources)]
        h, w = depth.shape
        cw, ch = int(rng.integers(w // 2, w + 1)), int(rng.integers(h // 2, h + 1))
        x0, y0 = int(rng.integers(0, w - cw + 1)), int(rng.integers(0, h - ch + 1))
        im, de, ma = img[y0 : y0 + ch, x0 : x0 + cw], depth[y0 : y0 + ch, x0 : x0 + cw], mask[y0 : y0 + ch, x0 : x0 + cw]
        if rng.random() < 0.5:
            im, de, ma = im[:, ::-1], de[:, ::-1], ma[:, ::-1]
        size = (lw, lh) if i % 8 == 7 else SIZES[int(rng.integers(0, len(SIZES)))]
        stem = f"{name}-{i:03d}"
        Image.fromarray(np.ascontiguousarray(im)).resize(size, Image.BICUBIC).save(
            os.path.join(a.out, "images", stem + ".jpg"), quality=92
        )
        de = smooth_depth(np.ascontiguousarray(de), size, a.blur)
        np.save(os.path.join(a.out, "depths", stem + ".npy"), de)
        if not a.no_masks:
            ma = Image.fromarray(np.ascontiguousarray(ma)).resize(size, Image.NEAREST)
            ma.save(os.path.join(a.out, "masks", stem + ".png"))
    print(f"{a.count} photos in {a.out} (largest {lw}x{lh})")


def smooth_depth(depth, size, blur):
    """`depth` resized bilinearly to `size` (W, H) over its known pixels, then blurred by a
    Gaussian of `blur` pixels (0: none); both normalised by the known pixels' weight, so unknown
    pixels never pull a known depth; NaN where no known pixel contributes."""
    known = (np.isfinite(depth) & (depth > 0)).astype(np.float32)
    vals = np.where(known > 0, depth, 0).astype(np.float32)

    def resize(x):
        return np.asarray(Image.fromarray(x).resize(size, Image.BILINEAR), dtype=np.float32)

    num, den = resize(vals * known), resize(known)
    if blur > 0:
        r = int(np.ceil(3 * blur))
        k = np.exp(-0.5 * (np.arange(-r, r + 1) / blur) ** 2).astype(np.float32)
        k /= k.sum()

        def conv(x):
            x = np.apply_along_axis(lambda v: np.convolve(np.pad(v, r, mode="edge"), k, "valid"), 0, x)
            return np.apply_along_axis(lambda v: np.convolve(np.pad(v, r, mode="edge"), k, "valid"), 1, x)

        num, den = conv(num), conv(den)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 1e-3, num / np.maximum(den, 1e-12), np.nan).astype(np.float32)


if __name__ == "__main__":
    main()
