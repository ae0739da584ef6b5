"""The client's errors, and which failed calls another replica or a later try may answer."""
from __future__ import annotations

import grpc

__all__ = ["MpiFlowError", "NotReadyError", "is_retryable", "reason_of"]

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


#: The trailer that names why the server refused or failed a call (the server's `Reason`).
REASON_TRAILER = "mpiflow-reason"

#: Reasons another try (later, or on another replica) may answer: the server's momentary limits
#: and its drain; every other reason is about what the request asks, the same on every replica.
RETRYABLE_REASONS = frozenset({"too-many-streams", "too-many-calls", "upload-limit", "draining", "internal"})


def reason_of(err: BaseException) -> str | None:
    """The server's reason for a failed call (its `mpiflow-reason` trailer), or None when the
    failure did not come from the server's error table (the transport, the client's own limits)."""
    trailing = getattr(err, "trailing_metadata", None)
    if not callable(trailing):
        return None
    for key, value in trailing() or ():
        if key == REASON_TRAILER:
            return value.decode() if isinstance(value, bytes) else str(value)
    return None


def is_retryable(err: BaseException) -> bool:
    """Whether a failed call may succeed on another replica or later (a transport failure, a
    draining or overloaded server) rather than being refused for what it asks. Decided by the
    server's reason when it gave one, else by the code (never by the message text)."""
    if not isinstance(err, grpc.RpcError) or not hasattr(err, "code"):
        return False
    reason = reason_of(err)
    if reason is not None:
        return reason in RETRYABLE_REASONS
    code = err.code()
    if code == grpc.StatusCode.RESOURCE_EXHAUSTED:
        # without a reason it is the client's own receive limit: the same on every replica
        return False
    return code in _RETRYABLE
