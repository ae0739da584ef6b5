//! The worker threads and their queue, least finish tag first.

use std::sync::{Arc, Mutex};

use super::lock;
use crate::service::error::ServiceError;

pub(super) type Job = Box<dyn FnOnce() + Send>;

/// The workers: each is a rayon pool of one thread, and all take their jobs from one queue, the
/// job of least finish tag first (`Scheduler::next_eligible`; ties in the order they were
/// handed in). A job handed in early for a client that asked for much does not keep a worker
/// from the job of a client first in line handed in after it. A sample's own parallel loops run
/// on its worker's thread; a worker never runs another job nested inside a waiting one (as the
/// threads of a shared rayon pool do while a `join` waits, which buried an old job under a feed
/// of new ones: a stream's sample could wait for as long as other streams kept the workers busy).
pub(super) struct Workers {
    pub(super) queue: Arc<JobQueue>,
    pub(super) _pools: Vec<rayon::ThreadPool>,
}

/// A job in the queue, ordered by (tag, the order it was handed in), least first.
pub(super) struct Queued {
    pub(super) tag: u64,
    pub(super) seq: u64,
    pub(super) job: Job,
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
pub(super) struct JobQueue {
    /// (the jobs handed in, how many were handed in, closed)
    pub(super) jobs: Mutex<(std::collections::BinaryHeap<Queued>, u64, bool)>,
    pub(super) more: std::sync::Condvar,
}

impl JobQueue {
    pub(super) fn push(&self, tag: u64, job: Job) {
        let mut g = lock(&self.jobs);
        let seq = g.1;
        g.1 += 1;
        g.0.push(Queued { tag, seq, job });
        drop(g);
        self.more.notify_one();
    }

    /// A worker's loop: the job of least tag, until the queue is closed and empty.
    pub(super) fn run(&self) {
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
    pub(super) fn new(n: usize) -> Result<Self, ServiceError> {
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

    pub(super) fn spawn(&self, tag: u64, job: impl FnOnce() + Send + 'static) {
        self.queue.push(tag, Box::new(job));
    }
}

impl Drop for Workers {
    fn drop(&mut self) {
        lock(&self.queue.jobs).2 = true;
        self.queue.more.notify_all();
    }
}
