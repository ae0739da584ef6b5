//! Benchmarks behind `mpiflow bench`: render timing (median of several runs), error against
//! run time (`accuracy`), and a server under a mix of clients for a while (`soak`).

pub mod accuracy;
pub mod clients;
pub mod ghost;
pub mod hostile;
pub mod measure;
pub mod quality;
pub mod realism;
pub mod realview;
pub mod sample;
pub mod soak;

use crate::geometry::{Intrinsics, Pose};
use crate::mpi::synthetic::bench_mpi;
use crate::render::{render, Fields, Mode, Occupancy, RenderParams, RenderStats, Resample, Skip};
use std::time::Instant;

/// Summary of repeated timings, in milliseconds.
#[derive(Clone, Copy, Debug)]
pub struct Timing {
    pub median: f64,
    pub min: f64,
    pub max: f64,
    pub runs: usize,
}

impl Timing {
    pub fn from_samples(mut ms: Vec<f64>) -> Self {
        ms.sort_by(f64::total_cmp);
        let n = ms.len();
        let median = if n % 2 == 1 { ms[n / 2] } else { 0.5 * (ms[n / 2 - 1] + ms[n / 2]) };
        Self { median, min: ms[0], max: ms[n - 1], runs: n }
    }
}

/// Times `f` `runs` times after one warm-up run.
pub fn time_runs(runs: usize, mut f: impl FnMut()) -> Timing {
    f();
    let ms = (0..runs.max(1))
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    Timing::from_samples(ms)
}

/// Peak resident memory of this process in MiB (Linux `VmHWM`), if known.
pub fn peak_rss_mib() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

/// The camera motion used by the render benchmark: a typical sample of the reference law.
pub fn bench_pose() -> Pose {
    Pose::from_axis_angle([0.021, -0.013, 0.008], [0.15, -0.12, -0.17])
}

pub struct RenderBenchConfig {
    pub width: usize,
    pub height: usize,
    pub planes: usize,
    /// The synthetic MPI carries its surface ([`crate::mpi::synthetic::with_surface`]): the
    /// true-depth layering's renders.
    pub true_depth: bool,
    pub runs: usize,
    pub mode: Mode,
    pub skip: Skip,
    pub resample: Resample,
    /// Which passes to time: the target view (image2), the source view (forward flow), or both.
    pub fields: Fields,
}

/// Renders the synthetic benchmark MPI (image + flow + depth; the occlusion pass is left out)
/// `runs` times in the current rayon pool, and returns the timings and one render's counts
/// (the target view's plane samples, what skipping avoided). A kernel's prefilter is computed
/// once before the timed runs (as the scene cache keeps it).
pub fn bench_render(cfg: &RenderBenchConfig) -> (Timing, RenderStats) {
    let mut mpi = bench_mpi(cfg.width, cfg.height, cfg.planes);
    if cfg.true_depth {
        crate::mpi::synthetic::with_surface(&mut mpi);
    }
    crate::render::resample::prefilter(&mut mpi, cfg.resample);
    if crate::render::store::packs(cfg.mode, cfg.resample, false) {
        crate::render::store::pack(&mut mpi);
    }
    let k = Intrinsics::reference_default(cfg.width, cfg.height);
    let mut p = RenderParams::new(k, bench_pose());
    p.mode = cfg.mode;
    p.skip = cfg.skip;
    p.resample = cfg.resample;
    p.fields = cfg.fields;
    // the occupancy belongs to the MPI (built once per cached MPI in the service)
    let occ = Occupancy::build(&mpi, cfg.skip.tile_sigma_eps);
    let mut stats = RenderStats::default();
    let t = time_runs(cfg.runs, || {
        let out = render::<f32>(&mpi, &p, Some(&occ)).expect("benchmark render");
        stats = out.stats;
        std::hint::black_box(out);
    });
    (t, stats)
}
