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
    #[error("unknown dataset {}: the datasets are {} (GetInfo lists them)", echo(.name), .known)]
    UnknownDataset { name: String, known: String },
    #[error(
        "fingerprint: the request expects dataset {} to have fingerprint {requested:016x}, but it has \
         {actual:016x} (different sources or sample configuration)",
        echo(dataset)
    )]
    FingerprintMismatch { dataset: String, requested: u64, actual: u64 },
    /// A dataset that cannot make scenes with the configured models (e.g. photos without depth
    /// and no depth model): refused at start-up (exit status 2) or when it is uploaded. The
    /// message names the fix.
    #[error("dataset {}: {source}", echo(dataset))]
    Unusable {
        dataset: String,
        #[source]
        source: crate::scene::SceneError,
    },
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
            ServiceError::UnknownDataset { .. } => Code::NotFound,
            ServiceError::FingerprintMismatch { .. } | ServiceError::Unusable { .. } => Code::FailedPrecondition,
            ServiceError::TooManyStreams { .. } | ServiceError::LimitExceeded(_) => Code::ResourceExhausted,
            ServiceError::Draining => Code::Unavailable,
            ServiceError::Generation { .. } | ServiceError::Internal(_) | ServiceError::Config(_) => Code::Internal,
            ServiceError::Unimplemented(_) => Code::Unimplemented,
        }
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

/// What tonic says of a request message that is not valid protobuf (or ends early): the client's
/// fault, INVALID_ARGUMENT by the error table, not the INTERNAL tonic gives it.
const MALFORMED: [&str; 3] =
    ["failed to decode Protobuf message", "Unexpected EOF decoding stream", "received message with compressed-flag"];

/// The code of the error table for a status tonic made before any handler ran (a trailers-only
/// reply): a request over the decoding limit is RESOURCE_EXHAUSTED (gRPC's code for a request
/// too large; tonic says OUT_OF_RANGE), a malformed request message INVALID_ARGUMENT (tonic says
/// INTERNAL, which the table keeps for a sample that could not be made). None = keep the code.
pub fn transport_code(code: Code, message: &str) -> Option<Code> {
    match code {
        Code::OutOfRange if message.contains(TOO_LARGE) => Some(Code::ResourceExhausted),
        Code::Internal if MALFORMED.iter().any(|m| message.contains(m)) => Some(Code::InvalidArgument),
        _ => None,
    }
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
