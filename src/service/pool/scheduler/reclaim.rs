//! The room a stream waits for: what the dispatch takes back from the streams that hold more than
//! their share or do not take what they were sent ([`Scheduler::reclaim`]).

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Instant;

use super::super::sched::Sched;
use super::super::stream::StreamShared;
use super::super::{lock, UNREAD_GRACE};
use super::Scheduler;
use crate::service::conn::Activity;
use crate::service::peer::PeerKey;

/// A stream that may not start for want of room while it, or its client, holds less than its
/// share.
struct Starving {
    stream: Arc<StreamShared>,
    /// Its client holds less than the client's share: the connections of other clients over
    /// theirs may be closed for it.
    peer_under: bool,
    /// It holds nothing: no sample, no message in the transport, no running job.
    holds_nothing: bool,
    /// Its own message does not wait untaken (`StreamShared::unread`).
    reads: bool,
}

impl Scheduler {
    /// Makes room for the streams that may not start for want of it while they hold less than
    /// their share, or their client less than its share (a stream holding nothing among them):
    /// the other streams over their share drop finished samples down to it, and, for a stream
    /// whose own message is taken, the streams whose message waits untaken
    /// (`StreamShared::unread`) drop every finished sample (all are made again, byte for byte,
    /// when they read on). For a client holding less than its share, a connection of another
    /// client over its share whose message has waited in the transport for [`UNREAD_GRACE`], its
    /// client taking none of its bytes as long, is closed (its calls end, their bytes are freed)
    /// and that client put in time out (`sched::Penalty`). A stream holding nothing that may not
    /// start even then has the room made within its own client ([`Scheduler::make_room_in_client`]).
    pub(super) fn reclaim(&self, s: &mut Sched) {
        if s.draining {
            return;
        }
        let first = self.first_in_line(s, Instant::now());
        let starving = self.starving(s, first);
        if starving.is_empty() {
            return;
        }
        let for_other_client = starving.iter().any(|x| x.peer_under);
        let for_reader = starving.iter().any(|x| x.reads);
        let mut cut = Vec::new();
        for st in &s.streams {
            let peer_over = st.group.held.load(Ordering::Acquire) > st.group.share.load(Ordering::Acquire);
            let mut g = lock(&st.state);
            let unread = st.unread(&g);
            // (a stream whose message waits untaken gives way to one that reads even when it too
            // would start a job)
            if unread && for_reader {
                self.shed(st, &mut g, 0, 0);
            } else if g.held > st.share.load(Ordering::Acquire) && !starving.iter().any(|x| Arc::ptr_eq(&x.stream, st))
            {
                self.trim(st, &mut g);
            }
            drop(g);
            let closable = for_other_client && peer_over && unread;
            if let Some(conn) = st.conn.as_ref().filter(|c| closable && !c.is_cut()) {
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
        if !cut.is_empty() {
            for peer in cut {
                s.penalise(peer);
            }
            return;
        }
        for x in starving.iter().filter(|x| x.holds_nothing) {
            self.make_room_in_client(s, &x.stream, first);
        }
    }

    /// The streams that may not start for want of room (and would with room enough) while they
    /// hold less than their share, or nothing, or their client less than its share.
    fn starving(&self, s: &Sched, first: Option<PeerKey>) -> Vec<Starving> {
        let room = self.room();
        s.streams
            .iter()
            .filter_map(|st| {
                let g = lock(&st.state);
                let peer_under = st.group.held.load(Ordering::Acquire) < st.group.share.load(Ordering::Acquire);
                let holds_nothing = g.held == 0 && g.running == 0;
                let under = peer_under || holds_nothing || g.held < st.share.load(Ordering::Acquire);
                let waits = !st.eligible(&g, room, self.spare(room, Some(st.peer) == first))
                    && st.eligible(&g, u64::MAX, u64::MAX);
                (under && waits).then(|| Starving {
                    stream: st.clone(),
                    peer_under,
                    holds_nothing,
                    reads: !st.unread(&g),
                })
            })
            .collect()
    }

    /// A stream holding nothing may start one job whatever its client holds: when it may not
    /// start even once the running jobs are done and its client's other streams whose message
    /// waits in the transport have dropped every finished sample, the connections of its own
    /// client whose message waits untaken (`StreamShared::unread`; a connection of the stream's
    /// own is never closed for it) are closed, the longest waiting first, as many as its job
    /// needs. Its client is not put in time out: it reads.
    fn make_room_in_client(&self, s: &Sched, st: &Arc<StreamShared>, first: Option<PeerKey>) {
        if s.in_time_out(st.peer, Instant::now()) {
            return;
        }
        let may = |room: u64| st.eligible(&lock(&st.state), room, self.spare(room, Some(st.peer) == first));
        let mut freed = self.room().saturating_add(self.making.load(Ordering::Acquire));
        let (mut droppable, mut holders) = (0u64, Vec::new());
        let own_conn = |c: &Arc<Activity>| st.conn.as_ref().is_some_and(|o| Arc::ptr_eq(o, c));
        for o in s.streams.iter().filter(|o| o.peer == st.peer && !Arc::ptr_eq(o, st)) {
            let g = lock(&o.state);
            match o.conn.as_ref() {
                // closing: what it holds is freed as soon as its calls end
                Some(c) if c.is_cut() => freed = freed.saturating_add(g.held),
                _ if g.in_transport > 0 => {
                    // what it has made or is making ahead goes first, once its message has
                    // waited untaken
                    droppable = droppable.saturating_add(g.held.saturating_sub(g.in_transport));
                    if let Some(c) = o.conn.as_ref().filter(|c| o.unread(&g) && !own_conn(c)) {
                        holders.push((g.in_transport_since, g.in_transport, c.clone()));
                    }
                }
                _ => {}
            }
        }
        freed = freed.saturating_add(droppable);
        if may(freed) {
            return;
        }
        holders.sort_by_key(|(since, ..)| *since);
        for (_, in_transport, conn) in holders {
            if may(freed) {
                break;
            }
            tracing::info!(
                peer = %st.peer,
                stream = st.id,
                grace_ms = UNREAD_GRACE.as_millis() as u64,
                "connection closed: it holds made samples it does not take, and a stream of the same client that \
                 holds nothing needs the room"
            );
            self.metrics.holders_cut.inc();
            conn.cut();
            freed = freed.saturating_add(in_transport);
        }
    }
}
