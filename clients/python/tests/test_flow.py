"""flow_to_image against the colour wheel `flow-vis` draws (tests/data/colorwheel), and the `.flo`
files of read_flo / write_flo against the ones the real server's `mpiflow pull --out` writes."""
from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest

import mpiflow
from mpiflow.flow import flow_uv_to_colors, make_colorwheel

from conftest import REPO, real_binary

WHEEL = REPO / "tests" / "data" / "colorwheel"


def png(name: str) -> np.ndarray:
    Image = pytest.importorskip("PIL.Image")
    return np.asarray(Image.open(WHEEL / name).convert("RGB"))


def test_flow_to_image_draws_the_wheel_as_flow_vis_draws_it():
    uv = np.load(WHEEL / "wheel_input_uv.npy")
    assert np.array_equal(make_colorwheel(), np.load(WHEEL / "colorwheel_55x3.npy"))
    assert np.array_equal(mpiflow.flow_to_image(uv), png("wheel_flow_to_color_normalized.png"))
    raw = flow_uv_to_colors(uv[..., 0], uv[..., 1])
    assert np.array_equal(raw, png("wheel_flow_uv_to_colors_unnormalized.png"))


def test_flow_to_image_takes_channels_first_a_fixed_scale_and_refuses_other_shapes():
    uv = np.load(WHEEL / "wheel_input_uv.npy")
    hwc = mpiflow.flow_to_image(uv)
    chw = mpiflow.flow_to_image(np.ascontiguousarray(uv.transpose(2, 0, 1)))
    assert chw.shape == (3, 257, 257) and np.array_equal(chw.transpose(1, 2, 0), hwc)
    # zero flow is white; a fixed scale saturates only at the rim
    assert (mpiflow.flow_to_image(np.zeros((4, 5, 2), np.float32)) == 255).all()
    half = mpiflow.flow_to_image(uv, max_flow=2.0)
    assert half[128, 128].tolist() == [255, 255, 255] and half[128, 256].min() > hwc[128, 256].min()
    # a non-finite vector is black and does not set the scale
    bad = uv.copy()
    bad[0, 0] = np.nan
    assert mpiflow.flow_to_image(bad)[0, 0].tolist() == [0, 0, 0]
    assert np.array_equal(mpiflow.flow_to_image(bad)[1:], hwc[1:])
    with pytest.raises(ValueError, match=r"\[H, W, 2\]"):
        mpiflow.flow_to_image(np.zeros((4, 5, 3)))


def test_flo_files_round_trip_and_a_bad_file_is_named(tmp_path: Path):
    flow = np.random.default_rng(0).normal(size=(6, 7, 2)).astype(np.float32)
    p = tmp_path / "a.flo"
    mpiflow.write_flo(p, flow)
    assert p.read_bytes()[:4] == b"PIEH" and p.stat().st_size == 12 + 6 * 7 * 8
    assert np.array_equal(mpiflow.read_flo(p), flow)
    mpiflow.write_flo(p, flow.transpose(2, 0, 1))
    assert np.array_equal(mpiflow.read_flo(p), flow)
    cut = tmp_path / "cut.flo"
    cut.write_bytes(p.read_bytes()[:-8])
    with pytest.raises(ValueError, match="cut.flo: a 7 x 6 .flo file holds 348 bytes, this one 340"):
        mpiflow.read_flo(cut)
    other = tmp_path / "other.flo"
    other.write_bytes(b"\x89PNG" + bytes(20))
    with pytest.raises(ValueError, match="other.flo: not a .flo file"):
        mpiflow.read_flo(other)


def test_a_served_flow_is_the_flo_file_pull_writes(server, client, tmp_path: Path):
    if server.kind != "real":
        pytest.skip("the real server's pull")
    s = client.get_sample(0, seed=0)
    out = tmp_path / "pulled"
    r = subprocess.run(
        [str(real_binary()), "pull", "--addr", server.address, "--count", "1", "--out", str(out)],
        capture_output=True, text=True, timeout=300,
    )
    assert r.returncode == 0, r.stderr
    pulled = out / "00000000_flow.flo"
    assert np.array_equal(mpiflow.read_flo(pulled), s["flow"])
    mine = tmp_path / "mine.flo"
    mpiflow.write_flo(mine, s["flow"])
    assert mine.read_bytes() == pulled.read_bytes()
    rgb = mpiflow.flow_to_image(s["flow"])
    assert rgb.shape == (s.height, s.width, 3) and rgb.dtype == np.uint8
