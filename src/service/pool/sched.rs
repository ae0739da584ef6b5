//! The dispatch's state: the streams, the virtual clock, the clients in time out, and the
//! workers' recent time on clients that do not read.

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Instant;

use super::meter::Rate;
use super::stream::{PeerGroup, StreamShared};
use crate::service::peer::PeerKey;

pub(super) struct Sched {
    pub(super) streams: Vec<Arc<StreamShared>>,
    /// The virtual clock of the dispatch: where the job started last started (its start tag), where a peer new to the dispatch starts.
    pub(super) vclock: u64,
    /// Per peer, the position of the stream served last.
    pub(super) rr_in_peer: std::collections::HashMap<PeerKey, u64>,
    pub(super) groups: std::collections::HashMap<PeerKey, Arc<PeerGroup>>,
    pub(super) in_flight: usize,
    pub(super) max_in_flight_seen: usize,
    pub(super) draining: bool,
    pub(super) next_id: u64,
    /// Jobs whose scene became ready, to hand to the workers first.
    pub(super) ready_jobs: std::collections::VecDeque<Ready>,
    /// Jobs waiting for their scene now.
    pub(super) waiting_scene: usize,
    /// Clients whose connection was closed for holding samples they did not take: no job starts
    /// for them until their time is up ([`Penalty`]).
    pub(super) penalties: std::collections::HashMap<PeerKey, Penalty>,
    /// What clients with no open call had used on the virtual clock, and whether they had taken
    /// a message, so that a client whose calls come one at a time (GetSample) keeps its place and
    /// its standing instead of starting again with each call (at most [`MAX_PENALTIES`] clients;
    /// the least used go first).
    pub(super) past_used: std::collections::HashMap<PeerKey, (u64, bool)>,
    /// Jobs dispatched and not yet done for clients that are not reading (`Scheduler::reading`).
    pub(super) others_in_flight: usize,
    /// The workers' recent time on the jobs of clients that are not reading, against all.
    pub(super) busy: Busy,
    /// Worker nanoseconds per work unit, learnt from the samples made.
    pub(super) rate: Rate,
}

/// A peer that has used less worker time than the dispatch's clock, idle for a while, counts
/// from this much below it: its credit is at most this much of the workers' time, so a client
/// that waited long does not take every worker for as long when it comes back. (Use older than
/// that is forgotten: only the clients with jobs to start now are compared, on one clock.)
pub const CREDIT: std::time::Duration = std::time::Duration::from_secs(2);

/// The workers' recent time on the jobs of clients that are not reading
/// (`Scheduler::reading`), each second of it decayed by `exp(-age / BUSY_DECAY_S)`.
#[derive(Clone, Copy, Debug)]
pub(super) struct Busy {
    pub(super) at: Instant,
    pub(super) others: f64,
}

/// How fast the workers' past time fades from [`Busy`], seconds.
pub(super) const BUSY_DECAY_S: f64 = 5.0;

/// While a client that reads has a call open, the clients that do not read (a new client until it
/// has taken its first message, and those whose sent message waits untaken) get at most this
/// part of the workers' time, one job at a time: a job of theirs may take a worker for long (an
/// 8-frame clip of every field takes one about 0.7 s at 640x480) and cannot be stopped once
/// started.
pub const OTHERS_SHARE: f64 = 0.125;

impl Busy {
    pub(super) fn add(&mut self, now: Instant, seconds: f64) {
        let fade = (-(now.saturating_duration_since(self.at).as_secs_f64()) / BUSY_DECAY_S).exp();
        self.at = now;
        self.others = self.others * fade + seconds;
    }

    /// The part of `workers`' recent time spent on clients that are not reading (a constant use
    /// of all of them decays to `workers * BUSY_DECAY_S`).
    pub(super) fn others_part(&self, now: Instant, workers: usize) -> f64 {
        let fade = (-(now.saturating_duration_since(self.at).as_secs_f64()) / BUSY_DECAY_S).exp();
        self.others * fade / (workers.max(1) as f64 * BUSY_DECAY_S)
    }
}

/// A client's time out after its connection was closed for holding samples it did not take:
/// [`PENALTY_FIRST`], doubled at each repeat up to [`PENALTY_MAX`], so that a client that never
/// reads cannot have the workers make sample after sample for it by reconnecting.
#[derive(Clone, Copy, Debug)]
pub(super) struct Penalty {
    pub(super) until: Instant,
    pub(super) strikes: u32,
}

/// A job that takes a client beyond its share leaves `budget / HEADROOM_DIVISOR` of the budget
/// free unless the client is first in line (`Scheduler::first_in_line`).
pub const HEADROOM_DIVISOR: u64 = 4;

/// The first time out of a client closed for not reading.
pub const PENALTY_FIRST: std::time::Duration = std::time::Duration::from_secs(10);
/// The longest time out.
pub const PENALTY_MAX: std::time::Duration = std::time::Duration::from_secs(300);
/// The most clients remembered in time out (older entries go first when it is full).
pub(super) const MAX_PENALTIES: usize = 4096;

impl Sched {
    /// Puts `peer` in time out (see [`Penalty`]).
    pub(super) fn penalise(&mut self, peer: PeerKey) {
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
    pub(super) fn in_time_out(&self, peer: PeerKey, now: Instant) -> bool {
        self.penalties.get(&peer).is_some_and(|p| p.until > now)
    }

    /// Whether `peer` was closed for not reading lately: in time out, or out of it for less than
    /// [`PENALTY_MAX`]. Such a client is not counted among those that read
    /// (`Scheduler::reading`) even when it takes a message again (a client that reads one
    /// message of each call and then stops does not take the readers' turns).
    pub(super) fn struck(&self, peer: PeerKey, now: Instant) -> bool {
        self.penalties.get(&peer).is_some_and(|p| p.until + PENALTY_MAX > now)
    }
}

/// A peer's next job as the dispatch sees it (`Scheduler::tags`).
#[derive(Clone)]
pub(super) struct Tag {
    /// Where the job starts on the virtual clock (the peer's use, at most [`CREDIT`] below the
    /// clock) and where it finishes (plus its cost).
    pub(super) start: u64,
    pub(super) finish: u64,
    pub(super) peer: PeerKey,
    pub(super) reading: bool,
    pub(super) stream: Arc<StreamShared>,
}

/// The job the dispatch starts next: its stream, its finish tag and whether its client is
/// among those that do not read.
pub(super) struct Pick {
    pub(super) stream: Arc<StreamShared>,
    pub(super) finish: u64,
    pub(super) cost: u64,
    pub(super) others: bool,
}

/// A job handed to the workers.
pub(super) struct Ready {
    pub(super) stream: Arc<StreamShared>,
    /// The position it makes.
    pub(super) k: u64,
    /// The bytes it holds in the budget while it runs.
    pub(super) reserved: u64,
    /// Its finish tag (the workers' queue goes by it).
    pub(super) tag: u64,
    /// The worker time it was charged at dispatch, nanoseconds (set right when it is done).
    pub(super) charged: u64,
    /// Its client is among those that do not read.
    pub(super) others: bool,
}
