#!/usr/bin/env python3
"""Writes tiny ONNX models with mpiflow's three scene-model contracts (docs/models.md) whose
outputs are known, simple functions of their inputs, plus broken variants for the error tests.

    python tools/make_test_models.py OUTDIR

Only the `onnx` package is needed (onnx.helper); opset 17, IR version 8, so that any ONNX
Runtime >= 1.14 (and the 1.31 the project pins) loads them. `h` and `w` are symbolic
dimensions unless a model says otherwise. The known functions (tests/samples/onnx_scene.rs checks them):

depth.onnx               image [1,3,h,w] -> depth [1,h,w] = 2 R + G - 0.5 B + 3
depth_fixed.onnx         the same on a static 32x24 (W x H) input, output [1,1,24,32]
depth_nan.onnx           depth [1,1,h,w] = sqrt(R - 0.25): NaN wherever R < 0.25
depth_wrong_input.onnx   like depth.onnx, input named `input`
depth_wrong_output.onnx  like depth.onnx, output named `predicted_depth`
depth_hub.onnx           like depth.onnx with the hub's tensor names (Depth Anything, DPT
                         exports): pixel_values [1,3,h,w] -> predicted_depth [1,h,w]
depth_two_channels.onnx  output [1,2,h,w] (wrong shape)
depth_rank3_input.onnx   input [3,h,w] (wrong rank)
mpi.onnx                 image [1,3,h,w], disparity [1,1,h,w] -> mpi [1,4,4,h,w]:
                         plane s: rgb = image, sigma = (s + 1) * disparity + 0.5 s
mpi_planes.onnx          the same on a static 32x32 input, plus
                         plane_disparity [1,4] = (0.9, 0.6, 0.3, 0.1)
mpi_bad_planes.onnx      like mpi_planes.onnx with plane_disparity increasing
mpi_wrong_rank.onnx      mpi reshaped to [1,16,h,w]
seg.onnx                 image [1,3,h,w] -> masks [K,1,h,w], scores [K], labels [K] (int64):
                         one candidate per channel c: mask = (channel c > 0.5), score = mean of
                         channel c, label = c + 1; candidates with score <= 0.05 are dropped in
                         the graph (so K is 0..3 and depends on the input)
seg_wrong_names.onnx     like seg.onnx, outputs named `out_masks`, `out_scores`, `out_labels`
"""

import os
import sys

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

OPSET = 17
IR_VERSION = 8
F = TensorProto.FLOAT


def const(name, array, dtype=np.float32):
    return numpy_helper.from_array(np.asarray(array, dtype=dtype), name)


def save(outdir, filename, nodes, inputs, outputs, initializers):
    graph = helper.make_graph(nodes, filename.removesuffix(".onnx"), inputs, outputs, initializers)
    model = helper.make_model(
        graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="mpiflow make_test_models"
    )
    model.ir_version = IR_VERSION
    onnx.checker.check_model(model, full_check=True)
    onnx.save(model, os.path.join(outdir, filename))


def image_input(name="image", h="h", w="w"):
    return helper.make_tensor_value_info(name, F, [1, 3, h, w])


def depth_models(outdir):
    weights = const("w", [[[[2.0]], [[1.0]], [[-0.5]]]])  # [1,3,1,1]
    bias = const("b", [3.0])
    axes = const("axes", [1], np.int64)

    def linear(input_name="image", output_name="depth", squeeze=True, h="h", w="w", filename="depth.onnx"):
        nodes = [helper.make_node("Conv", [input_name, "w", "b"], ["conv" if squeeze else output_name])]
        inits = [weights, bias]
        if squeeze:
            nodes.append(helper.make_node("Squeeze", ["conv", "axes"], [output_name]))
            inits.append(axes)
            out = helper.make_tensor_value_info(output_name, F, [1, h, w])
        else:
            out = helper.make_tensor_value_info(output_name, F, [1, 1, h, w])
        save(outdir, filename, nodes, [image_input(input_name, h, w)], [out], inits)

    linear()
    linear(squeeze=False, h=24, w=32, filename="depth_fixed.onnx")
    linear(input_name="input", filename="depth_wrong_input.onnx")
    linear(output_name="predicted_depth", filename="depth_wrong_output.onnx")
    linear(input_name="pixel_values", output_name="predicted_depth", filename="depth_hub.onnx")

    # Two output channels: [1,2,h,w].
    w2 = const("w2", [[[[2.0]], [[1.0]], [[-0.5]]], [[[1.0]], [[1.0]], [[1.0]]]])
    b2 = const("b2", [3.0, 0.0])
    save(
        outdir,
        "depth_two_channels.onnx",
        [helper.make_node("Conv", ["image", "w2", "b2"], ["depth"])],
        [image_input()],
        [helper.make_tensor_value_info("depth", F, [1, 2, "h", "w"])],
        [w2, b2],
    )

    # Input of rank 3: [3,h,w].
    save(
        outdir,
        "depth_rank3_input.onnx",
        [
            helper.make_node("Unsqueeze", ["image", "axes0"], ["image4"]),
            helper.make_node("Conv", ["image4", "w", "b"], ["depth"]),
        ],
        [helper.make_tensor_value_info("image", F, [3, "h", "w"])],
        [helper.make_tensor_value_info("depth", F, [1, 1, "h", "w"])],
        [weights, bias, const("axes0", [0], np.int64)],
    )

    # sqrt(R - 0.25): NaN where R < 0.25.
    save(
        outdir,
        "depth_nan.onnx",
        [
            helper.make_node("Slice", ["image", "s0", "s1", "s_axes"], ["red"]),
            helper.make_node("Sub", ["red", "quarter"], ["shifted"]),
            helper.make_node("Sqrt", ["shifted"], ["depth"]),
        ],
        [image_input()],
        [helper.make_tensor_value_info("depth", F, [1, 1, "h", "w"])],
        [
            const("s0", [0], np.int64),
            const("s1", [1], np.int64),
            const("s_axes", [1], np.int64),
            const("quarter", [0.25]),
        ],
    )


S = 4


def mpi_models(outdir):
    scale = const("scale", np.arange(1, S + 1, dtype=np.float32).reshape(1, S, 1, 1, 1))
    offset = const("offset", (0.5 * np.arange(S, dtype=np.float32)).reshape(1, S, 1, 1, 1))
    ones = const("ones", np.ones((1, S, 1, 1, 1), np.float32))
    ax1 = const("ax1", [1], np.int64)

    def make(filename, h="h", w="w", planes=None, output_name="mpi", wrong_rank=False):
        nodes = [
            helper.make_node("Unsqueeze", ["image", "ax1"], ["image5"]),  # [1,1,3,h,w]
            helper.make_node("Mul", ["image5", "ones"], ["rgb"]),  # [1,S,3,h,w]
            helper.make_node("Unsqueeze", ["disparity", "ax1"], ["disp5"]),  # [1,1,1,h,w]
            helper.make_node("Mul", ["disp5", "scale"], ["scaled"]),  # [1,S,1,h,w]
            helper.make_node("Add", ["scaled", "offset"], ["sigma"]),
            helper.make_node("Concat", ["rgb", "sigma"], ["mpi5" if wrong_rank else output_name], axis=2),
        ]
        inits = [scale, offset, ones, ax1]
        if wrong_rank:
            nodes += [
                helper.make_node("Shape", ["image"], ["image_shape"]),
                helper.make_node("Slice", ["image_shape", "hw_start", "hw_end"], ["hw"]),
                helper.make_node("Concat", ["lead", "hw"], ["flat_shape"], axis=0),
                helper.make_node("Reshape", ["mpi5", "flat_shape"], [output_name]),
            ]
            inits += [
                const("hw_start", [2], np.int64),
                const("hw_end", [4], np.int64),
                const("lead", [1, 4 * S], np.int64),
            ]
            mpi_out = helper.make_tensor_value_info(output_name, F, [1, 4 * S, h, w])
        else:
            mpi_out = helper.make_tensor_value_info(output_name, F, [1, S, 4, h, w])
        outputs = [mpi_out]
        if planes is not None:
            nodes.append(helper.make_node("Identity", ["planes"], ["plane_disparity"]))
            inits.append(const("planes", [planes]))
            outputs.append(helper.make_tensor_value_info("plane_disparity", F, [1, S]))
        inputs = [image_input(h=h, w=w), helper.make_tensor_value_info("disparity", F, [1, 1, h, w])]
        save(outdir, filename, nodes, inputs, outputs, inits)

    make("mpi.onnx")
    make("mpi_planes.onnx", h=32, w=32, planes=[0.9, 0.6, 0.3, 0.1])
    make("mpi_bad_planes.onnx", h=32, w=32, planes=[0.1, 0.3, 0.6, 0.9])
    make("mpi_wrong_rank.onnx", wrong_rank=True)


def seg_models(outdir):
    def make(filename, names=("masks", "scores", "labels")):
        nodes = [
            helper.make_node("Greater", ["image", "half"], ["above"]),
            helper.make_node("Cast", ["above"], ["binary"], to=F),  # [1,3,h,w]
            helper.make_node("Transpose", ["binary"], ["candidates"], perm=[1, 0, 2, 3]),  # [3,1,h,w]
            helper.make_node("ReduceMean", ["image"], ["means"], axes=[0, 2, 3], keepdims=0),  # [3]
            helper.make_node("Greater", ["means", "min_score"], ["keep"]),
            helper.make_node("Compress", ["candidates", "keep"], [names[0]], axis=0),
            helper.make_node("Compress", ["means", "keep"], [names[1]], axis=0),
            helper.make_node("Compress", ["all_labels", "keep"], [names[2]], axis=0),
        ]
        inits = [const("half", 0.5), const("min_score", 0.05), const("all_labels", [1, 2, 3], np.int64)]
        outputs = [
            helper.make_tensor_value_info(names[0], F, ["k", 1, "h", "w"]),
            helper.make_tensor_value_info(names[1], F, ["k"]),
            helper.make_tensor_value_info(names[2], TensorProto.INT64, ["k"]),
        ]
        save(outdir, filename, nodes, [image_input()], outputs, inits)

    make("seg.onnx")
    make("seg_wrong_names.onnx", names=("out_masks", "out_scores", "out_labels"))


def main():
    if len(sys.argv) != 2:
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        sys.exit(2)
    outdir = sys.argv[1]
    os.makedirs(outdir, exist_ok=True)
    depth_models(outdir)
    mpi_models(outdir)
    seg_models(outdir)


if __name__ == "__main__":
    main()
