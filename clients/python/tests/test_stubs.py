"""The committed stubs are exactly what grpcio-tools makes from the repo's proto/."""
import importlib.util

import pytest

from conftest import CLIENT_ROOT


def test_stubs_are_fresh():
    pytest.importorskip("grpc_tools.protoc")
    spec = importlib.util.spec_from_file_location("gen_stubs", CLIENT_ROOT / "gen_stubs.py")
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    problems = gen.check()
    assert not problems, "stale stubs (run python clients/python/gen_stubs.py):\n" + "\n".join(problems)


def test_stub_service_matches_the_proto():
    from mpiflow._proto import mpiflow_pb2 as pb

    svc = pb.DESCRIPTOR.services_by_name["MpiFlow"]
    assert svc.full_name == "mpiflow.v1.MpiFlow"
    assert pb.DESCRIPTOR.name == "mpiflow/v1/mpiflow.proto"
    assert {m.name for m in svc.methods} == {"StreamSamples", "GetSample", "GetSamples", "UploadSources", "GetInfo"}
