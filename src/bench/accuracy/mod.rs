//! Error against run time (`mpiflow bench accuracy`).
//!
//! Scenes with closed-form depth are layered into MPIs of N planes (hard and soft layering, with
//! the source camera's ray lengths, [`build_mpi_for_camera`]) and rendered under one camera
//! motion. Two errors are measured against the render time:
//!
//! - **Flow EPE**: the rendered forward flow against the exact per-pixel flow of the continuous
//!   scene, `X = depth(p) K^-1 p`, `X' = R X + t`, `flow = pi(K X') - p`, averaged over the pixels
//!   that are valid in the exact sense (X' in front of the target camera, `p + flow` inside the
//!   image) and visible in the target view. Visibility is decided in the continuous scene seen by
//!   the source camera, a height field (everything behind a visible surface is solid): the
//!   segment from the point to the target camera centre is marched in the source image (steps of
//!   half a pixel, depth interpolated perspective-correctly along it) and the point is occluded
//!   when the segment passes behind the surface. MPIs from networks blend flow across depth
//!   discontinuities, so the EPE is also reported without the pixels within 2 px of one.
//! - **Image MAE**: the rendered target image against an f64 render of the same scene with
//!   [`AccuracyConfig::reference_planes`] planes (soft layering, no work skipping), mean absolute
//!   error in [0, 1] units over the pixels where the reference coverage exceeds 0.99 (and PSNR).
//!
//! Everything here is a library function; the CLI only calls them. The parts: [`scenes`] (the
//! closed-form scenes and their exact flow), [`metrics`] (the errors), this module (the sweep and
//! convergence orders), [`report`] (the markdown) and [`plot`] (the PNG plot, with the `plots`
//! cargo feature only: `plotters` and its font stay out of builds without it, e.g. the server's).

use crate::bench::{time_runs, Timing};
use crate::geometry::{Intrinsics, Pose};
use crate::io::image::{ImageError, RgbImage};
use crate::mpi::layering::{build_mpi_for_camera, Layering, LayeringOptions, ALPHA_MAX};
use crate::mpi::npz::{load_npz_bytes_limited, save_npz_as, MpiDtype};
use crate::mpi::planes::DELTA_LAST;
use crate::mpi::{Mpi, MpiError};
use crate::render::{render, Fields, Mode, Occupancy, Real, RenderError, RenderOutput, RenderParams, Resample, Skip};
use glam::DVec3;
use rayon::prelude::*;
use std::fmt::Write as _;
use std::path::Path;

pub mod metrics;
#[cfg(feature = "plots")]
pub mod plot;
#[cfg(not(feature = "plots"))]
#[path = "plot_off.rs"]
pub mod plot;
pub mod report;
pub mod scenes;

pub use metrics::*;
pub use plot::*;
pub use report::*;
pub use scenes::*;

#[derive(Debug, thiserror::Error)]
pub enum AccuracyError {
    #[error(transparent)]
    Mpi(#[from] MpiError),
    #[error(transparent)]
    Render(#[from] RenderError),
    #[error(transparent)]
    Image(#[from] ImageError),
    #[error("{0}")]
    Invalid(String),
    #[error("plot: {0}")]
    Plot(String),
}
// ---------------------------------------------------------------------------------------------
// The sweep

#[derive(Clone, Debug)]
pub struct AccuracyConfig {
    pub width: usize,
    pub height: usize,
    /// Timed runs per configuration (after one warm-up run); the median is reported.
    pub runs: usize,
    /// Plane counts of the main sweep.
    pub planes: Vec<usize>,
    /// Planes of the f64 image reference.
    pub reference_planes: usize,
    /// Plane counts (soft layering) at which the skipping variants, f32 against f64 and the
    /// reference mode are measured.
    pub detail_planes: Vec<usize>,
    pub pose: Pose,
}

impl AccuracyConfig {
    /// N in {4, 8, 16, 32, 64, 128}, a 256-plane reference, details at N = 32 and 64,
    /// [`crate::bench::bench_pose`].
    pub fn new(width: usize, height: usize, runs: usize) -> Self {
        Self {
            width,
            height,
            runs,
            planes: vec![4, 8, 16, 32, 64, 128],
            reference_planes: 256,
            detail_planes: vec![32, 64],
            pose: crate::bench::bench_pose(),
        }
    }
}

/// Time and errors of one render configuration.
#[derive(Clone, Copy, Debug)]
pub struct Measurement {
    /// Image + flow + depth (no occlusion pass), median of the timed runs.
    pub time: Timing,
    /// Flow EPE over valid, visible pixels.
    pub epe: f64,
    /// Flow EPE over valid, visible pixels away from depth discontinuities.
    pub epe_edge_free: f64,
    /// Image error against the f64 reference.
    pub image: ImageErr,
    /// Fraction of the target-view plane samples avoided by skipping.
    pub skipped: f64,
}

#[derive(Clone, Debug)]
pub struct SweepRow {
    pub scene: String,
    pub planes: usize,
    pub layering: Layering,
    pub m: Measurement,
}

#[derive(Clone, Debug)]
pub struct SkipRow {
    pub scene: String,
    pub planes: usize,
    pub name: String,
    pub skip: Skip,
    pub m: Measurement,
    /// (max, mean) |image - image without skipping|.
    pub image_diff: (f64, f64),
    /// (max, mean) end-point difference to the flow without skipping.
    pub flow_diff: (f64, f64),
}

#[derive(Clone, Debug)]
pub struct PrecisionRow {
    pub scene: String,
    pub planes: usize,
    pub f32: Measurement,
    pub f64: Measurement,
    pub image_diff: (f64, f64),
    pub flow_diff: (f64, f64),
}

/// One soft MPI rendered as held (f32) and after a round trip through an `.npz` with f16
/// colours and densities ([`crate::mpi::npz::MpiDtype::F16`], what `mpiflow bake --mpi-dtype
/// f16` stores).
#[derive(Clone, Debug)]
pub struct StorageRow {
    pub scene: String,
    pub planes: usize,
    pub f32: Measurement,
    pub f16: Measurement,
    /// (max, mean) |image from the f16 file - image from the f32 MPI|.
    pub image_diff: (f64, f64),
    /// (max, mean) end-point difference between the two flows.
    pub flow_diff: (f64, f64),
    /// Bytes of the `.npz` written with f32 and with f16.
    pub bytes: (usize, usize),
}

/// One soft MPI rendered with each colour kernel ([`Resample`]): time, errors (the
/// image against the bilinear f64 reference in `m`, and against an f64 reference with the same
/// kernel), and the sharpness ratio of the render to the scene's photo.
#[derive(Clone, Debug)]
pub struct KernelRow {
    pub scene: String,
    pub planes: usize,
    pub kernel: Resample,
    pub m: Measurement,
    /// Image error against the f64 reference of `reference_planes` planes rendered with the
    /// same kernel (what the planes and f32 cost this kernel).
    pub same_kernel: ImageErr,
    /// Variance of the Laplacian of the render (rounded to 8 bits, over its covered interior)
    /// over that of the photo (`bench::measure::laplacian_variance`); None when either is empty.
    pub sharpness: Option<f64>,
}

#[derive(Clone, Debug)]
pub struct ReferenceModeRow {
    pub scene: String,
    pub planes: usize,
    /// Exact mode, default skipping.
    pub exact: Measurement,
    /// [`Mode::Reference`].
    pub reference: Measurement,
}

#[derive(Clone, Debug)]
pub struct SceneInfo {
    pub name: String,
    pub depth_min: f64,
    pub depth_max: f64,
    pub pixels: usize,
    pub valid: usize,
    pub visible: usize,
    pub edge_free: usize,
    /// Mean exact flow magnitude over the visible pixels (px).
    pub mean_flow: f64,
    /// Time of the f64 reference render (target view only, one run).
    pub reference_ms: f64,
}

#[derive(Clone, Debug)]
pub struct AccuracyReport {
    pub width: usize,
    pub height: usize,
    pub runs: usize,
    pub threads: usize,
    pub reference_planes: usize,
    pub pose: Pose,
    pub scenes: Vec<SceneInfo>,
    pub rows: Vec<SweepRow>,
    pub skips: Vec<SkipRow>,
    pub precision: Vec<PrecisionRow>,
    pub storage: Vec<StorageRow>,
    pub kernels: Vec<KernelRow>,
    pub reference_mode: Vec<ReferenceModeRow>,
}

/// What a scene's measurements compare against.
struct SceneCtx<'a> {
    scene: &'a Scene,
    exact: ExactFlow,
    visible: Vec<bool>,
    edge_free: Vec<bool>,
    ref_image: Vec<f32>,
    ref_coverage: Vec<f32>,
}

fn layer(scene: &Scene, planes: usize, layering: Layering) -> Result<Mpi, AccuracyError> {
    let opts =
        LayeringOptions { planes, layering, disparity_range: None, backdrop: false, ..LayeringOptions::default() };
    Ok(build_mpi_for_camera(&scene.rgb, &scene.depth, scene.width, scene.height, &opts, &scene.k)?)
}

/// Renders image + flow + depth `runs` times (after a warm-up) and measures the last output.
fn measure<T: Real>(
    ctx: &SceneCtx,
    mpi: &Mpi,
    params: &RenderParams,
    occ: Option<&Occupancy>,
    runs: usize,
) -> Result<(Measurement, RenderOutput), AccuracyError> {
    let mut result: Option<Result<RenderOutput, RenderError>> = None;
    let time = time_runs(runs, || result = Some(render::<T>(mpi, params, occ)));
    let out = result.ok_or_else(|| AccuracyError::Invalid("no render ran".into()))??;
    let s = out.stats;
    let total = (s.samples + s.skipped_tile + s.skipped_early) as f64;
    let m = Measurement {
        time,
        epe: flow_epe(&out.flow, &ctx.exact, &ctx.visible),
        epe_edge_free: flow_epe(&out.flow, &ctx.exact, &ctx.edge_free),
        image: image_error(&out.image, &ctx.ref_image, &ctx.ref_coverage),
        skipped: if total > 0.0 { (s.skipped_tile + s.skipped_early) as f64 / total } else { 0.0 },
    };
    Ok((m, out))
}

fn params_for(scene: &Scene, pose: Pose, skip: Skip, mode: Mode) -> RenderParams {
    let mut p = RenderParams::new(scene.k, pose);
    p.mode = mode;
    p.skip = skip;
    p.fields = Fields { target: true, flow: true, occlusion: false };
    p
}

/// The work-skipping variants compared at the detail plane counts.
pub fn skip_variants() -> Vec<(&'static str, Skip)> {
    let t = |eps: f32| Skip { transmittance_eps: eps, ..Skip::NONE };
    vec![
        ("none", Skip::NONE),
        ("tiles", Skip { tiles: true, ..Skip::NONE }),
        ("early stop T<1e-4", t(1e-4)),
        ("early stop T<1e-3", t(1e-3)),
        ("early stop T<1e-2", t(1e-2)),
        ("tiles + T<1e-4 (default)", Skip::DEFAULT),
        ("tiles sigma<=1e-3 + T<1e-4", Skip { tile_sigma_eps: 1e-3, ..Skip::DEFAULT }),
        ("tiles sigma<=0.1 + T<1e-4", Skip { tile_sigma_eps: 0.1, ..Skip::DEFAULT }),
    ]
}

/// Runs the whole measurement over `scenes` in the current rayon pool. `progress` receives one
/// line per finished step.
pub fn run_accuracy(
    cfg: &AccuracyConfig,
    scenes: &[Scene],
    progress: &mut dyn FnMut(&str),
) -> Result<AccuracyReport, AccuracyError> {
    if cfg.width < 2 || cfg.height < 2 || cfg.planes.is_empty() {
        return Err(AccuracyError::Invalid("accuracy bench: the size must be at least 2x2 and N non-empty".into()));
    }
    let mut report = AccuracyReport {
        width: cfg.width,
        height: cfg.height,
        runs: cfg.runs,
        threads: rayon::current_num_threads(),
        reference_planes: cfg.reference_planes,
        pose: cfg.pose,
        scenes: Vec::new(),
        rows: Vec::new(),
        skips: Vec::new(),
        precision: Vec::new(),
        storage: Vec::new(),
        kernels: Vec::new(),
        reference_mode: Vec::new(),
    };
    for scene in scenes {
        if scene.width != cfg.width || scene.height != cfg.height {
            return Err(AccuracyError::Invalid(format!(
                "scene `{}` is {}x{}, the bench is {}x{}",
                scene.name, scene.width, scene.height, cfg.width, cfg.height
            )));
        }
        let exact = exact_flow(scene, &cfg.pose);
        let visible = exact.visible();
        let edge_free = exact.edge_free();
        // the image reference: f64, soft, no skipping
        let mpi = layer(scene, cfg.reference_planes, Layering::Soft)?;
        let mut p = params_for(scene, cfg.pose, Skip::NONE, Mode::Exact);
        p.fields = Fields { target: true, flow: false, occlusion: false };
        let t0 = std::time::Instant::now();
        let reference = render::<f64>(&mpi, &p, None)?;
        let reference_ms = t0.elapsed().as_secs_f64() * 1e3;
        drop(mpi);
        let mean_flow = {
            let (mut s, mut c) = (0.0, 0usize);
            for (i, _) in visible.iter().enumerate().filter(|(_, &v)| v) {
                s += exact.flow[2 * i].hypot(exact.flow[2 * i + 1]);
                c += 1;
            }
            s / c.max(1) as f64
        };
        let finite = scene.depth.iter().filter(|z| z.is_finite()).map(|&z| z as f64);
        let (dmin, dmax) = finite.fold((f64::INFINITY, 0.0f64), |(a, b), z| (a.min(z), b.max(z)));
        report.scenes.push(SceneInfo {
            name: scene.name.clone(),
            depth_min: dmin,
            depth_max: dmax,
            pixels: scene.width * scene.height,
            valid: exact.valid.iter().filter(|&&v| v).count(),
            visible: visible.iter().filter(|&&v| v).count(),
            edge_free: edge_free.iter().filter(|&&v| v).count(),
            mean_flow,
            reference_ms,
        });
        progress(&format!(
            "{}: exact flow and {}-plane f64 reference ({reference_ms:.0} ms)",
            scene.name, cfg.reference_planes
        ));
        let ctx =
            SceneCtx { scene, exact, visible, edge_free, ref_image: reference.image, ref_coverage: reference.coverage };
        for &n in &cfg.planes {
            for layering in [Layering::Hard, Layering::Soft] {
                let mpi = layer(scene, n, layering)?;
                let occ = Occupancy::build(&mpi, 0.0);
                let p = params_for(scene, cfg.pose, Skip::DEFAULT, Mode::Exact);
                let (m, _) = measure::<f32>(&ctx, &mpi, &p, Some(&occ), cfg.runs)?;
                progress(&format!(
                    "{}: N={n:<3} {:<4} {:8.2} ms  EPE {:.4}  MAE {:.5}",
                    scene.name,
                    layering_name(layering),
                    m.time.median,
                    m.epe_edge_free,
                    m.image.mae
                ));
                report.rows.push(SweepRow { scene: scene.name.clone(), planes: n, layering, m });
                if layering == Layering::Soft && cfg.detail_planes.contains(&n) {
                    details(cfg, &ctx, &mpi, n, &mut report, progress)?;
                }
            }
        }
    }
    Ok(report)
}

/// Skipping variants, f32 against f64 and the reference mode for one soft MPI.
fn details(
    cfg: &AccuracyConfig,
    ctx: &SceneCtx,
    mpi: &Mpi,
    n: usize,
    report: &mut AccuracyReport,
    progress: &mut dyn FnMut(&str),
) -> Result<(), AccuracyError> {
    let scene = ctx.scene;
    let none_params = params_for(scene, cfg.pose, Skip::NONE, Mode::Exact);
    let (m_none, out_none) = measure::<f32>(ctx, mpi, &none_params, None, cfg.runs)?;
    for (name, skip) in skip_variants() {
        let (m, out) = if skip == Skip::NONE {
            (m_none, None)
        } else {
            let occ = skip.tiles.then(|| Occupancy::build(mpi, skip.tile_sigma_eps));
            let p = params_for(scene, cfg.pose, skip, Mode::Exact);
            let (m, out) = measure::<f32>(ctx, mpi, &p, occ.as_ref(), cfg.runs)?;
            (m, Some(out))
        };
        let o = out.as_ref().unwrap_or(&out_none);
        report.skips.push(SkipRow {
            scene: scene.name.clone(),
            planes: n,
            name: name.into(),
            skip,
            m,
            image_diff: abs_diff(&o.image, &out_none.image),
            flow_diff: flow_diff(&o.flow, &out_none.flow),
        });
    }
    progress(&format!("{}: N={n} skipping variants", scene.name));
    let (m64, out64) = measure::<f64>(ctx, mpi, &none_params, None, cfg.runs)?;
    report.precision.push(PrecisionRow {
        scene: scene.name.clone(),
        planes: n,
        f32: m_none,
        f64: m64,
        image_diff: abs_diff(&out_none.image, &out64.image),
        flow_diff: flow_diff(&out_none.flow, &out64.flow),
    });
    progress(&format!("{}: N={n} f32 against f64", scene.name));
    let (f32_bytes, _) = npz_round_trip(mpi, MpiDtype::F32)?;
    let (f16_bytes, stored) = npz_round_trip(mpi, MpiDtype::F16)?;
    let (m16, out16) = measure::<f32>(ctx, &stored, &none_params, None, cfg.runs)?;
    report.storage.push(StorageRow {
        scene: scene.name.clone(),
        planes: n,
        f32: m_none,
        f16: m16,
        image_diff: abs_diff(&out16.image, &out_none.image),
        flow_diff: flow_diff(&out16.flow, &out_none.flow),
        bytes: (f32_bytes, f16_bytes),
    });
    progress(&format!("{}: N={n} MPI stored as f16", scene.name));
    if cfg.detail_planes.first() == Some(&n) {
        kernel_rows(cfg, ctx, mpi, n, report)?;
        progress(&format!("{}: N={n} colour kernels", scene.name));
    }
    let p = params_for(scene, cfg.pose, Skip::NONE, Mode::Reference);
    let (m_ref, _) = measure::<f32>(ctx, mpi, &p, None, cfg.runs)?;
    let exact = report
        .rows
        .iter()
        .rev()
        .find(|r| r.scene == scene.name && r.planes == n && r.layering == Layering::Soft)
        .map(|r| r.m)
        .unwrap_or(m_none);
    report.reference_mode.push(ReferenceModeRow { scene: scene.name.clone(), planes: n, exact, reference: m_ref });
    progress(&format!("{}: N={n} reference mode", scene.name));
    Ok(())
}

/// [`KernelRow`]s of one soft MPI: every kernel at default skipping, against the bilinear f64
/// reference of the scene and against an f64 reference with the same kernel.
fn kernel_rows(
    cfg: &AccuracyConfig,
    ctx: &SceneCtx,
    mpi: &Mpi,
    n: usize,
    report: &mut AccuracyReport,
) -> Result<(), AccuracyError> {
    let scene = ctx.scene;
    let (w, h) = (scene.width, scene.height);
    let to_u8 = |v: &[f32]| -> Vec<u8> { v.iter().map(|&x| (x.clamp(0.0, 1.0) * 255.0 + 0.5) as u8).collect() };
    let photo = crate::bench::measure::laplacian_variance(&to_u8(&scene.rgb), w, h, |_| true);
    let reference_mpi = layer(scene, cfg.reference_planes, Layering::Soft)?;
    for kernel in Resample::ALL {
        let mut m_k = mpi.clone();
        crate::render::resample::prefilter(&mut m_k, kernel);
        let occ = Occupancy::build(&m_k, 0.0);
        let mut p = params_for(scene, cfg.pose, Skip::DEFAULT, Mode::Exact);
        p.resample = kernel;
        let (m, out) = measure::<f32>(ctx, &m_k, &p, Some(&occ), cfg.runs)?;
        let mut r_k = reference_mpi.clone();
        crate::render::resample::prefilter(&mut r_k, kernel);
        let mut pr = params_for(scene, cfg.pose, Skip::NONE, Mode::Exact);
        pr.fields = Fields { target: true, flow: false, occlusion: false };
        pr.resample = kernel;
        let reference = render::<f64>(&r_k, &pr, None)?;
        let same_kernel = image_error(&out.image, &reference.image, &reference.coverage);
        let covered = |i: usize| out.coverage[i] > 0.999;
        let rendered = crate::bench::measure::laplacian_variance(&to_u8(&out.image), w, h, covered);
        let sharpness = match (rendered, photo) {
            (Some(a), Some(b)) if b > 0.0 => Some(a / b),
            _ => None,
        };
        report.kernels.push(KernelRow { scene: scene.name.clone(), planes: n, kernel, m, same_kernel, sharpness });
    }
    Ok(())
}

/// `mpi` written to an in-memory `.npz` with `dtype` and read back (sanitised, as a source loads
/// it): the file's size and what a reader gets.
fn npz_round_trip(mpi: &Mpi, dtype: MpiDtype) -> Result<(usize, Mpi), AccuracyError> {
    let bad = |e: &dyn std::fmt::Display| AccuracyError::Invalid(format!("MPI npz round trip: {e}"));
    let bytes = save_npz_as(mpi, std::io::Cursor::new(Vec::new()), dtype).map_err(|e| bad(&e))?.into_inner();
    let mut back = load_npz_bytes_limited(&bytes, "round trip", u64::MAX).map_err(|e| bad(&e))?;
    back.sanitize();
    Ok((bytes.len(), back))
}

pub fn layering_name(l: Layering) -> &'static str {
    match l {
        Layering::Hard => "hard",
        Layering::Soft => "soft",
        Layering::TrueDepth => "true-depth",
    }
}

// ---------------------------------------------------------------------------------------------
// Convergence orders

/// The observed convergence of one error with the number of planes: error ~ N^slope.
#[derive(Clone, Debug)]
pub struct Order {
    pub scene: String,
    pub layering: Layering,
    pub metric: &'static str,
    pub slope: f64,
    pub n_min: usize,
    pub n_max: usize,
}

/// Flow errors below this are left out of the convergence fits when the report has no f32 against
/// f64 rows to measure the rounding floor from (see [`epe_fit_floor`]).
pub const EPE_FIT_FLOOR: f64 = 1e-4;

/// Flow errors below the floor no longer follow N: ten times the largest mean end-point
/// difference between f32 and f64 renders of the same MPI, or [`EPE_FIT_FLOOR`] without such rows.
pub fn epe_fit_floor(report: &AccuracyReport) -> f64 {
    let m = report.precision.iter().map(|r| r.flow_diff.1).filter(|v| v.is_finite()).fold(f64::NAN, f64::max);
    if m.is_finite() && m > 0.0 {
        10.0 * m
    } else {
        EPE_FIT_FLOOR
    }
}

pub const METRIC_EPE: &str = "flow EPE (edge-free)";
pub const METRIC_EPE_ALL: &str = "flow EPE (visible)";
pub const METRIC_MAE: &str = "image MAE";

/// Reads one error out of a measurement.
type Metric = fn(&Measurement) -> f64;

/// Least-squares slopes of log(error) against log(N), per scene, layering and metric, over the
/// whole sweep, leaving out flow errors below [`epe_fit_floor`]. The image MAE is fitted over
/// N <= reference_planes / 4 only: close to the reference's own N the error to the reference
/// falls faster than the error to the truth.
pub fn convergence_orders(report: &AccuracyReport) -> Vec<Order> {
    let mut out = Vec::new();
    let floor = epe_fit_floor(report);
    for s in &report.scenes {
        for layering in [Layering::Hard, Layering::Soft] {
            let rows: Vec<&SweepRow> =
                report.rows.iter().filter(|r| r.scene == s.name && r.layering == layering).collect();
            if rows.len() < 2 {
                continue;
            }
            let metrics: [(&'static str, Metric, usize, f64); 3] = [
                (METRIC_EPE, |m| m.epe_edge_free, usize::MAX, floor),
                (METRIC_EPE_ALL, |m| m.epe, usize::MAX, floor),
                (METRIC_MAE, |m| m.image.mae, (report.reference_planes / 4).max(2), 0.0),
            ];
            for (metric, f, nmax, floor) in metrics {
                let sel: Vec<&&SweepRow> = rows.iter().filter(|r| r.planes <= nmax && f(&r.m) >= floor).collect();
                let pts: Vec<(f64, f64)> = sel.iter().map(|r| (r.planes as f64, f(&r.m))).collect();
                out.push(Order {
                    scene: s.name.clone(),
                    layering,
                    metric,
                    slope: log_log_slope(&pts),
                    n_min: sel.iter().map(|r| r.planes).min().unwrap_or(0),
                    n_max: sel.iter().map(|r| r.planes).max().unwrap_or(0),
                });
            }
        }
    }
    out
}
