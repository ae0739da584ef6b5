//! The worker pool: samples are made on worker threads (never on tokio threads) that take their
//! jobs in the order they were started, each stream keeps a bounded queue (its prefetch depth),
//! the total number of samples being made is bounded, and free slots go first to the client
//! (peer: [`PeerKey`]) that has used the least, by its samples' bytes, then round-robin to that
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
//! made, then that sample's size plus an eighth. No job starts unless its
//! reservation fits what the budget has left. Within that, a stream may start a job while what it
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
//! client that stopped reading, the unary replies never read, the window never granted), and no
//! sample starts for that client for [`PENALTY_FIRST`] (doubled at each repeat, up to
//! [`PENALTY_MAX`]): a client that never reads cannot keep the workers making samples for it by
//! reconnecting. A client that reads, however slowly, is never closed for room. A unary reply (GetSample) keeps
//! its stream, and so its bytes, until the reply has left (`service::reply`).
//!
//! # Fairness by cost
//!
//! Turns go to peers by the bytes of the samples they were given ([`Scheduler::next_eligible`]),
//! a proxy of pixels x frames x fields: the job that would finish first on a virtual clock of
//! bytes goes first (weighted fair queueing), so a peer asking for 8-frame clips with every
//! field waits its turn as long as the bytes it asked for take, not one turn per call, and many
//! newcomers asking for clips do not each go ahead of a client of pairs already waiting. A
//! peer's use is kept for a while after its last call ends (a client of GetSample calls, one
//! at a time, keeps its place).
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

use std::collections::BTreeMap;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::task::{Context, Poll, Waker};
use std::time::Instant;

use prost::Message;
use tokio_stream::Stream;
use tonic::Status;

use super::conn::Activity;
use super::error::{with_cursor, ServiceError};
use super::metrics::Metrics;
use super::pb;
use super::peer::PeerKey;

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
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
}

impl Produce {
    /// A job with nothing to prepare (every sample is made straight away on a worker) and no
    /// known bound.
    pub fn new(make: Make) -> Self {
        Produce { make, prepare: None, bound: 0 }
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
const TICK: std::time::Duration = std::time::Duration::from_millis(100);

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

type Item = Result<(pb::Sample, usize), ServiceError>;

struct StreamState {
    /// Positions dispatched so far (the next job's k).
    dispatched: u64,
    /// Bytes this stream holds against the budget (queued samples, the message in transport and
    /// the estimates of running jobs).
    held: u64,
    /// The encoded size of the stream's latest sample (the estimate of the next); 0 = not known.
    estimate: u64,
    /// Bytes of the last message handed to the transport, held until the next poll.
    in_transport: u64,
    /// When that message was handed over.
    in_transport_since: Instant,
    /// Samples were dropped to bring the stream back to its share: it makes no more ahead until
    /// it sends a message (a stalled stream stays small instead of refilling and dropping again
    /// every time another stream comes and goes).
    trimmed: bool,
    /// Positions handed to the transport so far.
    delivered: u64,
    /// Jobs running now.
    running: usize,
    ready: BTreeMap<u64, Item>,
    /// Samples made for this stream (for tests and logs).
    produced: u64,
    waker: Option<Waker>,
    /// The consumer is gone or the stream ended.
    closed: bool,
    draining: bool,
}

/// The bytes held by all streams of one peer (client address), shared by them.
#[derive(Debug, Default)]
struct PeerGroup {
    held: AtomicU64,
    /// The peer's share of the budget (budget / peers with open streams).
    share: AtomicU64,
    /// The cost of the jobs started for the peer, on the dispatch's virtual clock
    /// ([`Scheduler::next_eligible`]).
    used: AtomicU64,
    /// The peer has taken a message it was sent (see [`Scheduler::reading`]).
    took: std::sync::atomic::AtomicBool,
}

/// One stream's shared state.
pub struct StreamShared {
    pub id: u64,
    pub spec: StreamSpec,
    /// The client's key: the fairness and the shares go by peer.
    peer: PeerKey,
    /// The client's connection.
    conn: Option<Arc<Activity>>,
    group: Arc<PeerGroup>,
    /// This stream's share of the budget: its peer's share / the peer's open streams.
    share: AtomicU64,
    /// An explicit index list (position k = `indices[k]`) instead of the spec's sequence.
    indices: Option<Arc<[u64]>>,
    len: u64,
    produce: Produce,
    state: Mutex<StreamState>,
}

impl StreamShared {
    /// The index of position `k` (`k < len`).
    fn index(&self, k: u64) -> u64 {
        match &self.indices {
            Some(list) => list[k as usize],
            None => self.spec.index(k).unwrap_or(u64::MAX),
        }
    }

    /// The cursor after `k` positions: the spec's for a sequence; for an index list the
    /// position itself (as `(k, k)`), which has no meaning as a start_index.
    fn cursor(&self, k: u64) -> (u64, u64) {
        if self.indices.is_some() {
            (k, k)
        } else {
            self.spec.cursor(k)
        }
    }

    /// What a job of the stream reserves in the budget while it runs: the job's bound until a
    /// sample's size is known, then that size and an eighth (never over the bound).
    fn reserve(&self, s: &StreamState) -> u64 {
        // the small fields vary with the sample's objects and its record: an eighth covers them
        let known = s.estimate.saturating_add(s.estimate / 8);
        match (self.produce.bound, known) {
            (0, k) => k,
            (b, 0) => b,
            (b, k) => k.min(b),
        }
    }

    /// What a job of the stream costs the peer on the dispatch's virtual clock: its sample's
    /// bytes (pixels x frames x fields), known or bounded.
    fn cost(&self, s: &StreamState) -> u64 {
        if s.estimate > 0 {
            s.estimate
        } else {
            self.produce.bound.max(1)
        }
    }

    /// Whether the stream may start a job now, with `room` what the budget has left over all
    /// streams and `spare` what a job beyond its share may take of it (all of `room` for the
    /// client first in line, less a budget / [`HEADROOM_DIVISOR`] for the others: [`Scheduler::spare`]).
    fn eligible(&self, s: &StreamState, room: u64, spare: u64) -> bool {
        if s.closed
            || s.draining
            || s.dispatched >= self.len
            || (s.dispatched - s.delivered) >= self.spec.prefetch as u64
        {
            return false;
        }
        let reserve = self.reserve(s);
        let (share, peer_share) = (self.share.load(Ordering::Acquire), self.group.share.load(Ordering::Acquire));
        let peer_held = self.group.held.load(Ordering::Acquire);
        let holds_nothing = s.held == 0 && s.running == 0;
        // within its share a stream may start a job while the budget has room for it; the first
        // job once its size is known (a batch is filled within the share too: a stream at its
        // share sends the batch it has, cut short, see `SampleStream::poll_next`)
        let fits_share = if holds_nothing {
            peer_held.saturating_add(reserve) <= peer_share
        } else {
            !s.trimmed && s.estimate > 0 && s.held.saturating_add(reserve) <= share
        };
        if fits_share {
            return reserve <= room;
        }
        // beyond its share a stream may go on while the budget has spare room: the shares decide
        // who gets the room back when a client waits for it (`Scheduler::reclaim`), not who
        // idles; a stream holding nothing may start one job while its peer holds less than its
        // share (so a new client gets going even when its share is smaller than one sample)
        let may_exceed = if holds_nothing { peer_held < peer_share } else { !s.trimmed && s.estimate > 0 };
        may_exceed && reserve <= spare
    }

    /// (dispatched, delivered, produced, queued) for tests and diagnostics.
    pub fn counts(&self) -> (u64, u64, u64, usize) {
        let s = lock(&self.state);
        (s.dispatched, s.delivered, s.produced, s.ready.len())
    }
}

struct Sched {
    streams: Vec<Arc<StreamShared>>,
    /// The virtual clock of the dispatch: where the job started last started (its start tag), where a peer new to the dispatch starts.
    vclock: u64,
    /// Per peer, the position of the stream served last.
    rr_in_peer: std::collections::HashMap<PeerKey, u64>,
    groups: std::collections::HashMap<PeerKey, Arc<PeerGroup>>,
    in_flight: usize,
    max_in_flight_seen: usize,
    draining: bool,
    next_id: u64,
    /// Jobs whose scene became ready, to hand to the workers first.
    ready_jobs: std::collections::VecDeque<Ready>,
    /// Jobs waiting for their scene now.
    waiting_scene: usize,
    /// Clients whose connection was closed for holding samples they did not take: no job starts
    /// for them until their time is up ([`Penalty`]).
    penalties: std::collections::HashMap<PeerKey, Penalty>,
    /// What clients with no open call had used on the virtual clock, and whether they had taken
    /// a message, so that a client whose calls come one at a time (GetSample) keeps its place and
    /// its standing instead of starting again with each call (at most [`MAX_PENALTIES`] clients;
    /// the least used go first).
    past_used: std::collections::HashMap<PeerKey, (u64, bool)>,
    /// Jobs dispatched and not yet done for clients that are not reading ([`Scheduler::reading`]).
    others_in_flight: usize,
    /// The workers' recent time on the jobs of clients that are not reading, against all.
    busy: Busy,
}

/// The workers' recent time on the jobs of clients that are not reading
/// ([`Scheduler::reading`]), each second of it decayed by `exp(-age / BUSY_DECAY_S)`.
#[derive(Clone, Copy, Debug)]
struct Busy {
    at: Instant,
    others: f64,
}

/// How fast the workers' past time fades from [`Busy`], seconds.
const BUSY_DECAY_S: f64 = 5.0;

/// While a client that reads has a call open, the clients that do not read (a new client until it
/// has taken its first message, and those whose sent message waits untaken) get at most this
/// part of the workers' time, one job at a time: a job of theirs may take a worker for long (an
/// 8-frame clip of every field takes one about 0.7 s at 640x480) and cannot be stopped once
/// started.
pub const OTHERS_SHARE: f64 = 0.125;

impl Busy {
    fn add(&mut self, now: Instant, seconds: f64) {
        let fade = (-(now.saturating_duration_since(self.at).as_secs_f64()) / BUSY_DECAY_S).exp();
        self.at = now;
        self.others = self.others * fade + seconds;
    }

    /// The part of `workers`' recent time spent on clients that are not reading (a constant use
    /// of all of them decays to `workers * BUSY_DECAY_S`).
    fn others_part(&self, now: Instant, workers: usize) -> f64 {
        let fade = (-(now.saturating_duration_since(self.at).as_secs_f64()) / BUSY_DECAY_S).exp();
        self.others * fade / (workers.max(1) as f64 * BUSY_DECAY_S)
    }
}

/// A client's time out after its connection was closed for holding samples it did not take:
/// [`PENALTY_FIRST`], doubled at each repeat up to [`PENALTY_MAX`], so that a client that never
/// reads cannot have the workers make sample after sample for it by reconnecting.
#[derive(Clone, Copy, Debug)]
struct Penalty {
    until: Instant,
    strikes: u32,
}

/// A job that takes a client beyond its share leaves `budget / HEADROOM_DIVISOR` of the budget
/// free unless the client is first in line ([`Scheduler::first_in_line`]).
pub const HEADROOM_DIVISOR: u64 = 4;

/// The first time out of a client closed for not reading.
pub const PENALTY_FIRST: std::time::Duration = std::time::Duration::from_secs(10);
/// The longest time out.
pub const PENALTY_MAX: std::time::Duration = std::time::Duration::from_secs(300);
/// The most clients remembered in time out (older entries go first when it is full).
const MAX_PENALTIES: usize = 4096;

impl Sched {
    /// Puts `peer` in time out (see [`Penalty`]).
    fn penalise(&mut self, peer: PeerKey) {
        let now = Instant::now();
        if self.penalties.len() >= MAX_PENALTIES {
            self.penalties.retain(|_, p| p.until > now);
            if self.penalties.len() >= MAX_PENALTIES {
                if let Some(first) = self.penalties.iter().min_by_key(|(_, p)| p.until).map(|(k, _)| *k) {
                    self.penalties.remove(&first);
                }
            }
        }
        if let Some(group) = self.groups.get(&peer) {
            group.took.store(false, Ordering::Release);
        }
        let strikes = self.penalties.get(&peer).map_or(0, |p| p.strikes).saturating_add(1);
        let time = PENALTY_FIRST.saturating_mul(1 << (strikes - 1).min(10)).min(PENALTY_MAX);
        self.penalties.insert(peer, Penalty { until: now + time, strikes });
    }

    /// Whether `peer` is in time out now.
    fn in_time_out(&self, peer: PeerKey, now: Instant) -> bool {
        self.penalties.get(&peer).is_some_and(|p| p.until > now)
    }

    /// Whether `peer` was closed for not reading lately: in time out, or out of it for less than
    /// [`PENALTY_MAX`]. Such a client is not counted among those that read
    /// ([`Scheduler::reading`]) even when it takes a message again (a client that reads one
    /// message of each call and then stops does not take the readers' turns).
    fn struck(&self, peer: PeerKey, now: Instant) -> bool {
        self.penalties.get(&peer).is_some_and(|p| p.until + PENALTY_MAX > now)
    }
}

/// A peer's next job as the dispatch sees it ([`Scheduler::tags`]).
#[derive(Clone)]
struct Tag {
    /// Where the job starts on the virtual clock (the peer's use, at least a budget below the
    /// clock) and where it finishes (plus its cost).
    start: u64,
    finish: u64,
    peer: PeerKey,
    reading: bool,
    stream: Arc<StreamShared>,
}

/// The job the dispatch starts next: its stream, its finish tag and whether its client is
/// among those that do not read.
struct Pick {
    stream: Arc<StreamShared>,
    finish: u64,
    others: bool,
}

/// A job handed to the workers: (stream, k, reserved bytes, finish tag, for a client not reading).
type Ready = (Arc<StreamShared>, u64, u64, u64, bool);

type Job = Box<dyn FnOnce() + Send>;

/// The workers: each is a rayon pool of one thread, and all take their jobs from one queue, the
/// job of least finish tag first ([`Scheduler::next_eligible`]; ties in the order they were
/// handed in). A job handed in early for a client that asked for much does not keep a worker
/// from the job of a client first in line handed in after it. A sample's own parallel loops run
/// on its worker's thread; a worker never runs another job nested inside a waiting one (as the
/// threads of a shared rayon pool do while a `join` waits, which buried an old job under a feed
/// of new ones: a stream's sample could wait for as long as other streams kept the workers busy).
struct Workers {
    queue: Arc<JobQueue>,
    _pools: Vec<rayon::ThreadPool>,
}

/// A job in the queue, ordered by (tag, the order it was handed in), least first.
struct Queued {
    tag: u64,
    seq: u64,
    job: Job,
}

impl PartialEq for Queued {
    fn eq(&self, other: &Self) -> bool {
        (self.tag, self.seq) == (other.tag, other.seq)
    }
}

impl Eq for Queued {}

impl PartialOrd for Queued {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}

impl Ord for Queued {
    // reversed: the heap's greatest is the least (tag, seq)
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        (other.tag, other.seq).cmp(&(self.tag, self.seq))
    }
}

#[derive(Default)]
struct JobQueue {
    /// (the jobs handed in, how many were handed in, closed)
    jobs: Mutex<(std::collections::BinaryHeap<Queued>, u64, bool)>,
    more: std::sync::Condvar,
}

impl JobQueue {
    fn push(&self, tag: u64, job: Job) {
        let mut g = lock(&self.jobs);
        let seq = g.1;
        g.1 += 1;
        g.0.push(Queued { tag, seq, job });
        drop(g);
        self.more.notify_one();
    }

    /// A worker's loop: the job of least tag, until the queue is closed and empty.
    fn run(&self) {
        loop {
            let job = {
                let mut g = lock(&self.jobs);
                loop {
                    if let Some(q) = g.0.pop() {
                        break q.job;
                    }
                    if g.2 {
                        return;
                    }
                    g = self.more.wait(g).unwrap_or_else(std::sync::PoisonError::into_inner);
                }
            };
            job();
        }
    }
}

impl Workers {
    fn new(n: usize) -> Result<Self, ServiceError> {
        let queue = Arc::new(JobQueue::default());
        let mut pools = Vec::with_capacity(n);
        for i in 0..n {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(1)
                .thread_name(move |_| format!("mpiflow-worker-{i}"))
                .build()
                .map_err(|e| ServiceError::Config(format!("cannot start {n} worker threads: {e}")))?;
            let q = queue.clone();
            pool.spawn(move || q.run());
            pools.push(pool);
        }
        Ok(Self { queue, _pools: pools })
    }

    fn spawn(&self, tag: u64, job: impl FnOnce() + Send + 'static) {
        self.queue.push(tag, Box::new(job));
    }
}

impl Drop for Workers {
    fn drop(&mut self) {
        lock(&self.queue.jobs).2 = true;
        self.queue.more.notify_all();
    }
}

/// The workers and the dispatch state shared by all streams.
pub struct Scheduler {
    pool: Workers,
    workers: usize,
    capacity: usize,
    /// Bytes of made-but-unsent samples over all streams (see the module docs).
    budget: u64,
    /// Bytes held now over all streams.
    buffered: AtomicU64,
    /// The most bytes held at once so far.
    max_buffered_seen: AtomicU64,
    /// Finished samples dropped to bring a stream back to its share (made again later).
    dropped: AtomicU64,
    inner: Mutex<Sched>,
    metrics: Arc<Metrics>,
}

impl std::fmt::Debug for Scheduler {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Scheduler").field("workers", &self.workers).field("capacity", &self.capacity).finish()
    }
}

/// A snapshot of the scheduler for tests and GetInfo.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SchedulerStats {
    pub streams: usize,
    pub in_flight: usize,
    pub max_in_flight_seen: usize,
    pub capacity: usize,
    /// The byte budget of made-but-unsent samples, the bytes held now and the most held at once.
    pub budget: u64,
    pub buffered: u64,
    pub max_buffered_seen: u64,
    /// Finished samples dropped to bring streams back to their share (made again when read).
    pub dropped: u64,
    /// Per stream: (id, dispatched, delivered, produced, queued).
    pub per_stream: Vec<(u64, u64, u64, u64, usize)>,
    /// Per stream: bytes held against the budget.
    pub held: Vec<u64>,
    /// Streams that may start a job now (0 with nothing in flight or waiting for a scene =
    /// production has settled).
    pub eligible: usize,
    /// Jobs dispatched whose scene is being built off the workers, or built and not yet handed to
    /// a worker (they hold their reserved bytes like running jobs).
    pub waiting_scene: usize,
}

impl Scheduler {
    /// A pool of `workers` threads running at most `capacity` jobs, holding at most about
    /// `budget` bytes of made-but-unsent samples (see the module docs).
    pub fn new(workers: usize, capacity: usize, budget: u64, metrics: Arc<Metrics>) -> Result<Arc<Self>, ServiceError> {
        let workers = workers.max(1);
        let pool = Workers::new(workers)?;
        metrics.workers.set(workers as i64);
        metrics.set_in_flight(0, capacity.max(1));
        metrics.set_buffered(0, budget.max(1));
        let scheduler = Arc::new(Self {
            pool,
            workers,
            capacity: capacity.max(1),
            budget: budget.max(1),
            buffered: AtomicU64::new(0),
            max_buffered_seen: AtomicU64::new(0),
            dropped: AtomicU64::new(0),
            inner: Mutex::new(Sched {
                streams: Vec::new(),
                vclock: 0,
                rr_in_peer: std::collections::HashMap::new(),
                groups: std::collections::HashMap::new(),
                in_flight: 0,
                max_in_flight_seen: 0,
                draining: false,
                next_id: 1,
                ready_jobs: std::collections::VecDeque::new(),
                waiting_scene: 0,
                penalties: std::collections::HashMap::new(),
                past_used: std::collections::HashMap::new(),
                others_in_flight: 0,
                busy: Busy { at: Instant::now(), others: 0.0 },
            }),
            metrics,
        });
        // the dispatch also runs as time passes: an unread message becomes reclaimable after
        // UNREAD_GRACE with nothing else happening
        let weak = Arc::downgrade(&scheduler);
        std::thread::Builder::new()
            .name("mpiflow-dispatch-tick".into())
            .spawn(move || loop {
                std::thread::sleep(TICK);
                match weak.upgrade() {
                    Some(s) => s.pump(),
                    None => return,
                }
            })
            .map_err(|e| ServiceError::Internal(format!("the dispatch's timer thread: {e}")))?;
        Ok(scheduler)
    }

    pub fn workers(&self) -> usize {
        self.workers
    }

    pub fn capacity(&self) -> usize {
        self.capacity
    }

    pub fn budget(&self) -> u64 {
        self.budget
    }

    /// Adds `add` and takes `sub` bytes from the total held and from the stream's peer's.
    fn account(&self, st: &StreamShared, add: u64, sub: u64) {
        if add >= sub {
            st.group.held.fetch_add(add - sub, Ordering::AcqRel);
        } else {
            st.group.held.fetch_sub(sub - add, Ordering::AcqRel);
        }
        let now = if add >= sub {
            self.buffered.fetch_add(add - sub, Ordering::AcqRel) + (add - sub)
        } else {
            self.buffered.fetch_sub(sub - add, Ordering::AcqRel) - (sub - add)
        };
        self.max_buffered_seen.fetch_max(now, Ordering::AcqRel);
        self.metrics.set_buffered(now, self.budget);
    }

    /// Opens a stream; its samples are made as the returned stream is polled.
    pub fn open(self: &Arc<Self>, spec: StreamSpec, produce: Produce) -> Result<SampleStream, ServiceError> {
        self.open_with(Client::default(), spec, None, produce)
    }

    /// Opens a stream of `client` (the workers' turns and the budget's shares go first by peer,
    /// then by stream).
    pub fn open_for(
        self: &Arc<Self>,
        peer: Client,
        spec: StreamSpec,
        produce: Produce,
    ) -> Result<SampleStream, ServiceError> {
        self.open_with(peer, spec, None, produce)
    }

    /// Opens a stream of an explicit index list (any order, duplicates allowed), delivered in
    /// the list's order, `batch_size` samples per batch and `prefetch` made ahead.
    pub fn open_indices(
        self: &Arc<Self>,
        peer: Client,
        indices: Vec<u64>,
        batch_size: usize,
        prefetch: usize,
        max_message_bytes: usize,
        produce: Produce,
    ) -> Result<SampleStream, ServiceError> {
        let spec = StreamSpec {
            start_index: 0,
            rank: 0,
            world_size: 1,
            count: indices.len() as u64,
            batch_size,
            prefetch,
            max_message_bytes,
        };
        self.open_with(peer, spec, Some(indices.into()), produce)
    }

    fn open_with(
        self: &Arc<Self>,
        client: Client,
        spec: StreamSpec,
        indices: Option<Arc<[u64]>>,
        produce: Produce,
    ) -> Result<SampleStream, ServiceError> {
        let mut spec = spec;
        spec.world_size = spec.world_size.max(1);
        spec.batch_size = spec.batch_size.max(1);
        spec.prefetch = spec.prefetch.max(spec.batch_size);
        let shared = {
            let mut s = lock(&self.inner);
            if s.draining {
                return Err(ServiceError::Draining);
            }
            let id = s.next_id;
            s.next_id += 1;
            // a peer new to the dispatch starts at the virtual clock (no credit from before), or
            // where it was when its last call ended, if that is later
            let (past, took) = s.past_used.remove(&client.peer).unwrap_or((0, false));
            let vclock = s.vclock.max(past);
            let group = s
                .groups
                .entry(client.peer)
                .or_insert_with(|| {
                    Arc::new(PeerGroup {
                        used: AtomicU64::new(vclock),
                        took: std::sync::atomic::AtomicBool::new(took),
                        ..PeerGroup::default()
                    })
                })
                .clone();
            let shared = Arc::new(StreamShared {
                id,
                spec,
                peer: client.peer,
                conn: client.conn,
                group,
                share: AtomicU64::new(0),
                len: indices.as_ref().map_or_else(|| spec.len(), |l| l.len() as u64),
                indices,
                produce,
                state: Mutex::new(StreamState {
                    dispatched: 0,
                    held: 0,
                    estimate: 0,
                    in_transport: 0,
                    in_transport_since: Instant::now(),
                    trimmed: false,
                    delivered: 0,
                    running: 0,
                    ready: BTreeMap::new(),
                    produced: 0,
                    waker: None,
                    closed: false,
                    draining: false,
                }),
            });
            s.streams.push(shared.clone());
            self.reshare(&s);
            for st in &s.streams {
                self.trim(st, &mut lock(&st.state));
            }
            shared
        };
        self.pump();
        Ok(SampleStream { shared, scheduler: self.clone(), finished: false })
    }

    /// Starts jobs while there is room, one per eligible stream per turn.
    fn pump(self: &Arc<Self>) {
        let mut s = lock(&self.inner);
        // jobs whose scene is ready go first (they were dispatched before any drain began)
        while s.in_flight < self.capacity {
            let Some((st, k, reserved, tag, others)) = s.ready_jobs.pop_front() else { break };
            s.in_flight += 1;
            s.max_in_flight_seen = s.max_in_flight_seen.max(s.in_flight);
            self.metrics.set_in_flight(s.in_flight, self.capacity);
            let me = self.clone();
            self.pool.spawn(tag, move || me.run_job(st, k, reserved, others));
        }
        while s.in_flight < self.capacity && !s.draining {
            let Some(Pick { stream: st, finish: tag, others }) = self.next_eligible(&mut s) else { break };
            if others {
                s.others_in_flight += 1;
            }
            let (k, reserved) = {
                let mut g = lock(&st.state);
                let k = g.dispatched;
                let reserved = st.reserve(&g);
                g.dispatched += 1;
                g.running += 1;
                g.held += reserved;
                self.account(&st, reserved, 0);
                (k, reserved)
            };
            if let Some(prepare) = &st.produce.prepare {
                let (me, st2) = (self.clone(), st.clone());
                let done: Box<dyn FnOnce() + Send> = Box::new(move || me.scene_ready((st2, k, reserved, tag, others)));
                if !prepare(st.index(k), done) {
                    s.waiting_scene += 1;
                    continue;
                }
            }
            s.in_flight += 1;
            s.max_in_flight_seen = s.max_in_flight_seen.max(s.in_flight);
            self.metrics.set_in_flight(s.in_flight, self.capacity);
            let me = self.clone();
            self.pool.spawn(tag, move || me.run_job(st, k, reserved, others));
        }
        if s.in_flight < self.capacity {
            self.reclaim(&mut s);
        }
    }

    /// Whether `peer` reads what it is sent: it has taken a message, was not closed for not
    /// reading lately ([`Sched::struck`]), and none of its streams
    /// has a message that has waited in the transport for [`UNREAD_GRACE`] while its client
    /// took none of its bytes as long. The clients that read go first for the workers; the
    /// others (new clients, and those that stopped reading) share [`OTHERS_SHARE`] of them while
    /// a client that reads waits ([`Scheduler::next_eligible`]).
    fn reading(group: &PeerGroup, of_peer: &[&Arc<StreamShared>], struck: bool) -> bool {
        !struck
            && group.took.load(Ordering::Acquire)
            && !of_peer.iter().any(|st| {
                let g = lock(&st.state);
                g.in_transport > 0
                    && g.in_transport_since.elapsed() >= UNREAD_GRACE
                    && st.conn.as_ref().is_none_or(|c| c.not_taken_for() >= UNREAD_GRACE)
            })
    }

    /// Each peer's first stream that `pick` takes, with its next job's finish tag on the virtual
    /// clock (the peer's use, at least a budget below the clock, plus the job's cost) and
    /// whether the peer is reading ([`Scheduler::reading`]). Streams are taken round-robin
    /// within a peer, from the one after the stream served last; peers in time out are left out.
    fn tags(&self, s: &Sched, now: Instant, pick: impl Fn(&StreamShared, &StreamState) -> bool) -> Vec<Tag> {
        // a peer that has used less than this, idle for a while, counts from here: its credit
        // is at most one budget's bytes
        let floor = s.vclock.saturating_sub(self.budget);
        let mut out = Vec::new();
        for (peer, group) in &s.groups {
            if s.in_time_out(*peer, now) {
                continue;
            }
            let used = group.used.load(Ordering::Acquire).max(floor);
            let last = s.rr_in_peer.get(peer).copied().unwrap_or(0);
            let of_peer: Vec<&Arc<StreamShared>> = s.streams.iter().filter(|st| st.peer == *peer).collect();
            let first = of_peer.iter().position(|st| st.id > last).unwrap_or(0);
            for j in 0..of_peer.len() {
                let st = of_peer[(first + j) % of_peer.len()];
                let g = lock(&st.state);
                if pick(st, &g) {
                    let finish = used.saturating_add(st.cost(&g));
                    drop(g);
                    let reading = Self::reading(group, &of_peer, s.struck(*peer, now));
                    out.push(Tag { start: used, finish, peer: *peer, reading, stream: (*st).clone() });
                    break;
                }
            }
        }
        out
    }

    /// The client first in line: of the clients that would start a job if the budget had room,
    /// those that read first, the one whose job would finish first on the virtual clock. It may
    /// take all the room the budget has; a job that takes any other client beyond its share
    /// leaves a budget / [`HEADROOM_DIVISOR`] free ([`Scheduler::spare`]), so that the client
    /// first in line (a fast reader of small samples among many that asked for clips and do not
    /// read them) does not wait for room to be reclaimed.
    fn first_in_line(&self, s: &Sched, now: Instant) -> Option<PeerKey> {
        let wanting = self.tags(s, now, |st, g| st.eligible(g, u64::MAX, u64::MAX));
        wanting.into_iter().min_by_key(|t| (!t.reading, t.finish, t.peer)).map(|t| t.peer)
    }

    /// Whether a client that reads has a stream with positions left to make (whether or not it
    /// may start one now: its window may be full for a moment).
    fn reader_active(&self, s: &Sched, now: Instant) -> bool {
        s.groups.iter().any(|(peer, group)| {
            let of_peer: Vec<&Arc<StreamShared>> = s.streams.iter().filter(|st| st.peer == *peer).collect();
            of_peer.iter().any(|st| {
                let g = lock(&st.state);
                !g.closed && g.dispatched < st.len
            }) && Self::reading(group, &of_peer, s.struck(*peer, now))
        })
    }

    /// What a job beyond its client's share may take of `room`: all of it for the client first in
    /// line, else what is left above a budget / [`HEADROOM_DIVISOR`].
    fn spare(&self, room: u64, first: bool) -> u64 {
        if first {
            room
        } else {
            room.saturating_sub(self.budget / HEADROOM_DIVISOR)
        }
    }

    /// The next job to start: of each peer, its next eligible stream (round-robin over its
    /// streams, in the order they opened, from the one after the stream served last); of those,
    /// the one whose job would finish first on the virtual clock: the peer's use plus the job's
    /// cost, its sample's bytes (ties by key; fair queueing with the clock at the start of the
    /// job started last: a peer new to the dispatch starts there, so a newcomer asking for a
    /// small sample goes ahead of clips asked for before it, and a peer idle for a while keeps
    /// at most one budget of credit below the clock). So a client of 8-frame clips gets about an
    /// eighth of the turns of a client of pairs, and a newcomer asking for an expensive sample
    /// does not go ahead of a cheap one already waiting. The clients that read go first: while
    /// one of them waits, the others (new clients, clients that stopped reading) start one job at
    /// a time and only while the workers' recent time on them is at most [`OTHERS_SHARE`]
    /// ([`Scheduler::reading`]). None when no stream may.
    fn next_eligible(&self, s: &mut Sched) -> Option<Pick> {
        let room = self.room();
        let now = Instant::now();
        let first = self.first_in_line(s, now);
        let candidates = self.tags(s, now, |st, g| st.eligible(g, room, self.spare(room, Some(st.peer) == first)));
        // while a client that reads has a call open, the others get their turn only one job at a
        // time and within their part of the workers' time
        let others_turn = (s.others_in_flight == 0 && s.busy.others_part(now, self.workers) <= OTHERS_SHARE)
            || !self.reader_active(s, now);
        let best = |reading: bool| {
            candidates.iter().filter(|t| t.reading == reading).min_by_key(|t| (t.finish, t.peer)).cloned()
        };
        let tag = if others_turn { best(false).or_else(|| best(true)) } else { best(true) }?;
        s.vclock = tag.start;
        tag.stream.group.used.store(tag.finish, Ordering::Release);
        s.rr_in_peer.insert(tag.peer, tag.stream.id);
        Some(Pick { stream: tag.stream, finish: tag.finish, others: !tag.reading })
    }

    /// Makes room for a stream that may not start for want of it while its peer holds less than
    /// its share: the streams of peers over their share drop their finished samples down to
    /// their share (made again when read), and a connection whose message has waited in the
    /// transport for [`UNREAD_GRACE`], its client taking none of its bytes as long, is closed
    /// (its calls end, their bytes are freed) and its client put in time out ([`Penalty`]).
    fn reclaim(&self, s: &mut Sched) {
        if s.draining {
            return;
        }
        let room = self.room();
        let first = self.first_in_line(s, Instant::now());
        let starving = s.streams.iter().any(|st| {
            let g = lock(&st.state);
            st.group.held.load(Ordering::Acquire) < st.group.share.load(Ordering::Acquire)
                && !st.eligible(&g, room, self.spare(room, Some(st.peer) == first))
                && st.eligible(&g, u64::MAX, u64::MAX)
        });
        if !starving {
            return;
        }
        let mut cut = Vec::new();
        for st in &s.streams {
            if st.group.held.load(Ordering::Acquire) <= st.group.share.load(Ordering::Acquire) {
                continue;
            }
            let mut g = lock(&st.state);
            if g.held > st.share.load(Ordering::Acquire) {
                self.trim(st, &mut g);
            }
            let unread = g.in_transport > 0 && g.in_transport_since.elapsed() >= UNREAD_GRACE;
            drop(g);
            if let Some(conn) = st.conn.as_ref().filter(|c| unread && !c.is_cut()) {
                if conn.not_taken_for() >= UNREAD_GRACE {
                    tracing::info!(
                        peer = %st.peer,
                        stream = st.id,
                        grace_ms = UNREAD_GRACE.as_millis() as u64,
                        "connection closed: it holds made samples it does not take, and another client needs the room"
                    );
                    self.metrics.holders_cut.inc();
                    conn.cut();
                    cut.push(st.peer);
                }
            }
        }
        for peer in cut {
            s.penalise(peer);
        }
    }

    /// Sets every peer's and stream's share of the budget: budget / peers with open streams,
    /// then the peer's share / its open streams.
    fn reshare(&self, s: &Sched) {
        let peers = s.groups.len().max(1) as u64;
        let peer_share = self.budget / peers;
        for (peer, group) in &s.groups {
            group.share.store(peer_share, Ordering::Release);
            let n = s.streams.iter().filter(|st| st.peer == *peer).count().max(1) as u64;
            for st in s.streams.iter().filter(|st| st.peer == *peer) {
                st.share.store(peer_share / n, Ordering::Release);
            }
        }
    }

    /// The scene of a waiting job is built (or failed): the job goes to the workers.
    fn scene_ready(self: &Arc<Self>, job: Ready) {
        {
            let mut s = lock(&self.inner);
            s.waiting_scene -= 1;
            s.ready_jobs.push_back(job);
        }
        self.pump();
    }

    /// What the budget has left over all streams.
    fn room(&self) -> u64 {
        self.budget.saturating_sub(self.buffered.load(Ordering::Acquire))
    }

    /// Brings a stream back within its share (its state locked by the caller): while it holds
    /// more, it drops its newest finished sample from the end of what it has dispatched (a
    /// running job there stops it) and will make it again, byte for byte, when it reads on.
    fn trim(&self, st: &StreamShared, g: &mut StreamState) {
        let share = st.share.load(Ordering::Acquire);
        let mut freed = 0u64;
        // never the next sample to send (a stream always gets to send one)
        while g.held > share && g.dispatched > g.delivered + 1 {
            let top = g.dispatched - 1;
            let Some(item) = g.ready.remove(&top) else { break }; // still running
            let size = match &item {
                Ok((_, n)) => *n as u64,
                Err(_) => 0,
            };
            g.dispatched = top;
            g.held -= size;
            g.trimmed = true;
            freed += size;
            self.dropped.fetch_add(1, Ordering::AcqRel);
            self.metrics.samples_dropped.inc();
        }
        if freed > 0 {
            self.metrics.set_queue_depth(st.id, g.ready.len());
            self.account(st, 0, freed);
        }
    }

    fn run_job(self: Arc<Self>, st: Arc<StreamShared>, k: u64, reserved: u64, others: bool) {
        let t = Instant::now();
        let skip = lock(&st.state).closed;
        let item: Option<Item> = if skip {
            None
        } else {
            // the index exists: k < len
            let index = st.index(k);
            let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| (st.produce.make)(index)))
                .unwrap_or_else(|_| Err(ServiceError::Internal(format!("sample {index}: the worker panicked"))));
            Some(r.map(|s| {
                let n = s.encoded_len();
                (s, n)
            }))
        };
        self.metrics.busy_seconds.inc_by(t.elapsed().as_secs_f64());
        let waker = {
            let mut g = lock(&st.state);
            g.running -= 1;
            // the estimate reserved at dispatch becomes the sample's real size
            let size = match &item {
                Some(Ok((_, n))) if !g.closed => *n as u64,
                _ => 0,
            };
            if !g.closed {
                g.held = g.held - reserved + size;
                if size > 0 {
                    g.estimate = size;
                }
                self.account(&st, size, reserved);
            }
            if let Some(item) = item {
                if !g.closed {
                    g.produced += 1;
                    g.ready.insert(k, item);
                    self.metrics.set_queue_depth(st.id, g.ready.len());
                    // a job that was running when the shares shrank may leave the stream over its share
                    if g.held > st.share.load(Ordering::Acquire) {
                        self.trim(&st, &mut g);
                    }
                }
            }
            g.waker.take()
        };
        if let Some(w) = waker {
            w.wake();
        }
        {
            let mut s = lock(&self.inner);
            s.in_flight -= 1;
            if others {
                s.others_in_flight -= 1;
            }
            if others {
                s.busy.add(Instant::now(), t.elapsed().as_secs_f64());
            }
            self.metrics.set_in_flight(s.in_flight, self.capacity);
        }
        self.pump();
    }

    fn close(self: &Arc<Self>, st: &Arc<StreamShared>) {
        {
            let mut g = lock(&st.state);
            // a unary reply's stream closes once the reply has left (`service::reply`): taken,
            // unless its connection was closed for not taking it
            if g.in_transport > 0 && !st.conn.as_ref().is_some_and(|c| c.is_cut()) {
                st.group.took.store(true, Ordering::Release);
            }
            g.closed = true;
            g.ready.clear();
            // what running jobs reserved is released here; they hand back nothing when done
            self.account(st, 0, g.held);
            g.held = 0;
            g.in_transport = 0;
        }
        {
            let mut s = lock(&self.inner);
            s.streams.retain(|x| !Arc::ptr_eq(x, st));
            if !s.streams.iter().any(|x| x.peer == st.peer) {
                if let Some(g) = s.groups.remove(&st.peer) {
                    let used = g.used.load(Ordering::Acquire);
                    if s.past_used.len() >= MAX_PENALTIES {
                        let vclock = s.vclock;
                        s.past_used.retain(|_, u| u.0 > vclock);
                        if s.past_used.len() >= MAX_PENALTIES {
                            if let Some(least) = s.past_used.iter().min_by_key(|(_, u)| u.0).map(|(k, _)| *k) {
                                s.past_used.remove(&least);
                            }
                        }
                    }
                    s.past_used.insert(st.peer, (used, g.took.load(Ordering::Acquire)));
                }
                s.rr_in_peer.remove(&st.peer);
            }
            self.reshare(&s);
        }
        self.metrics.remove_stream(st.id);
        self.pump();
    }

    /// Stops starting jobs; every stream sends what is finished, then ends with its cursor.
    pub fn begin_drain(&self) {
        let streams = {
            let mut s = lock(&self.inner);
            s.draining = true;
            s.streams.clone()
        };
        for st in streams {
            let w = {
                let mut g = lock(&st.state);
                g.draining = true;
                g.waker.take()
            };
            if let Some(w) = w {
                w.wake();
            }
        }
    }

    pub fn stats(&self) -> SchedulerStats {
        let s = lock(&self.inner);
        SchedulerStats {
            streams: s.streams.len(),
            in_flight: s.in_flight,
            max_in_flight_seen: s.max_in_flight_seen,
            capacity: self.capacity,
            budget: self.budget,
            buffered: self.buffered.load(Ordering::Acquire),
            max_buffered_seen: self.max_buffered_seen.load(Ordering::Acquire),
            dropped: self.dropped.load(Ordering::Acquire),
            held: s.streams.iter().map(|st| lock(&st.state).held).collect(),
            waiting_scene: s.waiting_scene + s.ready_jobs.len(),
            eligible: {
                let (room, first) = (self.room(), self.first_in_line(&s, Instant::now()));
                let spare = |st: &StreamShared| self.spare(room, Some(st.peer) == first);
                s.streams.iter().filter(|st| st.eligible(&lock(&st.state), room, spare(st))).count()
            },
            per_stream: s
                .streams
                .iter()
                .map(|st| {
                    let (d, v, p, q) = st.counts();
                    (st.id, d, v, p, q)
                })
                .collect(),
        }
    }
}

/// The consumer side of a stream: yields batches in index order as tonic polls it. Dropping it
/// (the client went away) closes the stream.
pub struct SampleStream {
    shared: Arc<StreamShared>,
    scheduler: Arc<Scheduler>,
    finished: bool,
}

impl SampleStream {
    pub fn id(&self) -> u64 {
        self.shared.id
    }

    fn end_with(&mut self, mut status: Status, delivered: u64) -> Poll<Option<Result<pb::SampleBatch, Status>>> {
        self.finished = true;
        if self.shared.indices.is_none() {
            let (next, resume) = self.shared.spec.cursor(delivered);
            with_cursor(&mut status, next, resume);
        }
        Poll::Ready(Some(Err(status)))
    }
}

impl Stream for SampleStream {
    type Item = Result<pb::SampleBatch, Status>;

    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        if self.finished {
            return Poll::Ready(None);
        }
        let shared = self.shared.clone();
        let spec = shared.spec;
        let mut g = lock(&shared.state);
        // the transport asks for the next message: it has taken the previous one
        let released = std::mem::take(&mut g.in_transport);
        if released > 0 {
            shared.group.took.store(true, Ordering::Release);
            g.held -= released;
            self.scheduler.account(&shared, 0, released);
            drop(g);
            self.scheduler.pump(); // the stream may start jobs again
            g = lock(&shared.state);
        }
        let remaining = shared.len - g.delivered;
        if remaining == 0 {
            drop(g);
            self.finished = true;
            return Poll::Ready(None);
        }
        // a failed sample at the head ends the stream; the cursor points at it
        if matches!(g.ready.get(&g.delivered), Some(Err(_))) {
            let delivered = g.delivered;
            let Some(Err(e)) = g.ready.remove(&delivered) else { unreachable!() };
            g.closed = true;
            drop(g);
            return self.end_with(e.into(), delivered);
        }
        let want = (spec.batch_size as u64).min(remaining) as usize;
        let mut contiguous = 0usize;
        while contiguous < want && matches!(g.ready.get(&(g.delivered + contiguous as u64)), Some(Ok(_))) {
            contiguous += 1;
        }
        let drained = g.draining && g.running == 0;
        // at its share of the budget, with nothing running, a stream sends the batch it has
        // (the room a client first in line may take beyond its share is not counted here: the
        // dispatch, which knows who is first, does not run under a stream's lock)
        let room = self.scheduler.room();
        let at_share = g.running == 0 && !shared.eligible(&g, room, self.scheduler.spare(room, false));
        if contiguous > 0 && (contiguous == want || drained || at_share) {
            let mut samples = Vec::with_capacity(contiguous);
            let mut bytes = 0usize;
            let mut moved = 0u64;
            for _ in 0..contiguous {
                let k = g.delivered;
                let size = match g.ready.get(&k) {
                    Some(Ok((_, n))) => *n,
                    _ => break,
                };
                if !samples.is_empty() && bytes + size + 16 > spec.max_message_bytes {
                    break; // cut the batch short rather than exceed the message limit
                }
                if let Some(Ok((s, n))) = g.ready.remove(&k) {
                    bytes += n + 16;
                    moved += n as u64;
                    samples.push(s);
                    g.delivered += 1;
                }
            }
            let delivered = g.delivered;
            let depth = g.ready.len();
            // the samples move from the queue to the transport: still held until the next poll
            g.in_transport = moved;
            g.in_transport_since = Instant::now();
            g.trimmed = false;
            drop(g);
            let (next_index, resume_start_index) = shared.cursor(delivered);
            let m = &self.scheduler.metrics;
            m.samples_sent.inc_by(samples.len() as u64);
            m.bytes_sent.inc_by(bytes as u64);
            m.set_queue_depth(shared.id, depth);
            self.scheduler.pump();
            return Poll::Ready(Some(Ok(pb::SampleBatch { samples, next_index, resume_start_index })));
        }
        if drained {
            let delivered = g.delivered;
            g.closed = true;
            drop(g);
            return self.end_with(ServiceError::Draining.into(), delivered);
        }
        g.waker = Some(cx.waker().clone());
        Poll::Pending
    }
}

impl Drop for SampleStream {
    fn drop(&mut self) {
        self.scheduler.close(&self.shared);
    }
}
