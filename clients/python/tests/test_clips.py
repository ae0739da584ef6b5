"""Backward flow and clips against the real server and `mpiflow generate`.

The Sintel export is read back by a reader written here from the MPI Sintel format itself
(the `.flo` spec: float32 tag 202021.25, int32 width, int32 height, then H x W x 2 float32,
little-endian; masks as 8-bit PNGs with 255 = occluded / invalid) and by the file listing that
RAFT's `MpiSintel` dataset class does, not by mpiflow's own code.
"""
from __future__ import annotations

import glob
import os
import subprocess
from pathlib import Path

import grpc
import numpy as np
import pytest
from PIL import Image

from conftest import real_binary

FLO_TAG = 202021.25


def read_flo(path: str) -> np.ndarray:
    with open(path, "rb") as f:
        tag = np.fromfile(f, "<f4", count=1)
        assert tag.size == 1 and tag[0] == FLO_TAG, f"{path}: bad .flo tag {tag}"
        w, h = (int(v) for v in np.fromfile(f, "<i4", count=2))
        data = np.fromfile(f, "<f4", count=2 * w * h)
        assert data.size == 2 * w * h, f"{path}: truncated"
        assert f.read() == b"", f"{path}: trailing bytes"
    return data.reshape(h, w, 2)


def read_png(path: str) -> np.ndarray:
    with Image.open(path) as im:
        return np.asarray(im)


def bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    h, w = img.shape[:2]
    x = np.clip(x, 0, w - 1)
    y = np.clip(y, 0, h - 1)
    x0 = np.floor(x).astype(int)
    y0 = np.floor(y).astype(int)
    x1 = np.minimum(x0 + 1, w - 1)
    y1 = np.minimum(y0 + 1, h - 1)
    fx = (x - x0)[..., None]
    fy = (y - y0)[..., None]
    img = img.astype(np.float64)
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bot = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return top * (1 - fy) + bot * fy


def photometric(img1: np.ndarray, img2: np.ndarray, flow: np.ndarray, ok: np.ndarray) -> float:
    """Mean |img1(p) - img2(p + flow(p))| (0..1 units, bilinear) over the pixels `ok`."""
    h, w = flow.shape[:2]
    ys, xs = np.mgrid[0:h, 0:w]
    warped = bilinear(img2, xs + flow[..., 0], ys + flow[..., 1])
    err = np.abs(img1.astype(np.float64) - warped).mean(axis=2) / 255.0
    return float(err[ok].mean())


def raft_mpisintel_lists(root: Path, dstype: str = "clean"):
    """The image pairs and flows RAFT's `MpiSintel(split='training', root, dstype)` collects."""
    flow_root = os.path.join(root, "training", "flow")
    image_root = os.path.join(root, "training", dstype)
    image_list, flow_list = [], []
    for scene in os.listdir(image_root):
        images = sorted(glob.glob(os.path.join(image_root, scene, "*.png")))
        for i in range(len(images) - 1):
            image_list += [[images[i], images[i + 1]]]
        flow_list += sorted(glob.glob(os.path.join(flow_root, scene, "*.flo")))
    return image_list, flow_list


def test_sintel_export_of_4_frame_clips(tmp_path):
    exe = real_binary()
    if exe is None:
        pytest.skip("target/release/mpiflow not built (set MPIFLOW_BIN)")
    out = tmp_path / "sintel"
    subprocess.run(
        [str(exe), "generate", "--count", "2", "--frames", "4", "--format", "sintel", "--out", str(out),
         "--size", "160x120", "--objects", "0", "--preview-every", "0", "--quiet"],
        check=True, capture_output=True, text=True, timeout=600,
    )
    scenes = sorted(os.listdir(out / "training" / "clean"))
    assert len(scenes) == 2
    pairs, flows = raft_mpisintel_lists(out)
    assert len(pairs) == len(flows) == 2 * 3
    for scene in scenes:
        frames = sorted(glob.glob(str(out / "training" / "clean" / scene / "frame_*.png")))
        assert [Path(f).name for f in frames] == [f"frame_000{k}.png" for k in range(1, 5)]
        for kind, ext in (("flow", "flo"), ("occlusions", "png"), ("invalid", "png")):
            got = sorted(Path(f).name for f in glob.glob(str(out / "training" / kind / scene / "*")))
            assert got == [f"frame_000{k}.{ext}" for k in range(1, 4)], (kind, got)
        images = [read_png(f) for f in frames]
        assert all(im.shape == (120, 160, 3) and im.dtype == np.uint8 for im in images)
        for k in range(3):
            flow = read_flo(str(out / "training" / "flow" / scene / f"frame_000{k + 1}.flo"))
            assert flow.shape == (120, 160, 2) and np.isfinite(flow).all()
            occ = read_png(str(out / "training" / "occlusions" / scene / f"frame_000{k + 1}.png"))
            inv = read_png(str(out / "training" / "invalid" / scene / f"frame_000{k + 1}.png"))
            assert set(np.unique(occ)) <= {0, 255} and set(np.unique(inv)) <= {0, 255}
            ok = (inv == 0) & (occ == 0)
            assert ok.mean() > 0.25, f"{scene} pair {k + 1}: only {ok.mean():.2f} usable"
            err = photometric(images[k], images[k + 1], flow, ok)
            assert err < 0.05, f"{scene} pair {k + 1}: photometric error {err:.4f}"


def _real(server):
    if server.kind != "real":
        pytest.skip("the stand-in server has no backward flow or clips")


def test_backward_fields(server, client):
    _real(server)
    cw, ch = server.crop
    fields = ["image1", "image2", "flow", "valid", "occlusion", "flow_bw", "valid_backward", "occlusion_backward"]
    s = client.get_sample(1, crop=server.crop, fields=fields, max_objects=0)
    assert s.frames == 2
    assert s["flow_backward"].shape == (ch, cw, 2) and s["flow_backward"].dtype == np.float32
    assert s["valid_backward"].shape == s["occlusion_backward"].shape == (ch, cw)
    assert np.isfinite(s["flow_backward"]).all()
    # forward-backward consistency (bilinear lookup) on valid, non-occluded pixels
    f, b = s["flow"], s["flow_backward"].astype(np.float64)
    ys, xs = np.mgrid[0:ch, 0:cw]
    ok = (s["valid"] != 0) & (s["occlusion"] == 0)
    tx, ty = xs + f[..., 0], ys + f[..., 1]
    nx = np.clip(np.rint(tx).astype(int), 0, cw - 1)
    ny = np.clip(np.rint(ty).astype(int), 0, ch - 1)
    ok &= (s["valid_backward"][ny, nx] != 0) & (s["occlusion_backward"][ny, nx] == 0)
    back = bilinear(b, tx, ty)
    err = np.hypot(f[..., 0] + back[..., 0], f[..., 1] + back[..., 1])[ok]
    assert ok.mean() > 0.25 and err.mean() < 0.1, (ok.mean(), err.mean())
    # the same sample without the backward fields: the same forward tensors
    plain = client.get_sample(1, crop=server.crop, fields=fields[:5], max_objects=0)
    for name in fields[:5]:
        assert np.array_equal(plain[name], s[name]), name


def test_clip_tensors_and_frames_validation(server, client):
    _real(server)
    cw, ch = server.crop
    fields = ["image1", "flow", "valid", "occlusion", "flow_backward", "valid_backward", "depth1"]
    s = client.get_sample(0, crop=server.crop, fields=fields, frames=3)
    assert s.frames == 3
    assert s["images"].shape == (3, ch, cw, 3) and s["images"].dtype == np.uint8
    assert s["flows"].shape == s["flows_backward"].shape == (2, ch, cw, 2)
    assert s["valids"].shape == s["occlusions"].shape == s["valids_backward"].shape == (2, ch, cw)
    assert s["depth1"].shape == (ch, cw)
    assert "image1" not in s and "flow" not in s
    again = client.get_sample(0, crop=server.crop, fields=fields, frames=3)
    for name in s.keys():
        assert np.array_equal(again[name], s[name]), name
    for bad in (1, 9):
        with pytest.raises(grpc.RpcError) as e:
            client.get_sample(0, crop=server.crop, frames=bad)
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert "frames" in e.value.details()
