"""The colour kernel of the target render (`resample=`, docs/quality.md) through the Client and
a dataset, against the real `mpiflow serve`: a kernel is part of the fingerprint, gives the same
bytes for the same address, changes image2 only through the render; an unknown kernel is
INVALID_ARGUMENT naming `resample`."""
from __future__ import annotations

import grpc
import numpy as np
import pytest

import mpiflow

FIELDS = ["image1", "image2", "flow", "valid"]


@pytest.fixture(autouse=True)
def _real_only(server):
    if server.kind != "real":
        pytest.skip("kernels are rendered by the real server")


def test_a_kernel_is_part_of_the_fingerprint_and_deterministic(server, client):
    default = client.get_sample(2, seed=5, fields=FIELDS)
    a = client.get_sample(2, seed=5, fields=FIELDS, resample="bilinear")
    b = client.get_sample(2, seed=5, fields=FIELDS, resample="bilinear")
    assert a.fingerprint != default.fingerprint
    for name in FIELDS:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    # naming the default kernel is the default dataset
    same = client.get_sample(2, seed=5, fields=FIELDS, resample="bspline3")
    assert same.fingerprint == default.fingerprint
    np.testing.assert_array_equal(same["image2"], default["image2"])


def test_the_datasets_pass_resample(server, client):
    kw = dict(seed=1, fields=FIELDS, resample="bicubic", timeout=120)
    ref = client.get_sample(2, seed=1, fields=FIELDS, resample="bicubic")
    ds = mpiflow.MPIFlowMapDataset(server.address, 4, **kw)
    np.testing.assert_array_equal(np.asarray(ds[2]["flow"]), ref["flow"].transpose(2, 0, 1))
    ds.close()
    stream = mpiflow.MPIFlowDataset(server.address, start_index=2, count=1, rank=0, world_size=1, prefetch=0, **kw)
    first = next(iter(stream))
    np.testing.assert_array_equal(np.asarray(first["flow"]), ref["flow"].transpose(2, 0, 1))


def test_an_unknown_kernel_names_the_field(server, client):
    with pytest.raises(grpc.RpcError) as e:
        client.get_sample(0, resample="nearest")
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert e.value.details().startswith("resample")
