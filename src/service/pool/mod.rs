//! The worker pool: samples are made on worker threads (never on tokio threads) that take their
//! jobs in the order they were started, each stream keeps a bounded queue (its prefetch depth),
//! the total number of samples being made is bounded, and free slots go first to the client
//! (peer: [`PeerKey`]) that has used the least, by its samples' worker time, then round-robin to that
//! client's streams, so that one client's many calls take one client's turn.
//!
//! # How it works
//!
//! Each worker is a rayon pool of one thread: a sample's own parallel loops run on its worker's
//! thread, one sample per worker at a time, and the workers take jobs from one queue, the job of
//! least finish tag first (below, "Fairness by cost"), so a job handed in early for a client that
//! asked for much does not keep a worker from a client first in line. (On
//! one shared rayon pool a thread whose `join` waits runs other jobs nested on its stack, and the
//! waiting job cannot finish before they do: under a steady feed of new jobs an old one could
//! stay buried for as long as the feed lasted, and its stream got nothing.)
//!
//! Each stream has a cursor `k` over its indices `start + rank + k * world_size`. A job for the
//! next `k` may start when the stream has fewer than `prefetch` samples dispatched but not yet
//! handed to the transport, and fewer than `capacity` jobs run over all streams. A finished job
//! puts its sample into the stream's queue (keyed by `k`, so jobs may finish out of order) and
//! wakes the stream. The stream is polled by tonic only when the transport can take a message,
//! so a client that stops reading stops its stream after at most `prefetch` samples: back-pressure
//! reaches the workers and memory stays bounded. Every change (a job done, a batch taken, a stream
//! opened or closed, and every [`TICK`]) re-runs the dispatch ([`Scheduler::pump`]), which
//! takes the peers by their use (below), and within a peer its streams from the one after the
//! stream served last: one job per turn.
//!
//! A stream may also carry an explicit index list (GetSamples, [`Scheduler::open_indices`]):
//! position `k` is then the list's `k`-th entry, in the list's order; everything else (prefetch
//! window, in-flight bound, round-robin, back-pressure, drain) is the same.
//!
//! # Scenes are built off the workers
//!
//! A job whose scene is not ready is not handed to a worker: at dispatch the stream's
//! [`Prepare`] starts the scene's build on the scene pool ([`crate::scene::cache::load_pool`])
//! and the job waits, outside the in-flight bound, until the build reports back; then it goes to
//! a worker before any new dispatch. So the workers (and the in-flight slots) only ever make
//! samples of ready scenes, a sample of a ready scene never waits on a scene being built, and
//! the stream's prefetch window is its scene lookahead: a stream asks for the scenes of its next
//! `prefetch` indices while it sends the current ones.
//!
//! While draining, no new job starts; each stream sends what is finished and then ends with
//! UNAVAILABLE and its resume cursor.
//!
//! # The byte budget
//!
//! Over all streams, the bytes of samples made, being made, or made but not yet sent are bounded
//! by `budget` (`max_buffered_mb`), however many clients and addresses there are: a stream
//! *holds* the encoded size of its finished samples waiting in its queue, of the last message
//! handed to the transport (until the transport asks for the next one, which it does once it
//! has room for it), and, for each running job, a reservation ([`StreamShared::reserve`]): the
//! job's bound from its request (`validate::admit_size`) until the stream's first sample is
//! made, then that sample's size plus an eighth. A running job also reserves its sample's
//! workspace, [`Produce::workspace`] (`service::work::workspace`; the service sets 0 for now: the renderer's buffers of each frame and the raw
//! tensors, estimated from the request's size, frames and fields), from dispatch until it is
//! done; the workspace counts in the budget's total (`mpiflow_buffered_bytes`), not in the
//! stream's share, so the samples being made are within the budget too and the shares still
//! divide what clients are sent. No job starts unless its reservation and its workspace fit what
//! the budget has left; a request whose largest sample's workspace and bound are over the budget is
//! refused before any work (`service::work::admit_workspace`). Within that, a stream may start a job while what it
//! holds plus the reservation stays within its fair share, `budget / peers with open streams /
//! the peer's open streams`; a stream holding nothing may start one while its peer holds less
//! than the peer's share. Beyond its share a stream may go on while the budget has room, but only
//! the client first in line (the one whose next job would finish first on the virtual clock,
//! below) may take the budget's last [`HEADROOM_DIVISOR`]th: a client reading small samples
//! quickly among many that asked for clips and left them unread finds room at once, instead of
//! waiting for the room to be reclaimed. When a stream opens and the shares shrink, streams holding more than
//! their new share drop their newest finished samples (made again, byte for byte, when the
//! stream reads on) and make no more ahead until they send a message, so a stalled stream never
//! keeps more than its share, does not refill and drop again as other streams come and go, and
//! the fast streams keep their share. A batch is filled within the share as well: a stream at
//! its share with nothing running sends the samples it has as a shorter batch (and never drops
//! the next sample to send), so a batch larger than the share is sent in parts.
//!
//! A message in the transport cannot be dropped. When a stream may not start for want of room
//! while its peer holds less than its share, the dispatch reclaims it ([`Scheduler::reclaim`]):
//! peers over their share drop finished samples, and a connection whose message has waited in
//! the transport for [`UNREAD_GRACE`] while its client took none of its bytes is closed (the
//! client that stopped reading, the unary replies never read, the window never granted; only
//! DATA taken counts, never a PING ACK: `service::progress`), and no
//! sample starts for that client for [`PENALTY_FIRST`] (doubled at each repeat, up to
//! [`PENALTY_MAX`]): a client that never reads cannot keep the workers making samples for it by
//! reconnecting. A client that reads, however slowly, is never closed for room. Stream slots
//! come back the same way: a newcomer refused because every slot of `max_streams` is taken
//! closes the connection of a stream whose message has so waited ([`Scheduler::stalled_holder`]). A unary reply (GetSample) keeps
//! its stream, and so its bytes, until the reply has left (`service::reply`).
//!
//! # Fairness by cost
//!
//! Turns go to peers by the worker time of the samples they were given
//! ([`Scheduler::next_eligible`]): the job that would finish first on a virtual clock of worker
//! nanoseconds goes first (weighted fair queueing), so a peer asking for 8-frame clips waits its
//! turn as long as its clips take the workers, not one turn per call, and not by the bytes it is
//! sent (a clip asking only `valid` with LZ4 is a few hundred bytes and takes a worker longer than
//! a pair of every field). A job is charged at dispatch what the stream's latest sample took
//! (each worker's time on the CPU while it made it: `meter`), or, before the stream's first
//! sample, its request's work units (`service::work`: pixels x frames x kernel taps) at the rate
//! the samples made so far have set; once done, the peer's use is set right by what it took. Use
//! is compared only between the peers with jobs to start, on one clock: a peer new to the
//! dispatch starts at the clock, and one idle for a while keeps at most [`CREDIT`] of credit
//! below it, so what a client used long ago fades instead of counting for ever. A peer's use is
//! kept for a while after its last call ends (a client of GetSample calls, one at a time, keeps
//! its place). A request whose largest sample is over `max_sample_work` is refused before any
//! work (`service::work::admit`).
//!
//! # Clients that read go first
//!
//! A client counts as reading ([`Scheduler::reading`]) once it has taken a message, until a
//! message of its has waited [`UNREAD_GRACE`] untaken, and never for [`PENALTY_MAX`] after a
//! time out. The server cannot know that a new client will read, nor stop a job once started
//! (an 8-frame clip of every field holds a worker for about 0.7 s at 640x480), so while a client
//! that reads has a call open, the others (a new client's first sample, clients that stopped
//! reading) start one job at a time, and only while the workers' recent time on them is at most
//! [`OTHERS_SHARE`]; otherwise the clients that read take the turns, by the same fair queueing.
//! Fifty addresses that ask for clips and never read them cost the workers at most one clip at a
//! time and an eighth of their time, instead of every worker for as long as the clips take.

mod meter;
mod sched;
mod scheduler;
mod stream;
mod workers;

use std::sync::{Arc, Mutex, MutexGuard};

use super::conn::Activity;
use super::error::ServiceError;
use super::pb;
use super::peer::PeerKey;

pub use meter::FIRST_NS_PER_UNIT;
pub use sched::CREDIT;
pub use sched::{HEADROOM_DIVISOR, OTHERS_SHARE, PENALTY_FIRST, PENALTY_MAX};
pub use scheduler::{PeerUse, SampleStream, Scheduler, SchedulerStats};
pub use stream::StreamShared;

pub(super) fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// Makes the sample of one index (runs on a worker).
pub type Make = Arc<dyn Fn(u64) -> Result<pb::Sample, ServiceError> + Send + Sync>;

/// Asked at dispatch whether the sample of an index can be made without waiting for a scene:
/// `true` = ready (its scene is cached, or there is nothing to prepare); `false` = the scene is
/// being built off the workers, and the callback is called (on another thread, never inside the
/// call) once it is built or failed.
pub type Prepare = Arc<dyn Fn(u64, Box<dyn FnOnce() + Send>) -> bool + Send + Sync>;

/// The job of a stream: how a sample is made, how its scene is prepared ahead, and the most
/// bytes one of its samples can take.
#[derive(Clone)]
pub struct Produce {
    pub make: Make,
    pub prepare: Option<Prepare>,
    /// The encoded size no sample of the job exceeds (`validate::admit_size`); 0 = not known.
    /// A job is reserved this much in the budget until the stream's first sample says its size.
    pub bound: u64,
    /// The work units of one sample (`service::work`): what a job is charged in worker time,
    /// at the rate the samples made have set, until the stream's first sample says what it
    /// takes; 0 = not known (charged next to nothing until then).
    pub work: u64,
    /// The bytes a sample takes on its worker while it is made, besides its encoded bytes
    /// (`service::work::workspace`): reserved in the budget from dispatch until it is done.
    pub workspace: u64,
}

impl Produce {
    /// A job with nothing to prepare (every sample is made straight away on a worker) and no
    /// known bound.
    pub fn new(make: Make) -> Self {
        Produce { make, prepare: None, bound: 0, work: 0, workspace: 0 }
    }
}

/// Who opens a stream: the key of its client (the fairness and the shares go by it) and its
/// connection (closed when it holds samples it does not take while another client needs the
/// room).
#[derive(Clone, Debug, Default)]
pub struct Client {
    pub peer: PeerKey,
    pub conn: Option<Arc<Activity>>,
}

/// How long a stream's message may wait in the transport, its client taking none of the
/// connection's bytes, before the connection may be closed for a client that needs the room.
pub const UNREAD_GRACE: std::time::Duration = std::time::Duration::from_millis(500);

/// How often the dispatch runs with nothing else happening (for [`UNREAD_GRACE`]).
pub(super) const TICK: std::time::Duration = std::time::Duration::from_millis(100);

/// The shape of one stream.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StreamSpec {
    pub start_index: u64,
    pub rank: u64,
    pub world_size: u64,
    /// Samples to send; 0 = endless.
    pub count: u64,
    /// Samples per message (a batch is cut short rather than exceed `max_message_bytes`).
    pub batch_size: usize,
    /// Samples dispatched but not yet handed to the transport, at most (>= batch_size).
    pub prefetch: usize,
    pub max_message_bytes: usize,
}

/// The end of the index space: sample indices are `0 .. END_INDEX` (2^64 - 1 itself is never a
/// sample), so a cursor can always say "after the last index" without repeating it.
pub const END_INDEX: u64 = u64::MAX;

impl StreamSpec {
    /// The index of position `k`, or None at or past [`END_INDEX`].
    pub fn index(&self, k: u64) -> Option<u64> {
        k.checked_mul(self.world_size)?.checked_add(self.start_index)?.checked_add(self.rank).filter(|&i| i < END_INDEX)
    }

    /// The number of positions this stream has (count, or as many as fit below [`END_INDEX`]).
    pub fn len(&self) -> u64 {
        let first = match self.start_index.checked_add(self.rank) {
            Some(f) if f < END_INDEX => f,
            _ => return 0,
        };
        let fit = (END_INDEX - 1 - first) / self.world_size.max(1) + 1;
        if self.count == 0 {
            fit
        } else {
            self.count.min(fit)
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The cursor (next_index, resume_start_index) after `k` positions were delivered; past the
    /// last index it is [`END_INDEX`] (and `END_INDEX - rank`): a request resuming from it gets
    /// nothing, so nothing is repeated or skipped.
    pub fn cursor(&self, k: u64) -> (u64, u64) {
        let next = self.index(k).unwrap_or(END_INDEX);
        (next, next.saturating_sub(self.rank))
    }
}

pub(super) type Item = Result<(pb::Sample, usize), ServiceError>;
