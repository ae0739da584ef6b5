"""The client's errors, and which failed calls another replica or a later try may answer."""
from __future__ import annotations

import re

import grpc

__all__ = ["MpiFlowError", "NotReadyError", "is_retryable"]

_RETRYABLE = {
    grpc.StatusCode.UNAVAILABLE,
    grpc.StatusCode.UNKNOWN,
    grpc.StatusCode.INTERNAL,
    grpc.StatusCode.ABORTED,
    grpc.StatusCode.CANCELLED,
    grpc.StatusCode.DEADLINE_EXCEEDED,
    grpc.StatusCode.RESOURCE_EXHAUSTED,
}



class MpiFlowError(RuntimeError):
    """An mpiflow call that failed for good (bad request, or no replica within the retry time)."""


class NotReadyError(MpiFlowError, TimeoutError):
    """No replica reported SERVING within the timeout."""


def is_retryable(err: BaseException) -> bool:
    """Whether a failed call may succeed on another replica or later (a transport failure, a
    draining or overloaded server) rather than being refused for what it asks."""
    if not isinstance(err, grpc.RpcError) or not hasattr(err, "code"):
        return False
    code = err.code()
    if code == grpc.StatusCode.RESOURCE_EXHAUSTED:
        details = (err.details() or "").lower()
        # The client's own receive limit, and a request whose sample is too large for the
        # server's limits (refused before any work): the same on every replica.
        return "larger than max" not in details and "sample too large" not in details
    if code == grpc.StatusCode.INTERNAL:
        # "sample N: ..." = that sample cannot be made (the same on every replica); other
        # INTERNAL errors come from the transport (a reset stream, a broken connection).
        return not re.match(r"sample \d+:", err.details() or "")
    return code in _RETRYABLE
