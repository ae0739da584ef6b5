#!/usr/bin/env python3
"""Exports torchvision's Mask R-CNN (maskrcnn_resnet50_fpn) to ONNX with mpiflow's
segmentation contract (docs/models.md):

    input   `image`   f32 [1,3,h,w], RGB in [0,1] (any size; torchvision's own resizing to
                      --min-size/--max-size and ImageNet normalisation are inside the graph)
    outputs `masks`   f32 [K,1,h,w], per-instance probabilities at the input size
            `scores`  f32 [K], decreasing
            `labels`  i64 [K], COCO category ids (1 = person, ...)
    K = 0..--detections, after torchvision's own score threshold --box-score-thresh.

Examples:
    # COCO weights (torchvision downloads them on first use)
    python tools/export/maskrcnn.py --weights default --out models/maskrcnn.onnx
    # random weights, no download (checks the recipe; a low threshold so that K > 0)
    python tools/export/maskrcnn.py --weights none --box-score-thresh 0 --out /tmp/seg.onnx --check

Needs: torch, torchvision, onnx (and onnxruntime for --check).
"""

import argparse
import sys

import numpy as np
import torch
from torch import nn

sys.path.insert(0, __import__("os").path.dirname(__file__))
from _common import OPSET, check, export  # noqa: E402


class SegmentationContract(nn.Module):
    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, image):
        out = self.model([image[0]])[0]
        return out["masks"], out["scores"], out["labels"]


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--weights", choices=["none", "default"], default="default",
                   help="none: random init (weights=None, weights_backbone=None); default: COCO weights")
    p.add_argument("--min-size", type=int, default=800, help="torchvision's resize: shorter side (default 800)")
    p.add_argument("--max-size", type=int, default=1333, help="torchvision's resize: longer side cap (default 1333)")
    p.add_argument("--box-score-thresh", type=float, default=0.05, help="detections below are dropped in the graph")
    p.add_argument("--detections", type=int, default=100, help="at most this many instances (default 100)")
    p.add_argument("--height", type=int, default=480, help="height of the example input used for tracing")
    p.add_argument("--width", type=int, default=640, help="width of the example input used for tracing")
    p.add_argument("--opset", type=int, default=OPSET)
    p.add_argument("--out", required=True, help="the .onnx file to write")
    p.add_argument("--check", action="store_true",
                   help="compare ONNX Runtime with PyTorch on two random images of different sizes")
    a = p.parse_args()

    from torchvision.models.detection import maskrcnn_resnet50_fpn

    torch.manual_seed(0)
    kwargs = dict(
        min_size=a.min_size,
        max_size=a.max_size,
        box_score_thresh=a.box_score_thresh,
        box_detections_per_img=a.detections,
    )
    if a.weights == "none":
        model = maskrcnn_resnet50_fpn(weights=None, weights_backbone=None, **kwargs)
    else:
        model = maskrcnn_resnet50_fpn(weights="DEFAULT", **kwargs)
    wrapper = SegmentationContract(model.eval()).eval()
    image = torch.rand(1, 3, a.height, a.width)
    export(
        wrapper,
        (image,),
        a.out,
        ["image"],
        ["masks", "scores", "labels"],
        dynamic_axes={
            "image": {2: "h", 3: "w"},
            "masks": {0: "k", 2: "h", 3: "w"},
            "scores": {0: "k"},
            "labels": {0: "k"},
        },
        opset=a.opset,
    )
    print(f"wrote {a.out}: image [1,3,h,w] -> masks [k,1,h,w], scores [k], labels [k]")
    if a.check:
        rng = np.random.default_rng(1)
        for h, w in [(a.height, a.width), (a.height * 3 // 4, a.width // 2)]:
            print(f" input {w}x{h}:")
            check(wrapper, a.out, {"image": rng.random((1, 3, h, w), np.float32)}, atol=1e-3, rtol=1e-2)


if __name__ == "__main__":
    main()
