//! The scheduler: opening and closing streams, the dispatch, the reclaim of room, and the
//! consumer side of a stream.

use std::collections::BTreeMap;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Instant;

use prost::Message;
use tokio_stream::Stream;
use tonic::Status;

use crate::service::conn::Activity;
use crate::service::error::{panic_message, with_cursor, ServiceError};
use crate::service::metrics::Metrics;
use crate::service::pb;
use crate::service::peer::PeerKey;

use super::meter::{Meter, Rate};
use super::sched::{Busy, Pick, Ready, Sched, Tag, CREDIT, HEADROOM_DIVISOR, MAX_PENALTIES, OTHERS_SHARE};
use super::stream::{PeerGroup, StreamShared, StreamState};
use super::workers::Workers;
use super::{lock, Client, Item, Produce, StreamSpec, TICK, UNREAD_GRACE};
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
    /// Bytes of that reserved for the workspace of samples being made.
    making: AtomicU64,
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
    /// Bytes of `buffered` reserved now for the workspace of samples being made.
    pub making: u64,
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
    /// Per client with a call open: the worker time its samples took and how many were made
    /// (what the fair queueing charges it), by key.
    pub per_peer: Vec<PeerUse>,
}

/// A client's use of the workers (`SchedulerStats::per_peer`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PeerUse {
    pub peer: PeerKey,
    /// Worker time its samples took, nanoseconds (each worker's time on the CPU while it made them).
    pub work_ns: u64,
    /// Samples made for it.
    pub samples: u64,
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
            making: AtomicU64::new(0),
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
                rate: Rate::default(),
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
        self.total(add, sub);
    }

    /// Adds `add` and takes `sub` bytes of the workspace of samples being made: in the total
    /// held and in `making`, never in a stream's or a peer's share.
    fn account_making(&self, add: u64, sub: u64) {
        if add >= sub {
            self.making.fetch_add(add - sub, Ordering::AcqRel);
        } else {
            self.making.fetch_sub(sub - add, Ordering::AcqRel);
        }
        self.total(add, sub);
    }

    /// Adds `add` and takes `sub` bytes from the total held.
    fn total(&self, add: u64, sub: u64) {
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
                    work: 0,
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
            let Some(job) = s.ready_jobs.pop_front() else { break };
            self.start_job(&mut s, job);
        }
        while s.in_flight < self.capacity && !s.draining {
            let Some(Pick { stream: st, finish: tag, cost: charged, others }) = self.next_eligible(&mut s) else {
                break;
            };
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
                self.account_making(st.produce.workspace, 0);
                (k, reserved)
            };
            if let Some(prepare) = &st.produce.prepare {
                let (me, later) = (self.clone(), Ready { stream: st.clone(), k, reserved, tag, charged, others });
                let done: Box<dyn FnOnce() + Send> = Box::new(move || me.scene_ready(later));
                if !prepare(st.index(k), done) {
                    s.waiting_scene += 1;
                    continue;
                }
            }
            self.start_job(&mut s, Ready { stream: st, k, reserved, tag, charged, others });
        }
        if s.in_flight < self.capacity {
            self.reclaim(&mut s);
        }
    }

    /// Hands a job to the workers (its scene is ready).
    fn start_job(self: &Arc<Self>, s: &mut Sched, job: Ready) {
        s.in_flight += 1;
        s.max_in_flight_seen = s.max_in_flight_seen.max(s.in_flight);
        self.metrics.set_in_flight(s.in_flight, self.capacity);
        let me = self.clone();
        self.pool.spawn(job.tag, move || me.run_job(job));
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
        // is at most CREDIT of worker time
        let floor = s.vclock.saturating_sub(u64::try_from(CREDIT.as_nanos()).unwrap_or(u64::MAX));
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
                    let finish = used.saturating_add(st.cost(&g, s.rate));
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
        Some(Pick { stream: tag.stream, finish: tag.finish, cost: tag.finish - tag.start, others: !tag.reading })
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

    /// The connection to close so that a client (`newcomer`) refused a stream slot gets one: of
    /// the streams `holds_slot` names, of other clients, one whose message has waited in the
    /// transport for [`UNREAD_GRACE`] while its connection took no DATA as long (a window never
    /// granted, a socket never read), from the client with the most such streams, the longest
    /// waiting first. None when every slot holder makes progress.
    pub fn stalled_holder(&self, newcomer: PeerKey, holds_slot: impl Fn(u64) -> bool) -> Option<Arc<Activity>> {
        let s = lock(&self.inner);
        let stalled: Vec<(PeerKey, std::time::Duration, Arc<Activity>)> = s
            .streams
            .iter()
            .filter(|st| st.peer != newcomer && holds_slot(st.id))
            .filter_map(|st| {
                let conn = st.conn.as_ref().filter(|c| !c.is_cut())?;
                let g = lock(&st.state);
                let waited = g.in_transport_since.elapsed();
                let stalled = g.in_transport > 0 && waited >= UNREAD_GRACE && conn.not_taken_for() >= UNREAD_GRACE;
                stalled.then(|| (st.peer, waited, conn.clone()))
            })
            .collect();
        let of_peer = |p: PeerKey| stalled.iter().filter(|(q, ..)| *q == p).count();
        stalled.iter().max_by_key(|(p, waited, _)| (of_peer(*p), *waited)).map(|(.., c)| c.clone())
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

    fn run_job(self: Arc<Self>, job: Ready) {
        let Ready { stream: st, k, reserved, charged, others, .. } = job;
        let (t, meter) = (Instant::now(), Meter::start());
        let skip = lock(&st.state).closed;
        let item: Option<Item> = if skip {
            None
        } else {
            // the index exists: k < len
            let index = st.index(k);
            let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| (st.produce.make)(index))).unwrap_or_else(
                |payload| {
                    Err(ServiceError::Internal(format!(
                        "sample {index}: the worker panicked: {}",
                        panic_message(payload.as_ref())
                    )))
                },
            );
            Some(r.map(|s| {
                let n = s.encoded_len();
                (s, n)
            }))
        };
        self.metrics.busy_seconds.inc_by(t.elapsed().as_secs_f64());
        let took = meter.ns();
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
                    g.work = took;
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
        self.account_making(0, st.produce.workspace);
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
            if !skip {
                Self::charge(&mut s, &st, charged, took);
            }
        }
        self.pump();
    }

    /// A job of `st` charged `charged` at dispatch took `took` worker nanoseconds: its peer's use
    /// on the virtual clock is set right by the difference, its work counted, and the rate of
    /// work units learns from it.
    fn charge(s: &mut Sched, st: &StreamShared, charged: u64, took: u64) {
        let group = &st.group;
        if took >= charged {
            group.used.fetch_add(took - charged, Ordering::AcqRel);
        } else {
            let refund = charged - took;
            let _ = group.used.fetch_update(Ordering::AcqRel, Ordering::Acquire, |u| Some(u.saturating_sub(refund)));
        }
        group.work_ns.fetch_add(took, Ordering::AcqRel);
        group.made.fetch_add(1, Ordering::AcqRel);
        s.rate.learn(st.produce.work, took);
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
            making: self.making.load(Ordering::Acquire),
            dropped: self.dropped.load(Ordering::Acquire),
            held: s.streams.iter().map(|st| lock(&st.state).held).collect(),
            waiting_scene: s.waiting_scene + s.ready_jobs.len(),
            per_peer: {
                let mut v: Vec<PeerUse> = s
                    .groups
                    .iter()
                    .map(|(peer, g)| PeerUse {
                        peer: *peer,
                        work_ns: g.work_ns.load(Ordering::Acquire),
                        samples: g.made.load(Ordering::Acquire),
                    })
                    .collect();
                v.sort_by_key(|u| u.peer);
                v
            },
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
