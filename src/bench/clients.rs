//! What the clients of `mpiflow bench soak` share (the soak's own and the hostile ones): their
//! counters, the error table, and the fields they ask for.

use std::collections::BTreeMap;
use std::sync::atomic::AtomicU64;
use std::sync::Mutex;

use crate::service::pb;

/// Every field of a pair: what the hostile and stalled clients ask for.
pub fn all_fields() -> Vec<i32> {
    // every field of a pair of the default law (the disparity needs a stereo law)
    let of_a_pair = |f: pb::Field| f != pb::Field::Unspecified && f != pb::Field::Disparity;
    (1..64).filter(|&v| pb::Field::try_from(v).is_ok_and(of_a_pair)).collect()
}

/// What the clients share: counters and the error table.
#[derive(Default)]
pub struct Shared {
    pub(super) fast_samples: AtomicU64,
    pub(super) lost: AtomicU64,
    pub(super) repeated: AtomicU64,
    pub(super) slow_samples: AtomicU64,
    pub(super) stalled_streams: AtomicU64,
    pub(super) cancelled_streams: AtomicU64,
    pub(super) uploads: AtomicU64,
    pub(super) unary_samples: AtomicU64,
    pub(super) unread_calls: AtomicU64,
    pub(super) idle_closed: AtomicU64,
    pub(super) watches: AtomicU64,
    pub(super) window_streams: AtomicU64,
    /// The fast clients' longest wait for a message, µs.
    pub(super) fast_max_gap_us: AtomicU64,
    pub(super) errors: Mutex<(BTreeMap<String, u64>, u64, Vec<String>)>,
}

impl Shared {
    /// Counts an error of a client kind; RESOURCE_EXHAUSTED is expected unless `strict`.
    pub(super) fn error(&self, kind: &str, code: &str, message: &str, expected: bool) {
        let mut e = self.errors.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        *e.0.entry(format!("{kind}: {code}")).or_insert(0) += 1;
        if !expected {
            e.1 += 1;
            if e.2.len() < 5 {
                e.2.push(format!("{kind}: {code}: {}", crate::failure::printable(message, 200)));
            }
        }
    }

    /// A client of `addr` from the local address `from` (the system's choice if None); a failure
    /// counted as `kind`'s unexpected error; None then, or once `until` has passed.
    pub(super) async fn connect(
        &self,
        kind: &str,
        addr: &str,
        from: Option<std::net::IpAddr>,
        until: tokio::time::Instant,
    ) -> Option<crate::service::client::Client> {
        let options = crate::service::client::ClientOptions { local_address: from, ..Default::default() };
        match tokio::time::timeout_at(until, crate::service::client::connect_with(addr, &options)).await {
            Ok(Ok(c)) => Some(c),
            Ok(Err(e)) => {
                self.error(kind, "connect", &e.to_string(), false);
                None
            }
            Err(_) => None,
        }
    }

    pub(super) fn status(&self, kind: &str, s: &tonic::Status, strict: bool) {
        let expected = !strict && s.code() == tonic::Code::ResourceExhausted;
        self.error(kind, &format!("{:?}", s.code()), s.message(), expected);
    }
}
