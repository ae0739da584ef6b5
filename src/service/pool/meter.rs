//! What a job costs the workers: the CPU time of the worker's thread while it makes the sample
//! (`CLOCK_THREAD_CPUTIME_ID`, through rustix; the wall time should it go backwards), and the rate, learnt from the samples made, that turns a request's work units
//! (`service::work`) into worker time before any of its own samples is made.

use std::time::Instant;

/// Worker time a job of a request is charged before any sample says what it takes: this many
/// nanoseconds per work unit until the samples made have calibrated the rate ([`Rate`]).
pub const FIRST_NS_PER_UNIT: f64 = 4.0;

/// How much of the rate each sample made moves ([`Rate::learn`]).
const RATE_STEP: f64 = 0.125;

/// The measure of one job on its worker's thread (a sample's own parallel loops run there too:
/// each worker is a rayon pool of one thread).
pub(super) struct Meter {
    cpu: Option<u64>,
    wall: Instant,
}

impl Meter {
    pub(super) fn start() -> Self {
        Meter { cpu: thread_cpu_ns(), wall: Instant::now() }
    }

    /// The job's worker time so far, nanoseconds (at least 1): the thread's time on the CPU, so
    /// that other load on the machine does not make one client's samples look dearer than
    /// another's.
    pub(super) fn ns(&self) -> u64 {
        let cpu = match (self.cpu, thread_cpu_ns()) {
            (Some(a), Some(b)) if b >= a => Some(b - a),
            _ => None,
        };
        cpu.unwrap_or_else(|| u64::try_from(self.wall.elapsed().as_nanos()).unwrap_or(u64::MAX)).max(1)
    }
}

/// The calling thread's time on the CPU, nanoseconds (`CLOCK_THREAD_CPUTIME_ID`).
fn thread_cpu_ns() -> Option<u64> {
    let t = rustix::time::clock_gettime(rustix::time::ClockId::ThreadCPUTime);
    let ns = u64::try_from(t.tv_sec).ok()?.checked_mul(1_000_000_000)?;
    ns.checked_add(u64::try_from(t.tv_nsec).ok()?)
}

/// Worker nanoseconds per work unit, learnt from the samples made (a moving average over the
/// latest few): what a request's first sample is charged before it says what it takes.
#[derive(Clone, Copy, Debug)]
pub(super) struct Rate(pub(super) f64);

impl Default for Rate {
    fn default() -> Self {
        Rate(FIRST_NS_PER_UNIT)
    }
}

impl Rate {
    /// The worker time of a sample of `units` work units (at least 1 ns).
    pub(super) fn ns(&self, units: u64) -> u64 {
        ((units as f64 * self.0).min(u64::MAX as f64) as u64).max(1)
    }

    /// A sample of `units` took `ns`.
    pub(super) fn learn(&mut self, units: u64, ns: u64) {
        if units > 0 {
            let r = ns as f64 / units as f64;
            if r.is_finite() {
                self.0 += (r - self.0) * RATE_STEP;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A busy loop is measured; the rate moves towards what samples take.
    #[test]
    fn a_job_is_measured_and_the_rate_learns() {
        let m = Meter::start();
        let mut x = 0u64;
        for i in 0..2_000_000u64 {
            x = x.wrapping_mul(31).wrapping_add(i);
        }
        std::hint::black_box(x);
        assert!(m.ns() > 1);
        let mut r = Rate::default();
        for _ in 0..100 {
            r.learn(1000, 40_000);
        }
        assert!((r.0 - 40.0).abs() < 1.0, "{r:?}");
        // units x the rate, truncated, and never 0 (a job always costs something)
        assert_eq!(r.ns(10), (10.0 * r.0) as u64);
        assert!((390..=410).contains(&r.ns(10)), "{r:?}");
        assert_eq!(Rate(0.0).ns(10), 1);
    }
}
