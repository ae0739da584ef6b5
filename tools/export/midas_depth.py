#!/usr/bin/env python3
"""Exports a MiDaS-family DPT depth network (Hugging Face `transformers` DPTForDepthEstimation,
no torch.hub) to ONNX with mpiflow's depth contract (docs/models.md):

    input  `image`  f32 [1,3,H,W], RGB in [0,1] (the network's mean/std is applied inside)
    output `depth`  f32 [1,H,W], relative inverse depth (larger = nearer)

Examples:
    # the DPT-Hybrid MiDaS checkpoint AdaMPI and MPI-Flow use (weights from the Hugging Face hub
    # or a local copy of it)
    python tools/export/midas_depth.py --model Intel/dpt-hybrid-midas --out models/depth.onnx
    # the same architecture with random weights (no download; checks the recipe)
    python tools/export/midas_depth.py --random-init dpt-hybrid --out /tmp/depth.onnx --check
    # the hub export's contract (pixel_values -> predicted_depth), as the registry entry
    # dpt-hybrid-midas runs it; a reduced-width copy for the tests
    python tools/export/midas_depth.py --random-init dpt-hybrid-tiny --hub-contract \
        --out tests/data/models/dpt_hybrid_tiny.onnx --check

Needs: torch, transformers, onnx (and onnxruntime for --check).
"""

import argparse
import sys

import numpy as np
import torch
from torch import nn

sys.path.insert(0, __import__("os").path.dirname(__file__))
from _common import OPSET, check, export  # noqa: E402


def random_config(arch):
    from transformers import DPTConfig

    if arch == "dpt-large":  # ViT-L/16, the transformers default (Intel/dpt-large)
        return DPTConfig()
    if arch == "dpt-hybrid":  # ViT-B/16 on a BiT ResNet stem, like Intel/dpt-hybrid-midas
        return DPTConfig(
            is_hybrid=True,
            hidden_size=768,
            num_hidden_layers=12,
            num_attention_heads=12,
            intermediate_size=3072,
            neck_hidden_sizes=[256, 512, 768, 768],
            backbone_out_indices=[2, 5, 8, 11],
        )
    if arch == "dpt-hybrid-tiny":  # the same layers, narrower and shallower (for tests only)
        from transformers import BitConfig

        bit = BitConfig(
            global_padding="same",
            layer_type="bottleneck",
            depths=[1, 1, 1],
            hidden_sizes=[16, 32, 64],
            embedding_size=16,
            num_groups=8,
            out_features=["stage1", "stage2", "stage3"],
            embedding_dynamic_padding=True,
        )
        return DPTConfig(
            is_hybrid=True,
            backbone_config=bit,
            hidden_size=48,
            num_hidden_layers=4,
            num_attention_heads=2,
            intermediate_size=96,
            neck_hidden_sizes=[16, 32, 48, 48],
            backbone_out_indices=[0, 1, 2, 3],
            fusion_hidden_size=16,
            backbone_featmap_shape=[1, 64, 24, 24],
        )
    raise SystemExit(f"unknown architecture {arch}")


class HubContract(nn.Module):
    """pixel_values [1,3,H,W] (normalised by the caller) -> predicted_depth [1,H,W], as the hub's
    ONNX exports (Xenova/dpt-hybrid-midas) have it."""

    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, pixel_values):
        return self.model(pixel_values=pixel_values).predicted_depth


class DepthContract(nn.Module):
    """[1,3,H,W] in [0,1] -> [1,H,W] relative inverse depth."""

    def __init__(self, model, mean, std):
        super().__init__()
        self.model = model
        self.register_buffer("mean", torch.tensor(mean, dtype=torch.float32).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(std, dtype=torch.float32).view(1, 3, 1, 1))

    def forward(self, image):
        return self.model(pixel_values=(image - self.mean) / self.std).predicted_depth


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--model", help="Hugging Face model id or local directory of a DPTForDepthEstimation checkpoint")
    src.add_argument(
        "--random-init",
        choices=["dpt-hybrid", "dpt-large", "dpt-hybrid-tiny"],
        help="the architecture with random weights (dpt-hybrid-tiny: a reduced-width copy for tests)",
    )
    p.add_argument(
        "--hub-contract",
        action="store_true",
        help="export the hub's contract instead (pixel_values, normalised by mpiflow -> predicted_depth), "
        "the one the registry entry dpt-hybrid-midas runs with; --mean/--std are then not baked in",
    )
    p.add_argument("--height", type=int, default=384, help="static input height (multiple of 32; default 384)")
    p.add_argument("--width", type=int, default=384, help="static input width (multiple of 32; default 384)")
    p.add_argument("--mean", type=float, nargs=3, default=[0.5, 0.5, 0.5], help="normalisation baked into the graph")
    p.add_argument("--std", type=float, nargs=3, default=[0.5, 0.5, 0.5], help="normalisation baked into the graph")
    p.add_argument("--opset", type=int, default=OPSET)
    p.add_argument("--out", required=True, help="the .onnx file to write")
    p.add_argument("--check", action="store_true", help="compare ONNX Runtime with PyTorch on a random image")
    a = p.parse_args()

    from transformers import DPTForDepthEstimation

    torch.manual_seed(0)
    if a.model:
        model = DPTForDepthEstimation.from_pretrained(a.model)
    else:
        model = DPTForDepthEstimation(random_config(a.random_init))
    names = ("pixel_values", "predicted_depth") if a.hub_contract else ("image", "depth")
    if a.hub_contract:
        wrapper = HubContract(model.eval()).eval()
    else:
        wrapper = DepthContract(model.eval(), a.mean, a.std).eval()
    image = torch.rand(1, 3, a.height, a.width)
    export(wrapper, (image,), a.out, [names[0]], [names[1]], opset=a.opset)
    params = sum(t.numel() for t in model.parameters())
    print(
        f"wrote {a.out}: {params / 1e6:.2f} M parameters, "
        f"{names[0]} [1,3,{a.height},{a.width}] -> {names[1]} [1,{a.height},{a.width}]"
    )
    if a.check:
        check(wrapper, a.out, {names[0]: np.random.default_rng(1).random((1, 3, a.height, a.width), np.float32)})


if __name__ == "__main__":
    main()
