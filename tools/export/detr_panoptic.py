#!/usr/bin/env python3
"""Exports a DETR panoptic segmentation network (Hugging Face `transformers` DetrForSegmentation)
to ONNX with the hub export's tensor contract, the one the registry entry
`detr-resnet-50-panoptic` runs with (docs/models.md):

    input  `pixel_values`  f32 [1,3,h,w], ImageNet-normalised RGB (mpiflow normalises), any size
    output `logits`        f32 [1,Q,C+1], class logits per query (the last class: no object)
    output `pred_masks`    f32 [1,Q,h/4,w/4], mask logits per query

Height and width are dynamic (multiples of 32 keep the masks aligned). mpiflow's post-processing
(softmax, "thing" classes, thresholds, overlaps) is in Rust (`src/scene/onnx/detr.rs`).

Examples:
    # the ResNet-50 architecture (100 queries, 6 + 6 transformer layers, 250 COCO panoptic
    # classes) with random weights: what the registry entry's real weights run as, to time it
    python tools/export/detr_panoptic.py --random-init resnet50 --out /tmp/detr_r50.onnx --check
    # the same, dynamically quantised to 8 bits, the kind of file the registry pins
    python tools/export/detr_panoptic.py --random-init resnet50 --quantize --out /tmp/detr_r50_q.onnx
    # a reduced copy of the architecture for the repository's tests; its class bias makes every
    # query a confident "person" (COCO id 1), so the random network finds objects to move
    python tools/export/detr_panoptic.py --random-init tiny --class-bias 1=12 --quantize \\
        --out tests/data/models/detr_panoptic_tiny.onnx --check
    # released weights (a local copy of facebook/detr-resnet-50-panoptic)
    python tools/export/detr_panoptic.py --model path/to/detr-resnet-50-panoptic --out detr.onnx

Needs: torch, transformers, onnx (and onnxruntime for --check and --quantize).
"""

import argparse
import os
import sys

import numpy as np
import torch
from torch import nn

sys.path.insert(0, os.path.dirname(__file__))
from _common import OPSET, check, export  # noqa: E402

# COCO panoptic: class ids 0..249 (things 1..90, stuff 92..199, the rest unused), plus no-object
NUM_LABELS = 250


def random_config(arch):
    from transformers import DetrConfig, ResNetConfig

    stages = ["stage1", "stage2", "stage3", "stage4"]
    if arch == "resnet50":  # facebook/detr-resnet-50-panoptic
        backbone = ResNetConfig(out_features=stages)  # ResNet-50: bottleneck, depths 3-4-6-3
        return DetrConfig(
            use_timm_backbone=False,
            backbone=None,
            backbone_config=backbone,
            use_pretrained_backbone=False,
            num_labels=NUM_LABELS,
            num_queries=100,
        )
    if arch == "tiny":  # the same layers, narrower and shallower (for tests only)
        backbone = ResNetConfig(
            embedding_size=8, hidden_sizes=[8, 16, 32, 64], depths=[1, 1, 1, 1], layer_type="basic", out_features=stages
        )
        # the mask head's group norms need d_model a multiple of 128 (and d_model + heads of 8)
        return DetrConfig(
            use_timm_backbone=False,
            backbone=None,
            backbone_config=backbone,
            use_pretrained_backbone=False,
            num_labels=NUM_LABELS,
            num_queries=8,
            d_model=128,
            encoder_layers=1,
            decoder_layers=1,
            encoder_attention_heads=8,
            decoder_attention_heads=8,
            encoder_ffn_dim=64,
            decoder_ffn_dim=64,
        )
    raise SystemExit(f"unknown architecture {arch}")


class HubContract(nn.Module):
    """pixel_values [1,3,h,w] -> logits [1,Q,C+1], pred_masks [1,Q,h/4,w/4]."""

    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, pixel_values):
        out = self.model(pixel_values=pixel_values)
        return out.logits, out.pred_masks


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--model", help="a local directory (or hub id) of a DetrForSegmentation checkpoint")
    src.add_argument("--random-init", choices=["resnet50", "tiny"], help="the architecture with random weights")
    p.add_argument("--class-bias", action="append", default=[], metavar="ID=B",
                   help="add B to the class head's bias of class ID (random weights that detect that class)")
    p.add_argument("--width", type=int, default=640, help="width of the example input used for tracing")
    p.add_argument("--height", type=int, default=480, help="height of the example input used for tracing")
    p.add_argument("--quantize", action="store_true",
                   help="dynamic 8-bit quantisation of the weights (onnxruntime.quantization, QUInt8)")
    p.add_argument("--opset", type=int, default=OPSET)
    p.add_argument("--out", required=True, help="the .onnx file to write")
    p.add_argument("--check", action="store_true", help="compare ONNX Runtime with PyTorch at two input sizes")
    a = p.parse_args()

    from transformers import DetrForSegmentation

    torch.manual_seed(0)
    if a.model:
        model = DetrForSegmentation.from_pretrained(a.model)
    else:
        model = DetrForSegmentation(random_config(a.random_init))
    with torch.no_grad():
        for item in a.class_bias:
            label, bias = item.split("=")
            model.detr.class_labels_classifier.bias[int(label)] += float(bias)
    wrapper = HubContract(model.eval()).eval()
    params = sum(t.numel() for t in model.parameters())
    image = torch.randn(1, 3, a.height, a.width)
    out = os.path.abspath(a.out)
    os.makedirs(os.path.dirname(out), exist_ok=True)
    plain = out + ".fp32.onnx" if a.quantize else out
    axes = {"pixel_values": {2: "height", 3: "width"}, "pred_masks": {2: "mask_height", 3: "mask_width"}}
    export(wrapper, (image,), plain, ["pixel_values"], ["logits", "pred_masks"], dynamic_axes=axes, opset=a.opset)
    if a.quantize:
        from onnxruntime.quantization import QuantType, quantize_dynamic

        quantize_dynamic(plain, out, weight_type=QuantType.QUInt8)
        os.remove(plain)
    q = model.config.num_queries
    print(
        f"wrote {a.out} ({os.path.getsize(out)} bytes): {params / 1e6:.2f} M parameters, "
        f"pixel_values [1,3,h,w] -> logits [1,{q},{model.config.num_labels + 1}], pred_masks [1,{q},h/4,w/4]"
    )
    if a.check:
        rng = np.random.default_rng(1)
        # a quantised graph differs from PyTorch by its rounding: compare loosely
        tol = 0.5 if a.quantize else 1e-3
        for h, w in [(a.height, a.width), (a.height // 2 + 32, a.width // 2)]:
            print(f"  input {w}x{h}:")
            check(wrapper, out, {"pixel_values": rng.standard_normal((1, 3, h, w), np.float32)}, atol=tol, rtol=tol)


if __name__ == "__main__":
    main()
