"""grpc.health.v1 Check without extra dependencies.

The two messages are tiny (HealthCheckRequest{string service = 1},
HealthCheckResponse{ServingStatus status = 1}), so they are encoded by hand instead of pulling in
grpcio-health-checking.
"""
from __future__ import annotations

CHECK_METHOD = "/grpc.health.v1.Health/Check"

UNKNOWN = "UNKNOWN"
SERVING = "SERVING"
NOT_SERVING = "NOT_SERVING"
SERVICE_UNKNOWN = "SERVICE_UNKNOWN"
_STATUS = {0: UNKNOWN, 1: SERVING, 2: NOT_SERVING, 3: SERVICE_UNKNOWN}


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        b = n & 0x7F
        n >>= 7
        if n:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)


def _read_varint(buf: bytes, pos: int):
    shift = 0
    value = 0
    while True:
        if pos >= len(buf):
            raise ValueError("truncated varint")
        b = buf[pos]
        pos += 1
        value |= (b & 0x7F) << shift
        if not b & 0x80:
            return value, pos
        shift += 7
        if shift > 63:
            raise ValueError("varint too long")


def encode_request(service: str = "") -> bytes:
    """HealthCheckRequest{service} in the protobuf wire format."""
    raw = service.encode("utf-8")
    if not raw:
        return b""
    return b"\x0a" + _varint(len(raw)) + raw


def decode_response(buf: bytes) -> str:
    """The status name of a HealthCheckResponse (unknown fields are skipped)."""
    pos = 0
    status = 0
    while pos < len(buf):
        key, pos = _read_varint(buf, pos)
        num, wire = key >> 3, key & 7
        if wire == 0:
            v, pos = _read_varint(buf, pos)
            if num == 1:
                status = v
        elif wire == 2:
            n, pos = _read_varint(buf, pos)
            pos += n
        elif wire == 1:
            pos += 8
        elif wire == 5:
            pos += 4
        else:
            raise ValueError(f"unsupported wire type {wire}")
    return _STATUS.get(status, UNKNOWN)
