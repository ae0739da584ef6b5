"""Rectified stereo pairs (motion preset `stereo`, FIELD_DISPARITY, `--format stereo`) against
the real `mpiflow`: the disparity over gRPC is -u of the flow with v = 0; the exported folders
load with the SceneFlow PFM reader that RAFT-Stereo uses (written out here from the format, not
taken from mpiflow), and the right view warped by the disparity matches the left view."""
from __future__ import annotations

import re
import subprocess

import numpy as np
import pytest
from PIL import Image

from conftest import real_binary


@pytest.fixture(autouse=True)
def _real_only(server):
    if server.kind != "real":
        pytest.skip("stereo pairs are made by the real server")


def read_pfm(path):
    """SceneFlow's readPFM (as in RAFT-Stereo's frame_utils): header, size, scale whose sign is
    the byte order, rows stored bottom to top."""
    with open(path, "rb") as f:
        header = f.readline().rstrip()
        assert header in (b"PF", b"Pf"), header
        m = re.match(rb"^(\d+)\s(\d+)\s$", f.readline())
        width, height = map(int, m.groups())
        scale = float(f.readline().rstrip())
        data = np.fromfile(f, ("<" if scale < 0 else ">") + "f")
    shape = (height, width, 3) if header == b"PF" else (height, width)
    return np.flipud(np.reshape(data, shape))


def test_disparity_over_grpc_is_minus_u(client):
    s = client.get_sample(2, seed=1, fields=["image1", "image2", "flow", "valid", "disparity"],
                          motion_preset="stereo")
    d, flow = s["disparity"], s["flow"]
    assert d.dtype == np.float32 and d.shape == flow.shape[:2]
    np.testing.assert_array_equal(flow[..., 1], 0.0)
    np.testing.assert_array_equal(d, -flow[..., 0])
    assert (d >= 0).all() and d.max() > 0
    assert s.camera.law == "stereo" and list(s.camera.translation)[1:] == [0.0, 0.0]


def test_exported_stereo_folders_load_with_the_sceneflow_reader(tmp_path):
    exe = real_binary()
    out = tmp_path / "stereo"
    subprocess.run([str(exe), "generate", "--count", "2", "--size", "160x120", "--preset", "stereo",
                    "--format", "stereo", "--out", str(out), "--quiet"], check=True, timeout=600)
    for key in ("00000000", "00000001"):
        left = np.asarray(Image.open(out / "left" / f"{key}.png"), dtype=np.float64)
        right = np.asarray(Image.open(out / "right" / f"{key}.png"), dtype=np.float64)
        d = read_pfm(out / "disparity" / f"{key}.pfm")
        valid = np.asarray(Image.open(out / "valid" / f"{key}.png")) > 0
        occ = np.asarray(Image.open(out / "occlusion" / f"{key}.png")) > 0
        h, w = d.shape
        assert left.shape == right.shape == (h, w, 3) and (h, w) == (120, 160)
        assert np.isfinite(d).all() and (d >= 0).all()
        # the right view at x - d (linear in x) reproduces the left view where the pixel is seen
        ys, xs = np.mgrid[0:h, 0:w]
        x2 = xs - d
        ok = valid & ~occ & (x2 >= 0) & (x2 <= w - 1)
        x0 = np.clip(np.floor(x2).astype(int), 0, w - 2)
        f = (x2 - x0)[..., None]
        warped = (1 - f) * right[ys, x0] + f * right[ys, x0 + 1]
        err = np.abs(warped - left)[ok].mean() / 255.0
        assert ok.mean() > 0.5 and err < 0.03, (ok.mean(), err)
