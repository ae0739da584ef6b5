"""Helpers shared by the export recipes: ONNX export with the legacy (TorchScript) exporter,
and an optional check of the exported model with ONNX Runtime against PyTorch."""

import inspect

import numpy as np
import torch

OPSET = 17


def export(module, args, path, input_names, output_names, dynamic_axes=None, opset=OPSET):
    """torch.onnx.export with the TorchScript-based exporter (the `dynamo` exporter, the
    default from torch 2.9, does not handle the data-dependent control flow of detection
    models), weights embedded, constants folded."""
    kwargs = dict(
        input_names=input_names,
        output_names=output_names,
        dynamic_axes=dynamic_axes or {},
        opset_version=opset,
        do_constant_folding=True,
    )
    if "dynamo" in inspect.signature(torch.onnx.export).parameters:
        kwargs["dynamo"] = False
    module.eval()
    with torch.no_grad():
        torch.onnx.export(module, args, path, **kwargs)


def check(module, path, feeds, atol=1e-3, rtol=1e-3):
    """Runs the exported model with ONNX Runtime on `feeds` (name -> numpy array) and compares
    every output with PyTorch's; prints the outputs' names, shapes and largest differences."""
    import onnxruntime

    session = onnxruntime.InferenceSession(path, providers=["CPUExecutionProvider"])
    names = [o.name for o in session.get_outputs()]
    got = session.run(None, feeds)
    with torch.no_grad():
        want = module(*[torch.from_numpy(v) for v in feeds.values()])
    if isinstance(want, torch.Tensor):
        want = (want,)
    ok = True
    for name, g, w in zip(names, got, want):
        w = w.detach().cpu().numpy()
        if g.shape != w.shape:
            print(f"  {name}: shape {g.shape} from ONNX Runtime, {w.shape} from PyTorch")
            ok = False
            continue
        diff = float(np.max(np.abs(g.astype(np.float64) - w.astype(np.float64)))) if g.size else 0.0
        close = g.size == 0 or np.allclose(g, w, atol=atol, rtol=rtol)
        ok &= bool(close)
        print(f"  {name}: {g.dtype} {list(g.shape)}, max |onnx - torch| = {diff:.3g}{'' if close else '  MISMATCH'}")
    if not ok:
        raise SystemExit(f"{path}: ONNX Runtime and PyTorch disagree")
    return dict(zip(names, got))
