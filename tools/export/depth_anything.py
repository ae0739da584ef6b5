#!/usr/bin/env python3
"""Exports a Depth Anything V2 network (Hugging Face `transformers`
DepthAnythingForDepthEstimation) to ONNX with the hub export's tensor contract, the one the
registry entry `depth-anything-v2-small` runs with (docs/models.md):

    input  `pixel_values`     f32 [1,3,h,w], ImageNet-normalised RGB (mpiflow normalises)
    output `predicted_depth`  f32 [1,h,w], relative inverse depth (larger = nearer)

The export is static at --size x --size (default 518, a multiple of 14, the ViT patch): the
traced graph keeps the backbone's interpolation sizes as constants, so it does not take other
sizes (the hub's own export is dynamic); mpiflow feeds the registry's 518x518 either way.

Examples:
    # the Small architecture (DINOv2 ViT-S/14 + DPT head, ~25 M parameters) with random weights:
    # what the registry entry's real weights run as, to time it (no download)
    python tools/export/depth_anything.py --random-init small --out /tmp/da2_small.onnx --check
    # a reduced-width copy of the architecture, small enough for the repository's tests
    python tools/export/depth_anything.py --random-init tiny --out tests/data/models/depth_anything_v2_tiny.onnx
    # released weights (a local copy of depth-anything/Depth-Anything-V2-Small-hf)
    python tools/export/depth_anything.py --model path/to/Depth-Anything-V2-Small-hf --out da2.onnx

Needs: torch, transformers, onnx (and onnxruntime for --check).
"""

import argparse
import os
import sys

import numpy as np
import torch
from torch import nn

sys.path.insert(0, os.path.dirname(__file__))
from _common import OPSET, check, export  # noqa: E402


def random_config(arch):
    from transformers import DepthAnythingConfig, Dinov2Config

    if arch == "small":  # depth-anything/Depth-Anything-V2-Small-hf
        backbone = Dinov2Config(
            hidden_size=384,
            num_attention_heads=6,
            num_hidden_layers=12,
            mlp_ratio=4,
            patch_size=14,
            image_size=518,
            out_features=["stage3", "stage6", "stage9", "stage12"],
            reshape_hidden_states=False,
        )
        return DepthAnythingConfig(
            backbone_config=backbone,
            reassemble_hidden_size=384,
            neck_hidden_sizes=[48, 96, 192, 384],
            fusion_hidden_size=64,
            head_hidden_size=32,
            reassemble_factors=[4, 2, 1, 0.5],
            depth_estimation_type="relative",
        )
    if arch == "tiny":  # the same layers, narrower and shallower (for tests only)
        backbone = Dinov2Config(
            hidden_size=48,
            num_attention_heads=2,
            num_hidden_layers=4,
            mlp_ratio=2,
            patch_size=14,
            image_size=518,
            out_features=["stage1", "stage2", "stage3", "stage4"],
            reshape_hidden_states=False,
        )
        return DepthAnythingConfig(
            backbone_config=backbone,
            reassemble_hidden_size=48,
            neck_hidden_sizes=[8, 16, 32, 48],
            fusion_hidden_size=16,
            head_hidden_size=8,
            reassemble_factors=[4, 2, 1, 0.5],
            depth_estimation_type="relative",
        )
    raise SystemExit(f"unknown architecture {arch}")


class HubContract(nn.Module):
    """pixel_values [1,3,h,w] -> predicted_depth [1,h,w], as the hub's ONNX export has it."""

    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, pixel_values):
        return self.model(pixel_values=pixel_values).predicted_depth


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--model", help="a local directory (or hub id) of a DepthAnythingForDepthEstimation checkpoint")
    src.add_argument("--random-init", choices=["small", "tiny"], help="the architecture with random weights")
    p.add_argument("--size", type=int, default=518, help="side of the example input used for tracing (multiple of 14)")
    p.add_argument("--opset", type=int, default=OPSET)
    p.add_argument("--out", required=True, help="the .onnx file to write")
    p.add_argument("--check", action="store_true", help="compare ONNX Runtime with PyTorch on a random image")
    a = p.parse_args()

    from transformers import DepthAnythingForDepthEstimation

    torch.manual_seed(0)
    if a.model:
        model = DepthAnythingForDepthEstimation.from_pretrained(a.model)
    else:
        model = DepthAnythingForDepthEstimation(random_config(a.random_init))
    wrapper = HubContract(model.eval()).eval()
    params = sum(t.numel() for t in model.parameters())
    image = torch.randn(1, 3, a.size, a.size)
    os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
    export(wrapper, (image,), a.out, ["pixel_values"], ["predicted_depth"], opset=a.opset)
    print(f"wrote {a.out}: {params / 1e6:.2f} M parameters, pixel_values [1,3,{a.size},{a.size}] -> predicted_depth [1,{a.size},{a.size}]")
    if a.check:
        rng = np.random.default_rng(1)
        check(wrapper, a.out, {"pixel_values": rng.standard_normal((1, 3, a.size, a.size), np.float32)})


if __name__ == "__main__":
    main()
