//! The service's one error enum and its mapping to gRPC status codes (the only place where codes
//! are chosen), each status with its typed reason in the `mpiflow-reason` trailer ([`Reason`]:
//! what clients and the server's own layers decide by, never the message text), and the resume
//! cursor in the trailers of an interrupted stream.

use tonic::metadata::MetadataValue;
use tonic::{Code, Status};

use crate::failure::{echo, printable};
use crate::sample::error::SampleError;
use crate::source::SourceError;

/// Trailer key of the next index an interrupted stream would have sent.
pub const NEXT_INDEX_TRAILER: &str = "mpiflow-next-index";
/// Trailer key of the `start_index` that resumes an interrupted stream.
pub const RESUME_START_TRAILER: &str = "mpiflow-resume-start-index";
/// Trailer key of a failure's [`Reason`].
pub const REASON_TRAILER: &str = "mpiflow-reason";

/// Why a call failed, as a word on the wire (the `mpiflow-reason` trailer): whether trying again
/// (later, or on another replica) can help is decided by it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Reason {
    InvalidArgument,
    UnknownDataset,
    FingerprintMismatch,
    DatasetUnusable,
    /// `max_streams`, or a client's half of it.
    TooManyStreams,
    /// `max_random_access_calls`.
    TooManyCalls,
    /// A request's largest sample is over the message limit or the byte budget.
    SampleTooLarge,
    /// An upload's size, slot or buffer limit.
    UploadLimit,
    /// A request message over `max_request_bytes`.
    RequestTooLarge,
    /// A request message that is not valid protobuf.
    MalformedRequest,
    Draining,
    /// A sample that cannot be made (the same on every replica).
    SampleFailed,
    Unimplemented,
    Internal,
}

impl Reason {
    pub const ALL: [Reason; 14] = [
        Reason::InvalidArgument,
        Reason::UnknownDataset,
        Reason::FingerprintMismatch,
        Reason::DatasetUnusable,
        Reason::TooManyStreams,
        Reason::TooManyCalls,
        Reason::SampleTooLarge,
        Reason::UploadLimit,
        Reason::RequestTooLarge,
        Reason::MalformedRequest,
        Reason::Draining,
        Reason::SampleFailed,
        Reason::Unimplemented,
        Reason::Internal,
    ];

    pub fn as_str(self) -> &'static str {
        match self {
            Reason::InvalidArgument => "invalid-argument",
            Reason::UnknownDataset => "unknown-dataset",
            Reason::FingerprintMismatch => "fingerprint-mismatch",
            Reason::DatasetUnusable => "dataset-unusable",
            Reason::TooManyStreams => "too-many-streams",
            Reason::TooManyCalls => "too-many-calls",
            Reason::SampleTooLarge => "sample-too-large",
            Reason::UploadLimit => "upload-limit",
            Reason::RequestTooLarge => "request-too-large",
            Reason::MalformedRequest => "malformed-request",
            Reason::Draining => "draining",
            Reason::SampleFailed => "sample-failed",
            Reason::Unimplemented => "unimplemented",
            Reason::Internal => "internal",
        }
    }

    /// Whether another try (later, or on another replica) may succeed: the server's momentary
    /// limits and its drain, not what the request asks.
    pub fn retryable(self) -> bool {
        matches!(
            self,
            Reason::TooManyStreams | Reason::TooManyCalls | Reason::UploadLimit | Reason::Draining | Reason::Internal
        )
    }

    /// The reason in a status's trailers (or headers, for a trailers-only reply).
    pub fn of(status: &Status) -> Option<Reason> {
        let v = status.metadata().get(REASON_TRAILER)?.to_str().ok()?;
        Reason::ALL.into_iter().find(|r| r.as_str() == v)
    }

    /// Puts the reason into a status's trailers.
    pub fn set(self, status: &mut Status) {
        status.metadata_mut().insert(REASON_TRAILER, MetadataValue::from_static(self.as_str()));
    }
}

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
    /// A limit of the server (RESOURCE_EXHAUSTED), with its reason.
    #[error("{1}")]
    LimitExceeded(Reason, String),
    #[error("the server is shutting down: reconnect to another replica")]
    Draining,
    /// A sample could not be made.
    #[error("sample {index}: {source}")]
    Generation {
        index: u64,
        #[source]
        source: SampleError,
    },
    /// Making a sample panicked (a defect, caught on the worker): the item and the panic's own
    /// message are named, and the worker goes on with the next job.
    #[error("sample {index} of dataset {} (source item {item}): the worker panicked: {message}", echo(.dataset))]
    Panicked { dataset: String, index: u64, item: String, message: String },
    /// A call's request did not arrive whole within the request deadline (headers sent, the
    /// body trickled or withheld: `service::reply`).
    #[error("the request did not arrive whole within {seconds} s (idle_connection_timeout_s)")]
    RequestIncomplete { seconds: f64 },
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
            ServiceError::InvalidArgument { .. } | ServiceError::RequestIncomplete { .. } => Code::InvalidArgument,
            ServiceError::UnknownDataset { .. } => Code::NotFound,
            ServiceError::FingerprintMismatch { .. } | ServiceError::Unusable { .. } => Code::FailedPrecondition,
            ServiceError::TooManyStreams { .. } | ServiceError::LimitExceeded(..) => Code::ResourceExhausted,
            ServiceError::Draining => Code::Unavailable,
            ServiceError::Generation { .. }
            | ServiceError::Panicked { .. }
            | ServiceError::Internal(_)
            | ServiceError::Config(_) => Code::Internal,
            ServiceError::Unimplemented(_) => Code::Unimplemented,
        }
    }
}

impl ServiceError {
    /// The error's [`Reason`].
    pub fn reason(&self) -> Reason {
        match self {
            ServiceError::InvalidArgument { .. } => Reason::InvalidArgument,
            ServiceError::RequestIncomplete { .. } => Reason::MalformedRequest,
            ServiceError::UnknownDataset { .. } => Reason::UnknownDataset,
            ServiceError::FingerprintMismatch { .. } => Reason::FingerprintMismatch,
            ServiceError::Unusable { .. } => Reason::DatasetUnusable,
            ServiceError::TooManyStreams { .. } => Reason::TooManyStreams,
            ServiceError::LimitExceeded(r, _) => *r,
            ServiceError::Draining => Reason::Draining,
            ServiceError::Generation { .. } => Reason::SampleFailed,
            ServiceError::Unimplemented(_) => Reason::Unimplemented,
            ServiceError::Panicked { .. } | ServiceError::Internal(_) | ServiceError::Config(_) => Reason::Internal,
        }
    }
}

/// The message of a caught panic's payload (a `&str` or a `String`, as `panic!` makes them).
pub fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    match (payload.downcast_ref::<&str>(), payload.downcast_ref::<String>()) {
        (Some(s), _) => (*s).to_string(),
        (_, Some(s)) => s.clone(),
        _ => "(no message)".to_string(),
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
            SourceError::Limit(m) => ServiceError::LimitExceeded(Reason::UploadLimit, m),
            SourceError::Upload { field, message } => ServiceError::InvalidArgument { field, message },
            other => ServiceError::invalid("chunks", other.to_string()),
        }
    }
}

/// A failure reading a client stream's next message: over the message limit (tonic's
/// OUT_OF_RANGE, the only status its decoder gives that code) is RESOURCE_EXHAUSTED (gRPC's code
/// for a request too large), anything else is the `chunks`' fault.
pub fn from_request_stream(status: Status) -> ServiceError {
    if status.code() == Code::OutOfRange {
        ServiceError::LimitExceeded(Reason::RequestTooLarge, format!("chunks: {}", status.message()))
    } else {
        ServiceError::invalid("chunks", status.message().to_string())
    }
}

/// The code and reason of the error table for a status tonic made itself, before any handler
/// ran (a trailers-only reply without a reason): its decoder's OUT_OF_RANGE (a request over the
/// decoding limit) is RESOURCE_EXHAUSTED, gRPC's code for a request too large; its INTERNAL (a
/// request message that is not valid protobuf, or ends early) is INVALID_ARGUMENT, the client's
/// fault (the table keeps INTERNAL for a sample that could not be made). None = keep the code.
pub fn transport_code(code: Code) -> Option<(Code, Reason)> {
    match code {
        Code::OutOfRange => Some((Code::ResourceExhausted, Reason::RequestTooLarge)),
        Code::Internal => Some((Code::InvalidArgument, Reason::MalformedRequest)),
        _ => None,
    }
}

/// Most characters of a status message: a message never grows with what a client sent (a
/// gRPC client refuses metadata over its limit, which would hide the real error).
pub const MAX_STATUS_CHARS: usize = 2048;

impl From<ServiceError> for Status {
    fn from(e: ServiceError) -> Self {
        let mut status = Status::new(e.code(), printable(&e.to_string(), MAX_STATUS_CHARS));
        e.reason().set(&mut status);
        status
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
            assert!(Reason::of(&status).is_some(), "{status:?}");
        }
    }

    /// Every reason is its own word on the wire and reads back from a status.
    #[test]
    fn reasons_round_trip_through_a_status() {
        let words: std::collections::HashSet<&str> = Reason::ALL.iter().map(|r| r.as_str()).collect();
        assert_eq!(words.len(), Reason::ALL.len());
        for r in Reason::ALL {
            let mut s = Status::internal("x");
            r.set(&mut s);
            assert_eq!(Reason::of(&s), Some(r));
        }
        assert_eq!(Reason::of(&Status::internal("sample 3: no reason trailer")), None);
    }

    /// The Python client retries exactly the reasons the server declares retryable.
    #[test]
    fn the_python_client_retries_the_retryable_reasons() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/clients/python/mpiflow/errors.py");
        let text = std::fs::read_to_string(path).expect("the Python client's errors module");
        let line = text.lines().find(|l| l.starts_with("RETRYABLE_REASONS")).expect("RETRYABLE_REASONS");
        let python: std::collections::BTreeSet<&str> = line.split('"').skip(1).step_by(2).collect();
        let rust: std::collections::BTreeSet<&str> =
            Reason::ALL.into_iter().filter(|r| r.retryable()).map(Reason::as_str).collect();
        assert_eq!(python, rust, "{path}: RETRYABLE_REASONS");
    }
}
