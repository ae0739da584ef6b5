#!/usr/bin/env python3
"""What server-side augmentation saves a trainer: the CPU time of RAFT's FlowAugmentor (the
`raft-chairs` stage: crop 368x496, scale -0.1..1.0, flips) in Python on a sample from the server,
against the same augmentation made by the server (docs/augment.md).

RAFT's augmentor needs cv2, PIL and torchvision; this is the same algorithm (core/utils/
augmentor.py, FlowAugmentor.__call__: colour jitter, eraser, resize + stretch, flips, crop) with
numpy and PIL only: PIL's ImageEnhance in a random order and the HSV hue shift for ColorJitter
(what torchvision does on PIL images), PIL's bilinear resize for the images and for each flow
channel (mode F) in place of cv2.resize. Timed per call on one thread, after one warm-up call.

    python clients/python/bench_augment.py --address 127.0.0.1:50051 --runs 20
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
from PIL import Image, ImageEnhance

import mpiflow


class FlowAugmentor:
    """RAFT's FlowAugmentor (dense), numpy + PIL."""

    def __init__(self, crop_size, min_scale=-0.2, max_scale=0.5, do_flip=True):
        self.crop_size = crop_size
        self.min_scale, self.max_scale = min_scale, max_scale
        self.spatial_aug_prob, self.stretch_prob, self.max_stretch = 0.8, 0.8, 0.2
        self.do_flip, self.h_flip_prob, self.v_flip_prob = do_flip, 0.5, 0.1
        self.jitter = dict(brightness=0.4, contrast=0.4, saturation=0.4, hue=0.5 / 3.14)
        self.asymmetric_color_aug_prob, self.eraser_aug_prob = 0.2, 0.5

    def photo_aug(self, img: Image.Image) -> Image.Image:
        j = self.jitter
        for op in np.random.permutation(4):
            if op == 0:
                img = ImageEnhance.Brightness(img).enhance(np.random.uniform(1 - j["brightness"], 1 + j["brightness"]))
            elif op == 1:
                img = ImageEnhance.Contrast(img).enhance(np.random.uniform(1 - j["contrast"], 1 + j["contrast"]))
            elif op == 2:
                img = ImageEnhance.Color(img).enhance(np.random.uniform(1 - j["saturation"], 1 + j["saturation"]))
            else:
                h, s, v = img.convert("HSV").split()
                shift = np.uint8(int(np.random.uniform(-j["hue"], j["hue"]) * 255) % 256)
                h = Image.fromarray((np.asarray(h, dtype=np.uint8) + shift).astype(np.uint8), "L")
                img = Image.merge("HSV", (h, s, v)).convert("RGB")
        return img

    def color_transform(self, img1, img2):
        if np.random.rand() < self.asymmetric_color_aug_prob:
            img1 = np.array(self.photo_aug(Image.fromarray(img1)), dtype=np.uint8)
            img2 = np.array(self.photo_aug(Image.fromarray(img2)), dtype=np.uint8)
        else:
            stack = np.concatenate([img1, img2], axis=0)
            stack = np.array(self.photo_aug(Image.fromarray(stack)), dtype=np.uint8)
            img1, img2 = np.split(stack, 2, axis=0)
        return img1, img2

    def eraser_transform(self, img1, img2, bounds=(50, 100)):
        ht, wd = img1.shape[:2]
        if np.random.rand() < self.eraser_aug_prob:
            img2 = img2.copy()
            mean_color = np.mean(img2.reshape(-1, 3), axis=0)
            for _ in range(np.random.randint(1, 3)):
                x0, y0 = np.random.randint(0, wd), np.random.randint(0, ht)
                dx, dy = np.random.randint(bounds[0], bounds[1]), np.random.randint(bounds[0], bounds[1])
                img2[y0:y0 + dy, x0:x0 + dx, :] = mean_color
        return img1, img2

    @staticmethod
    def _resize(a, size):
        if a.dtype == np.uint8:
            return np.asarray(Image.fromarray(a).resize(size, Image.BILINEAR))
        return np.stack([np.asarray(Image.fromarray(a[..., c], "F").resize(size, Image.BILINEAR))
                         for c in range(a.shape[2])], axis=-1)

    def spatial_transform(self, img1, img2, flow):
        ht, wd = img1.shape[:2]
        min_scale = np.maximum((self.crop_size[0] + 8) / float(ht), (self.crop_size[1] + 8) / float(wd))
        scale = 2 ** np.random.uniform(self.min_scale, self.max_scale)
        scale_x = scale_y = scale
        if np.random.rand() < self.stretch_prob:
            scale_x *= 2 ** np.random.uniform(-self.max_stretch, self.max_stretch)
            scale_y *= 2 ** np.random.uniform(-self.max_stretch, self.max_stretch)
        scale_x, scale_y = max(scale_x, min_scale), max(scale_y, min_scale)
        if np.random.rand() < self.spatial_aug_prob:
            size = (int(round(wd * scale_x)), int(round(ht * scale_y)))
            img1, img2 = self._resize(img1, size), self._resize(img2, size)
            flow = self._resize(flow, size) * [scale_x, scale_y]
        if self.do_flip:
            if np.random.rand() < self.h_flip_prob:
                img1, img2, flow = img1[:, ::-1], img2[:, ::-1], flow[:, ::-1] * [-1.0, 1.0]
            if np.random.rand() < self.v_flip_prob:
                img1, img2, flow = img1[::-1, :], img2[::-1, :], flow[::-1, :] * [1.0, -1.0]
        y0 = np.random.randint(0, max(1, img1.shape[0] - self.crop_size[0]))
        x0 = np.random.randint(0, max(1, img1.shape[1] - self.crop_size[1]))
        sl = (slice(y0, y0 + self.crop_size[0]), slice(x0, x0 + self.crop_size[1]))
        return img1[sl], img2[sl], flow[sl]

    def __call__(self, img1, img2, flow):
        img1, img2 = self.color_transform(img1, img2)
        img1, img2 = self.eraser_transform(img1, img2)
        img1, img2, flow = self.spatial_transform(img1, img2, flow)
        return np.ascontiguousarray(img1), np.ascontiguousarray(img2), np.ascontiguousarray(flow)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--address", required=True)
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    client = mpiflow.Client(a.address)
    s = client.get_sample(1, seed=a.seed, fields=["image1", "image2", "flow"])
    img1, img2, flow = s["image1"], s["image2"], s["flow"]
    aug = FlowAugmentor((368, 496), -0.1, 1.0, do_flip=True)
    np.random.seed(0)
    aug(img1, img2, flow)
    times = []
    for _ in range(a.runs):
        t = time.perf_counter()
        out = aug(img1, img2, flow)
        times.append((time.perf_counter() - t) * 1e3)
    assert out[0].shape == (368, 496, 3)
    print(f"python FlowAugmentor(raft-chairs) on a {s.width}x{s.height} sample: median {statistics.median(times):.1f} ms "
          f"(min {min(times):.1f}, max {max(times):.1f}) over {a.runs} calls, one thread")
    client.close()


if __name__ == "__main__":
    main()
