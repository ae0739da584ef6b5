"""Generated gRPC stubs of proto/mpiflow/v1/mpiflow.proto (see gen_stubs.py; do not edit them)."""
from . import mpiflow_pb2, mpiflow_pb2_grpc

__all__ = ["mpiflow_pb2", "mpiflow_pb2_grpc"]
