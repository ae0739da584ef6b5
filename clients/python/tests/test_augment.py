"""Server-side augmentation (`augment=`, docs/augment.md) through the Client and both datasets,
against the real `mpiflow serve`: a RAFT preset gives its crop and the same bytes for the same
address; the dict form is the JSON form; a bad key is INVALID_ARGUMENT naming it."""
from __future__ import annotations

import json

import grpc
import numpy as np
import pytest

import mpiflow

FIELDS = ["image1", "image2", "flow", "valid"]


@pytest.fixture(autouse=True)
def _real_only(server):
    if server.kind != "real":
        pytest.skip("augmentation is made by the real server")


def test_presets_are_deterministic_and_recorded(server, client):
    a = client.get_sample(3, seed=2, fields=FIELDS, augment="raft-chairs")
    b = client.get_sample(3, seed=2, fields=FIELDS, augment="raft-chairs")
    assert a["image1"].shape == (368, 496, 3) and a["flow"].shape == (368, 496, 2)
    for name in FIELDS:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    record = json.loads(a.augment)
    assert record["preset"] == "raft-chairs" and len(record["crop"]) == 4
    assert np.isfinite(a["flow"]).all()
    plain = client.get_sample(3, seed=2, fields=FIELDS)
    assert plain.augment == "" and plain.fingerprint == a.fingerprint


def test_dict_form_equals_json_text_and_crop_replaces_the_presets(server, client):
    spec = {"preset": "raft-things", "eraser_prob": 0.0}
    kw = dict(seed=4, fields=FIELDS, crop=(200, 100))
    a = client.get_sample(1, augment=spec, **kw)
    b = client.get_sample(1, augment=json.dumps(spec), **kw)
    assert a["image1"].shape == (100, 200, 3)
    for name in FIELDS:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    assert json.loads(a.augment)["preset"] == "raft-things+json"


def test_datasets_pass_augment_and_agree_with_the_client(server, client):
    kw = dict(seed=6, fields=FIELDS, augment="raft-kitti", crop=(240, 96), timeout=120)
    ds = mpiflow.MPIFlowMapDataset(server.address, 4, **kw)
    item = ds[2]
    ref = client.get_sample(2, seed=6, fields=FIELDS, augment="raft-kitti", crop=(240, 96))
    np.testing.assert_array_equal(np.asarray(item["flow"]), ref["flow"].transpose(2, 0, 1))
    stream = mpiflow.MPIFlowDataset(server.address, start_index=2, count=1, rank=0, world_size=1, prefetch=0, **kw)
    first = next(iter(stream))
    np.testing.assert_array_equal(np.asarray(first["flow"]), np.asarray(item["flow"]))
    ds.close()


def test_bad_augment_names_the_key(server, client):
    with pytest.raises(grpc.RpcError) as e:
        client.get_sample(0, augment={"preset": "raft-chairs", "hue": 2})
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert e.value.details().startswith("augment.hue")
    with pytest.raises(TypeError):
        client.get_sample(0, augment=3)
