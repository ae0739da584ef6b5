#!/usr/bin/env python3
"""Exports the AdaMPI network (Han et al., SIGGRAPH 2022; the MPI network of MPI-Flow) to ONNX
with mpiflow's MPI contract (docs/models.md):

    inputs  `image`            f32 [1,3,H,W], RGB in [0,1]
            `disparity`        f32 [1,1,H,W], disparity in [0,1] (1 = nearest)
    outputs `mpi`              f32 [1,S,4,H,W], rgb in [0,1] (sigmoid), density sigma > 0
                               (relu + 1e-4, a density, not an alpha)
            `plane_disparity`  f32 [1,S], near to far (only with --planes adjusted, or when
                               --plane-disparity-output is given)

AdaMPI is not on PyPI: clone its repository (github.com/yxuhan/AdaMPI, or MPI-Flow's copy of
it) and pass it with --adampi-repo; the recipe imports `model.AdaMPI.MPIPredictor` from there
(which imports `model/CPN/{encoder,unet,decoder}.py` and `model/PAN.py`; needs torch and
torchvision only). Checkpoints (`adampi_32p.pth`, `adampi_64p.pth`) are dicts with
"num_planes" and "weight" (the state dict).

H and W are static (AdaMPI's plane-adjustment branch is built for one size) and must be
multiples of 128; AdaMPI was trained at 384x256. mpiflow resizes to the model's size
(SizePolicy::Model, the default) and back.

--planes fixed (default) is what MPI-Flow's generator does: the plane-adjustment network is
bypassed and the planes sit at linspace(1.0, 0.001, S+2)[1:-1], which is also mpiflow's default
when the model has no `plane_disparity` output. --planes adjusted keeps AdaMPI's own
plane-adjustment network (PAN) and exports the disparities it predicts.

Examples:
    python tools/export/adampi.py --adampi-repo ~/src/AdaMPI --ckpt adampiweight/adampi_64p.pth \\
        --out models/adampi_64p.onnx
    # random weights of the same architecture (checks the recipe; still needs the repository)
    python tools/export/adampi.py --adampi-repo ~/src/AdaMPI --random-init --num-planes 8 \\
        --out /tmp/mpi.onnx --check

Needs: torch, torchvision, numpy, onnx (and onnxruntime for --check).
"""

import argparse
import os
import sys

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

sys.path.insert(0, os.path.dirname(__file__))
from _common import OPSET, check, export  # noqa: E402


def static_adaptive_avg_pool2d(original):
    """AdaMPI's decoder calls adaptive_avg_pool2d with sizes read from tensors, which the
    TorchScript exporter cannot export ("output_size is not constant"). With static input sizes
    every such pooling divides evenly, where it equals a plain average pooling with a constant
    kernel: use that (and the original otherwise)."""

    def pool(x, output_size):
        if isinstance(output_size, int):
            output_size = (output_size, output_size)
        oh, ow = (int(s) for s in output_size)
        h, w = int(x.shape[-2]), int(x.shape[-1])
        if oh > 0 and ow > 0 and h % oh == 0 and w % ow == 0:
            return F.avg_pool2d(x, kernel_size=(h // oh, w // ow))
        return original(x, (oh, ow))

    return pool


class MpiContract(nn.Module):
    def __init__(self, model, with_planes):
        super().__init__()
        self.model = model
        self.with_planes = with_planes

    def forward(self, image, disparity):
        mpi, planes = self.model(image, disparity)
        return (mpi, planes) if self.with_planes else mpi


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--adampi-repo", required=True, help="a checkout of the AdaMPI repository (holds model/AdaMPI.py)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--ckpt", help="checkpoint: a dict with 'num_planes' and 'weight'")
    src.add_argument("--random-init", action="store_true", help="random weights (with --num-planes)")
    p.add_argument("--num-planes", type=int, default=64, help="planes S for --random-init (released: 32 or 64)")
    p.add_argument("--width", type=int, default=384, help="static input width, a multiple of 128 (default 384)")
    p.add_argument("--height", type=int, default=256, help="static input height, a multiple of 128 (default 256)")
    p.add_argument("--planes", choices=["fixed", "adjusted"], default="fixed",
                   help="fixed: MPI-Flow's fixed plane disparities; adjusted: AdaMPI's plane adjustment")
    p.add_argument("--plane-disparity-output", action="store_true",
                   help="also export `plane_disparity` with --planes fixed (always exported with adjusted)")
    p.add_argument("--opset", type=int, default=OPSET)
    p.add_argument("--out", required=True, help="the .onnx file to write")
    p.add_argument("--check", action="store_true", help="compare ONNX Runtime with PyTorch on random inputs")
    a = p.parse_args()
    if a.width % 128 or a.height % 128:
        raise SystemExit("AdaMPI needs --width and --height to be multiples of 128")

    sys.path.insert(0, os.path.abspath(a.adampi_repo))
    from model.AdaMPI import MPIPredictor  # noqa: E402  (from the AdaMPI repository)

    torch.manual_seed(0)
    if a.ckpt:
        ckpt = torch.load(a.ckpt, map_location="cpu")
        model = MPIPredictor(width=a.width, height=a.height, num_planes=ckpt["num_planes"])
        model.load_state_dict(ckpt["weight"])
    else:
        model = MPIPredictor(width=a.width, height=a.height, num_planes=a.num_planes)
    model.eval()
    if a.planes == "fixed" and hasattr(model, "dpn"):
        # Bypass the plane-adjustment network: the planes stay at the initial linspace, exactly
        # as MPI-Flow's copy of MPIPredictor.forward does (`render_disp = dpn_input_disparity`).
        model.dpn.forward = lambda init_disp, rgb_low_res, disp_low_res: init_disp
    with_planes = a.planes == "adjusted" or a.plane_disparity_output
    wrapper = MpiContract(model, with_planes).eval()
    image = torch.rand(1, 3, a.height, a.width)
    disparity = torch.rand(1, 1, a.height, a.width)
    outputs = ["mpi", "plane_disparity"] if with_planes else ["mpi"]
    original_pool = F.adaptive_avg_pool2d
    F.adaptive_avg_pool2d = static_adaptive_avg_pool2d(original_pool)
    try:
        export(wrapper, (image, disparity), a.out, ["image", "disparity"], outputs, opset=a.opset)
    finally:
        F.adaptive_avg_pool2d = original_pool
    print(f"wrote {a.out}: image [1,3,{a.height},{a.width}], disparity [1,1,{a.height},{a.width}] -> {', '.join(outputs)}")
    if a.check:
        rng = np.random.default_rng(1)
        check(
            wrapper,
            a.out,
            {
                "image": rng.random((1, 3, a.height, a.width), np.float32),
                "disparity": rng.random((1, 1, a.height, a.width), np.float32),
            },
        )


if __name__ == "__main__":
    main()
