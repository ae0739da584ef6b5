//! The service's one error enum and its mapping to gRPC status codes (the only place where codes
//! are chosen), with the resume cursor in the trailers of an interrupted stream.

use tonic::metadata::MetadataValue;
use tonic::{Code, Status};

use crate::failure::{echo, printable};
use crate::sample::error::SampleError;
use crate::source::SourceError;

/// Trailer key of the next index an interrupted stream would have sent.
pub const NEXT_INDEX_TRAILER: &str = "mpiflow-next-index";
/// Trailer key of the `start_index` that resumes an interrupted stream.
pub const RESUME_START_TRAILER: &str = "mpiflow-resume-start-index";

#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    /// A request field is out of range or malformed; the message starts with the field's name.
    #[error("{field}: {message}")]
    InvalidArgument { field: &'static str, message: String },
    /// The name is echoed short and escaped ([`echo`]).
    #[error("unknown dataset {} (GetInfo lists the datasets)", echo(.0))]
    UnknownDataset(String),
    #[error(
        "fingerprint: the request expects dataset {} to have fingerprint {requested:016x}, but it has \
         {actual:016x} (different sources or sample configuration)",
        echo(dataset)
    )]
    FingerprintMismatch { dataset: String, requested: u64, actual: u64 },
    #[error("too many streams: {limit} are open (max_streams)")]
    TooManyStreams { limit: usize },
    #[error("{0}")]
    LimitExceeded(String),
    #[error("the server is shutting down: reconnect to another replica")]
    Draining,
    /// A sample could not be made.
    #[error("sample {index}: {source}")]
    Generation {
        index: u64,
        #[source]
        source: SampleError,
    },
    #[error("{0}")]
    Unimplemented(String),
    /// A start-up configuration problem (never sent to clients during serving).
    #[error("configuration: {0}")]
    Config(String),
    #[error("internal error: {0}")]
    Internal(String),
}

impl ServiceError {
    pub fn invalid(field: &'static str, message: impl Into<String>) -> Self {
        ServiceError::InvalidArgument { field, message: message.into() }
    }

    pub fn code(&self) -> Code {
        match self {
            ServiceError::InvalidArgument { .. } => Code::InvalidArgument,
            ServiceError::UnknownDataset(_) => Code::NotFound,
            ServiceError::FingerprintMismatch { .. } => Code::FailedPrecondition,
            ServiceError::TooManyStreams { .. } | ServiceError::LimitExceeded(_) => Code::ResourceExhausted,
            ServiceError::Draining => Code::Unavailable,
            ServiceError::Generation { .. } | ServiceError::Internal(_) | ServiceError::Config(_) => Code::Internal,
            ServiceError::Unimplemented(_) => Code::Unimplemented,
        }
    }

    /// The status of a stream that ends with this error, with the resume cursor in its trailers.
    pub fn into_status_with_cursor(self, next_index: u64, resume_start_index: u64) -> Status {
        let mut status: Status = self.into();
        with_cursor(&mut status, next_index, resume_start_index);
        status
    }
}

/// Puts the resume cursor into a status's trailer metadata.
pub fn with_cursor(status: &mut Status, next_index: u64, resume_start_index: u64) {
    let md = status.metadata_mut();
    md.insert(NEXT_INDEX_TRAILER, MetadataValue::from(next_index));
    md.insert(RESUME_START_TRAILER, MetadataValue::from(resume_start_index));
}

/// Reads the resume cursor (`next_index`, `resume_start_index`) from a status's trailers.
pub fn cursor_of(status: &Status) -> Option<(u64, u64)> {
    let get = |k: &str| status.metadata().get(k)?.to_str().ok()?.parse::<u64>().ok();
    Some((get(NEXT_INDEX_TRAILER)?, get(RESUME_START_TRAILER)?))
}

/// An upload store error as the service's: limits are RESOURCE_EXHAUSTED, a malformed stream
/// names its chunk field (`dataset`, `name`), the rest are the `chunks`' fault.
impl From<SourceError> for ServiceError {
    fn from(e: SourceError) -> Self {
        match e {
            SourceError::Limit(m) => ServiceError::LimitExceeded(m),
            SourceError::Upload { field, message } => ServiceError::InvalidArgument { field, message },
            other => ServiceError::invalid("chunks", other.to_string()),
        }
    }
}

/// The message tonic gives a request over the decoding limit (with OUT_OF_RANGE).
const TOO_LARGE: &str = "decoded message length too large";

/// A failure reading a client stream's next message: over the message limit is
/// RESOURCE_EXHAUSTED (gRPC's code for a request too large), anything else is the `chunks`' fault.
pub fn from_request_stream(status: Status) -> ServiceError {
    if status.code() == Code::OutOfRange && status.message().contains(TOO_LARGE) {
        ServiceError::LimitExceeded(format!("chunks: {}", status.message()))
    } else {
        ServiceError::invalid("chunks", status.message().to_string())
    }
}

/// The response layer of the server: tonic answers a unary or server-streaming request over the
/// decoding limit with OUT_OF_RANGE before any handler runs; by gRPC's convention (and the error
/// table of docs/api.md) a request too large is RESOURCE_EXHAUSTED, so the status header of such
/// a (trailers-only) response is rewritten. Every other response passes unchanged.
pub fn oversized_is_resource_exhausted<B>(
    mut response: tonic::codegen::http::Response<B>,
) -> tonic::codegen::http::Response<B> {
    let h = response.headers();
    let out_of_range = h.get("grpc-status").is_some_and(|v| v.as_bytes() == b"11");
    let too_large =
        h.get("grpc-message").and_then(|v| v.to_str().ok()).is_some_and(|m| percent_decoded_contains(m, TOO_LARGE));
    if out_of_range && too_large {
        response.headers_mut().insert("grpc-status", tonic::codegen::http::HeaderValue::from_static("8"));
    }
    response
}

/// Whether a `grpc-message` header (percent-encoded) contains `needle` (plain ASCII).
fn percent_decoded_contains(header: &str, needle: &str) -> bool {
    let mut plain = String::with_capacity(header.len());
    let b = header.as_bytes();
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%' && i + 2 < b.len() {
            if let Ok(v) = u8::from_str_radix(&header[i + 1..i + 3], 16) {
                plain.push(char::from(v));
                i += 3;
                continue;
            }
        }
        plain.push(char::from(b[i]));
        i += 1;
    }
    plain.contains(needle)
}

/// Most characters of a status message: a message never grows with what a client sent (a
/// gRPC client refuses metadata over its limit, which would hide the real error).
pub const MAX_STATUS_CHARS: usize = 2048;

impl From<ServiceError> for Status {
    fn from(e: ServiceError) -> Self {
        Status::new(e.code(), printable(&e.to_string(), MAX_STATUS_CHARS))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::source::FailureKind;

    #[test]
    fn source_errors_map_to_their_field_and_code() {
        let cases = [
            (
                SourceError::Upload { field: "dataset", message: "empty name".into() },
                Code::InvalidArgument,
                "dataset: empty name",
            ),
            (SourceError::Upload { field: "name", message: "unnamed".into() }, Code::InvalidArgument, "name: unnamed"),
            (SourceError::Limit("upload: too big".into()), Code::ResourceExhausted, "upload: too big"),
            (SourceError::file("x.png", FailureKind::Decode, "bad"), Code::InvalidArgument, "chunks: x.png: bad"),
        ];
        for (e, code, message) in cases {
            let status: Status = ServiceError::from(e).into();
            assert_eq!((status.code(), status.message()), (code, message));
        }
    }
}
