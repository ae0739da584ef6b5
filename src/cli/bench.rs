//! `mpiflow bench render` (speed) and `mpiflow bench accuracy` (error against run time).

use super::CliError;
use clap::{Args, Subcommand};
use mpiflow::bench::accuracy::{
    load_photo_scene, machine_description, markdown, run_accuracy, sphere_scene, tilted_plane_scene, write_plot,
    AccuracyConfig, ReportMeta,
};
use mpiflow::bench::{bench_render, peak_rss_mib, RenderBenchConfig};
use mpiflow::render::{Mode, Resample, Skip};
use std::path::PathBuf;

#[derive(Subcommand, Debug)]
pub enum BenchCommand {
    /// Median time of image + flow + depth renders of a synthetic MPI.
    Render(RenderBench),
    /// Flow and image error against render time for N = 4..128 planes, both layerings, the
    /// work-skipping thresholds and f32 against f64; writes a markdown report and a PNG plot.
    Accuracy(AccuracyBench),
    /// Median time of whole samples (cached scene, renders, merge, inpainting) of a synthetic
    /// RGB-D scene with one moving object, and without it; the share of each stage.
    Sample(SampleBench),
    /// Delivered samples/s of `mpiflow serve` over loopback against the in-process generator
    /// rate on the same workers; time to first sample, p99 gap, memory with stalled/fast clients.
    Serve(super::bench_serve::ServeBench),
    /// The figures to check before training on a photo collection: photometric error on valid,
    /// non-occluded pixels, label-law violations, hole fraction, thin-line runs, valid and
    /// occluded fractions, flow magnitude percentiles; per merge rule, with and without objects.
    Quality(QualityBench),
    /// A real server under fast, stalled, slow, cancelling and uploading clients for M minutes:
    /// RSS over time, fast-client rate against a solo run, errors by code, lost/repeated indices.
    Soak(super::bench_soak::SoakBench),
}

#[derive(Args, Debug)]
pub struct QualityBench {
    /// A folder of photos or the reference layout (default: the bundled scenes).
    #[arg(long)]
    source: Option<PathBuf>,
    /// Samples per row of the table.
    #[arg(long, default_value_t = 12)]
    count: u64,
    /// Resize every image to WxH (default: the bundled scenes' 640x480, photos as they are).
    #[arg(long, value_parser = mpiflow::sample::pipeline::parse_size)]
    size: Option<(usize, usize)>,
    /// Motion preset: reference, paper-kitti, depthstillation, mixed or stereo.
    #[arg(long, default_value = "reference")]
    preset: mpiflow::sample::motion::MotionPreset,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Colour kernels to compare (comma-separated; default: the default kernel); the table gets
    /// one block of rows per kernel.
    #[arg(long, value_name = "KERNEL", value_delimiter = ',', value_parser = super::kernels::resample_parser())]
    resample: Vec<Resample>,
    /// Replace the preset's camera law by a pure lateral translation: tx and ty of random sign
    /// and magnitude uniform in [0, T], no forward part, no rotation (T = 0.05 moves the nearest
    /// content, at depth ~1, by up to 0.58 W x 0.05 ~ 19 px at 640 x 480).
    #[arg(long, value_name = "T")]
    lateral: Option<f64>,
    /// Only the sharpness table: no objects, depth-aware merge, one row per kernel (the sharpness
    /// ratio image2 / image1 with its range, photometric error, hole fraction, flow p50 / p95).
    #[arg(long)]
    sharpness: bool,
    /// Only the realism table: the default merge with each fill (planes, inpaint), 0 and 1
    /// objects: hole fraction, revealed share of image2, detail and noise of the revealed
    /// background against image2's other background, the patch classifiers' AUC (revealed
    /// image2 patches against image1's background; image2 against image1), photometric error
    /// and the forward-backward residual (docs/quality.md).
    #[arg(long)]
    realism: bool,
    /// Every row on the same motions (the addresses of the default configuration of the
    /// preset) instead of each configuration's own draws: a paired comparison of the rules.
    #[arg(long)]
    same_motions: bool,
    /// Restore image1's noise level in image2 (`restore_noise`). With --sharpness: each kernel
    /// also gets a row with the noise restored.
    #[arg(long)]
    restore_noise: bool,
    /// Alias-free minification (`minify`). With --sharpness: each kernel also gets a row with it.
    #[arg(long)]
    minify: bool,
    #[command(flatten)]
    scene: super::scene_flags::SceneFlags,
    /// What fills the holes: exemplar (texture from image1's background) or a Telea variant
    /// (telea, telea-known-only, telea-zero-order, telea-opencv). With --same-motions the rows
    /// keep the default method's motions.
    #[arg(long, value_name = "METHOD", default_value_t = mpiflow::sample::config::InpaintMethod::default())]
    inpaint: mpiflow::sample::config::InpaintMethod,
    /// A real second photo of the scene, the right view of a rectified stereo pair (needs
    /// `--source` in the reference layout with `depths/NAME.npy` for the left photo `NAME`): one
    /// sample is rendered to the right camera and compared with it (image error, sharpness, flow
    /// error against the measured disparity `FB / depth`; docs/quality.md, "The real view").
    #[arg(long, value_name = "FILE", requires = "source")]
    right_view: Option<PathBuf>,
    /// Focal length times baseline of the stereo pair, in pixels times the depth file's units
    /// (disparity = FB / depth).
    #[arg(long, value_name = "FB", default_value_t = 100.0, requires = "right_view")]
    focal_baseline: f64,
}

#[derive(Args, Debug)]
pub struct SampleBench {
    #[arg(long, default_value_t = 640)]
    width: usize,
    #[arg(long, default_value_t = 480)]
    height: usize,
    /// Planes of the built-in layering (default: the scene models' default).
    #[arg(long, value_name = "N")]
    planes: Option<usize>,
    /// Where the planes go: content or uniform (default: the scene models' default).
    #[arg(long, value_name = "KIND")]
    placement: Option<mpiflow::mpi::layering::Placement>,
    /// Layering of the built-in MPI: soft, hard or true-depth (default: the scene models'
    /// default).
    #[arg(long, value_name = "KIND")]
    layering: Option<mpiflow::mpi::layering::Layering>,
    /// Complete the background behind the object and depth edges (default: the scene models'
    /// default, off).
    #[arg(long, value_name = "BOOL", num_args = 0..=1, default_missing_value = "true")]
    backdrop: Option<bool>,
    /// Timed samples per case (after one warm-up sample that fills the cache).
    #[arg(long, default_value_t = 10)]
    samples: usize,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Merge rule: depth-aware or reference.
    #[arg(long, default_value = "depth-aware")]
    merge: mpiflow::sample::merge::MergeRule,
    /// Motion preset: reference, paper-kitti, depthstillation, mixed or stereo.
    #[arg(long, default_value = "reference")]
    preset: mpiflow::sample::motion::MotionPreset,
    /// Render the object and mask channel over full frames (the reference's way) instead of windows.
    #[arg(long)]
    full_frame: bool,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Also time a training augmentation of each sample (a preset such as raft-chairs, or its
    /// JSON form; docs/augment.md), on one thread.
    #[arg(long, value_name = "NAME|JSON")]
    augment: Option<String>,
    /// Frames per sample: 2 = a pair, 3 to 8 = a clip (docs/outputs.md).
    #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(u64).range(2..=8))]
    frames: u64,
    /// Also make the backward fields (flow image2 -> image1 and its masks).
    #[arg(long)]
    backward: bool,
    /// Restore image1's noise level in image2 (`restore_noise`; its time is part of the
    /// inpaint stage).
    #[arg(long)]
    restore_noise: bool,
    /// Alias-free minification of the target renders (`minify`).
    #[arg(long)]
    minify: bool,
    /// Leave out the occlusion mask, as the service does for requests that do not ask for it.
    #[arg(long)]
    no_occlusion: bool,
    /// What fills the holes: exemplar (texture from image1's background) or a Telea variant.
    #[arg(long, value_name = "METHOD", default_value_t = mpiflow::sample::config::InpaintMethod::default())]
    inpaint: mpiflow::sample::config::InpaintMethod,
}

#[derive(Args, Debug)]
pub struct AccuracyBench {
    /// The markdown report; the plot is written next to it with the extension .png.
    #[arg(long, default_value = "docs/accuracy.md")]
    out: PathBuf,
    #[arg(long, default_value_t = 320)]
    width: usize,
    #[arg(long, default_value_t = 240)]
    height: usize,
    /// Timed runs per configuration (after one warm-up run).
    #[arg(long, default_value_t = 7)]
    runs: usize,
    /// The photo of the third scene (resized to the bench size).
    #[arg(long, default_value = "examples/data/images/chelsea.png")]
    photo: PathBuf,
}

#[derive(Args, Debug)]
pub struct RenderBench {
    #[arg(long, default_value_t = 640)]
    width: usize,
    #[arg(long, default_value_t = 480)]
    height: usize,
    /// Planes of the synthetic MPI (default: the scene models' default).
    #[arg(long, default_value_t = mpiflow::scene::models::ModelConfig::default().planes)]
    planes: usize,
    #[arg(long, default_value_t = 10)]
    runs: usize,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    #[arg(long, default_value = "exact")]
    mode: Mode,
    /// Also time each work-skipping variant separately.
    #[arg(long)]
    variants: bool,
    /// Colour kernels to time, comma-separated (default: the default kernel), one after the
    /// other.
    #[arg(long, value_name = "KERNEL", value_delimiter = ',', value_parser = super::kernels::resample_parser())]
    resample: Vec<Resample>,
    /// The passes to time: `both` (image2 and the forward flow, the default), `target` (image2,
    /// its depth and coverage) or `source` (the forward flow and its validity).
    #[arg(long, default_value = "both", value_parser = ["both", "target", "source"])]
    pass: String,
    /// Give the synthetic MPI its surface, so every texel lies at its pixel's own disparity
    /// within its plane's slab: the renders of the true-depth layering (`--layering true-depth`).
    #[arg(long)]
    true_depth: bool,
}

pub fn run(cmd: BenchCommand) -> Result<(), CliError> {
    match cmd {
        BenchCommand::Render(b) => render(b),
        BenchCommand::Accuracy(a) => accuracy(a),
        BenchCommand::Sample(s) => sample(s),
        BenchCommand::Serve(s) => super::bench_serve::run(s),
        BenchCommand::Quality(q) => quality(q),
        BenchCommand::Soak(s) => super::bench_soak::run(s),
    }
}

/// A quality report of one configuration, for the tables below.
type RunQuality<'a> =
    dyn Fn(&mpiflow::sample::config::SampleConfig) -> Result<mpiflow::bench::quality::QualityReport, CliError> + 'a;

/// `bench quality --sharpness`: one row per kernel (and noise / minify variant), no objects.
fn sharpness_table(
    run: &RunQuality<'_>,
    q: &QualityBench,
    base: &mpiflow::sample::config::SampleConfig,
    kernels: &[mpiflow::render::Resample],
) -> Result<(), CliError> {
    use mpiflow::sample::config::SampleConfig;
    println!("| resample | sharpness img2 / img1 (min-max) | ideal warp / img2, pixels img1 sees | img2 / ideal | AUC img2 vs img1 (ideal warp vs img1) | noise img1 / img2 (levels) | photometric | background | fb residual px (across motion edges: px, share) | hole fraction | flow p50 / p95 px |");
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    let mut variants = vec![(false, false)];
    if q.restore_noise {
        variants.push((true, false));
    }
    if q.minify {
        variants.push((false, true));
    }
    for (&resample, (restore_noise, minify)) in kernels.iter().flat_map(|k| variants.iter().map(move |&v| (k, v))) {
        // the backward fields only add outputs (the ideal warp's geometry), no other byte
        let c = SampleConfig { max_objects: 0, resample, restore_noise, minify, backward: true, ..base.clone() };
        let r = run(&c)?;
        let name = match (restore_noise, minify) {
            (true, _) => format!("{resample} + noise"),
            (_, true) => format!("{resample} + minify"),
            _ => resample.to_string(),
        };
        println!(
            "| {name} | {:.3} ({:.3}-{:.3}) | {:.3} / {:.3} | {:.0}% | {} ({}) | {:.2} / {:.2} | {:.4} | {:.4} | {} | {:.4} | {:.2} / {:.2} |",
            r.sharpness,
            r.sharpness_min,
            r.sharpness_max,
            r.ideal_sharpness,
            r.ideal_image2_sharpness,
            if r.ideal_sharpness > 0.0 { 100.0 * r.ideal_image2_sharpness / r.ideal_sharpness } else { 0.0 },
            opt3(r.realism.auc_pair),
            opt3(r.realism.auc_ideal),
            r.noise1,
            r.noise2,
            r.photometric,
            r.photometric_background,
            fb_cell(&r.realism),
            r.hole_fraction,
            r.flow_p50,
            r.flow_p95
        );
    }
    Ok(())
}

/// The forward-backward residual off motion edges, with the reads across them apart.
fn fb_cell(r: &mpiflow::bench::realism::RealismReport) -> String {
    match r.fb_edges {
        Some(e) => format!("{} ({:.3}, {:.1}%)", opt3(r.fb_residual), e.residual, 100.0 * e.share),
        None => opt3(r.fb_residual),
    }
}

/// `bench quality --realism`: per fill and object count (docs/quality.md, "Realism").
fn realism_table(run: &RunQuality<'_>, base: &mpiflow::sample::config::SampleConfig) -> Result<(), CliError> {
    use mpiflow::sample::background::Background;
    use mpiflow::sample::config::SampleConfig;
    println!("| fill | objects | hole fraction | revealed | revealed detail / noise vs other background | AUC revealed vs img1 background | AUC img2 vs img1 | AUC ideal warp vs img1 | object colour revealed - ring (revealed / ring) | photometric | label laws | fb residual px (across motion edges: px, share) |");
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
    for background in [Background::Planes, Background::Inpaint] {
        for objects in [0, 1] {
            let c = SampleConfig { background, max_objects: objects, backward: true, ..base.clone() };
            let r = run(&c)?;
            let laws = r.laws.holes + r.laws.label + r.laws.depth;
            println!(
                "| {background} | {objects} ({} moved) | {:.4} | {:.4} | {} / {} | {} | {} | {} | {} | {:.4} | {laws} | {} |",
                r.with_objects,
                r.hole_fraction,
                r.realism.revealed,
                opt3(r.realism.revealed_detail),
                opt3(r.realism.revealed_noise),
                opt3(r.realism.auc_revealed),
                opt3(r.realism.auc_pair),
                opt3(r.realism.auc_ideal),
                object_colour_cell(r.realism.object_colour),
                r.photometric,
                fb_cell(&r.realism),
            );
        }
    }
    Ok(())
}

/// `bench quality --right-view`: the left photo rendered to the right camera against the right
/// photo (`bench::realview`).
fn real_view_table(
    p: &mpiflow::sample::pipeline::Pipeline,
    base: &mpiflow::sample::config::SampleConfig,
    q: &QualityBench,
    right: &std::path::Path,
    kernels: &[mpiflow::render::Resample],
) -> Result<(), CliError> {
    use mpiflow::bench::realview::RealView;
    use mpiflow::io::image::{load_rgb, rgb_to_u8, ImageLimits};
    use mpiflow::sample::config::{MotionSpec, SampleConfig};
    if q.size.is_some() {
        return Err(CliError("--right-view compares at the photos' own size: leave out --size".into()));
    }
    let source = q.source.as_deref().unwrap_or(std::path::Path::new("."));
    let stem = right.file_stem().and_then(|s| s.to_str()).unwrap_or_default();
    let depth_path = source.join("depths").join(format!("{stem}.npy"));
    let img = load_rgb(right, &ImageLimits::default()).map_err(|e| CliError(format!("{}: {e}", right.display())))?;
    let depth = mpiflow::io::npy::read_npy_file(&depth_path).map_err(|e| {
        CliError(format!("{}: {e} (the left photo's depth, needed by --right-view)", depth_path.display()))
    })?;
    let view =
        RealView::new(img.width, img.height, rgb_to_u8(&img), &depth.data, q.focal_baseline).ok_or_else(|| {
            CliError(format!(
                "{} ({}x{}) and {} ({} values): expected the same size and at least one known depth",
                right.display(),
                img.width,
                img.height,
                depth_path.display(),
                depth.data.len()
            ))
        })?;
    let law = view.law(view.default_fx(), q.focal_baseline);
    let src = p.source();
    let item = (0..src.len()).find(|&i| std::path::Path::new(&src.id(i)).file_stem().is_some_and(|n| n == stem));
    let item = item.ok_or_else(|| CliError(format!("--right-view: the source has no photo named {stem}")))?;
    println!(
        "| real view | kernel | MAE /255 (pair floor) | sharpness vs the right photo | flow EPE px vs measured disparity |"
    );
    println!("|---|---|---|---|---|");
    // one row per colour kernel (the motion is the right camera's, the same for each)
    for &resample in kernels {
        let c = SampleConfig {
            motion: MotionSpec::Ranges(Box::new(law.clone())),
            max_objects: 0,
            resample,
            ..base.clone()
        };
        let g = p.generator().with_config(c).map_err(|e| CliError(e.to_string()))?;
        let s = g.sample(q.seed, item as u64).map_err(|e| CliError(e.to_string()))?;
        let r = view
            .compare(&s)
            .ok_or_else(|| CliError("--right-view: the sample's size differs from the right view".into()))?;
        let (mae, floor, sharp, epe) = (r.mae, r.floor, r.sharpness, r.epe);
        println!("| {} | {resample} | {mae:.2} ({floor:.2}) | {sharp:.3} | {epe:.4} |", right.display());
    }
    Ok(())
}

/// The object-colour column: the excess over the ring, with the two shares.
fn object_colour_cell(c: Option<mpiflow::bench::ghost::ObjectColour>) -> String {
    match c.and_then(|c| Some((c.excess()?, c.revealed_share()?, c.ring_share()?))) {
        Some((e, r, g)) => format!("{e:+.3} ({r:.3} / {g:.3})"),
        None => "-".to_string(),
    }
}

/// A figure with three decimals, or `-` when there is none.
fn opt3(v: Option<f64>) -> String {
    v.map_or_else(|| "-".to_string(), |v| format!("{v:.3}"))
}

fn quality(q: QualityBench) -> Result<(), CliError> {
    use mpiflow::bench::quality::{quality, quality_same_motions};
    use mpiflow::sample::config::{MotionSpec, SampleConfig};
    use mpiflow::sample::pipeline::{open_source, OpenOptions, Pipeline, SourceSpec};
    use mpiflow::scene::cache::SceneCache;
    use std::sync::Arc;
    if q.count == 0 || q.count > 100_000 {
        return Err(CliError("--count must be 1 to 100000".into()));
    }
    let spec = q.source.clone().map_or(SourceSpec::Builtin, SourceSpec::Path);
    let source = open_source(&spec, &OpenOptions { resize: q.size, ..OpenOptions::default() })
        .map_err(|e| CliError(e.to_string()))?;
    let models = q.scene.models();
    let stage = Arc::new(models.build_stage().map_err(|e| CliError(e.to_string()))?);
    let mut base = SampleConfig::with_preset(q.preset);
    let mut motion = q.preset.to_string();
    if let Some(t) = q.lateral {
        if !(t.is_finite() && (0.0..=1.0).contains(&t)) {
            return Err(CliError("--lateral must be 0 to 1".into()));
        }
        base.motion = MotionSpec::Ranges(Box::new(base.motion.ranges().with_lateral_camera(t)));
        motion = format!("lateral (|tx|, |ty| <= {t}, no tz, no rotation)");
    }
    if !q.sharpness {
        base.restore_noise = q.restore_noise;
        base.minify = q.minify;
    }
    let kernels = if q.resample.is_empty() { vec![base.resample] } else { q.resample.clone() };
    // the generator keeps the default method's addresses (--same-motions)
    let p = Pipeline::new(source, stage, Arc::new(SceneCache::new(1 << 30)), base.clone())
        .map_err(|e| CliError(e.to_string()))?;
    base.inpaint_method = q.inpaint;
    println!(
        "{}; {} samples per row, seed {}, motion {motion}, holes filled by {}{}",
        p.describe(),
        q.count,
        q.seed,
        q.inpaint,
        if q.same_motions { ", every row on the same motions" } else { "" }
    );
    let run = |c: &SampleConfig| {
        if q.same_motions {
            quality_same_motions(p.generator(), c, q.seed, q.count)
        } else {
            quality(p.generator(), c, q.seed, q.count)
        }
        .map_err(|e| CliError(e.to_string()))
    };
    scene_line(p.generator(), p.source().len())?;
    if let Some(right) = &q.right_view {
        real_view_table(&p, &base, &q, right, &kernels)?;
    }
    if q.sharpness {
        // every kernel on the same motions (the addresses of the base configuration)
        let same = |c: &SampleConfig| {
            quality_same_motions(p.generator(), c, q.seed, q.count).map_err(|e| CliError(e.to_string()))
        };
        return sharpness_table(&same, &q, &base, &kernels);
    }
    if q.realism {
        return realism_table(&run, &base);
    }
    rules_table(&run, &base, &kernels)
}

/// What the source's scenes cost: the first `items`' scenes (at most 8) built into the generator's
/// cache one at a time and timed (loading, the scene models, the layering and the preparation the
/// cache keeps: what a cache miss costs), and their size in the scene cache (`Scene::byte_size`),
/// medians with the largest; a build that fails is counted, not timed.
fn scene_line(g: &mpiflow::sample::pipeline::Generator, items: usize) -> Result<(), CliError> {
    let n = items.min(8);
    let (mut ms, mut mib, mut failed) = (Vec::new(), Vec::new(), 0);
    // the largest scene's parts: planes (colour and density), B-spline colour coefficients,
    // the rest of the MPI (extras, levels, surface), the photo with its depth and masks
    let mut parts = [0usize; 4];
    let m = |b: usize| b as f64 / f64::from(1 << 20);
    for i in 0..n {
        let t = std::time::Instant::now();
        match g.scene(i) {
            Ok(scene) => {
                ms.push(t.elapsed().as_secs_f64() * 1e3);
                mib.push(m(scene.byte_size()));
                if scene.byte_size() >= parts.iter().sum() {
                    let mpi = &scene.mpi;
                    let planes = mpi.rgba.len() * 4 + mpi.rgba_blocks.as_ref().map_or(0, |b| b.byte_size());
                    let coefficients = mpi.bspline_rgb.as_ref().map_or(0, |c| c.coefficients.byte_size());
                    let rest = mpi.byte_size() - planes - coefficients;
                    parts = [planes, coefficients, rest, scene.byte_size() - mpi.byte_size()];
                }
            }
            Err(_) => failed += 1,
        }
    }
    if ms.is_empty() {
        println!("scenes: none of the first {n} items built");
        return Ok(());
    }
    let (t, sz) = (mpiflow::bench::Timing::from_samples(ms), mpiflow::bench::Timing::from_samples(mib));
    println!(
        "scenes: {} of the first {n} items built one at a time: build median {:.0} ms (max {:.0}), scene cache size median {:.1} MiB (max {:.1}: planes {:.1}, B-spline colour {:.1}, the MPI's other maps {:.1}, photo, depth and masks {:.1}){}",
        t.runs,
        t.median,
        t.max,
        sz.median,
        sz.max,
        m(parts[0]),
        m(parts[1]),
        m(parts[2]),
        m(parts[3]),
        if failed > 0 { format!(", {failed} failed") } else { String::new() }
    );
    Ok(())
}

/// The table of the merge and label rules (`bench quality`'s default): a row per kernel, merge
/// rule, fill and objects.
fn rules_table(
    run: &RunQuality<'_>,
    base: &mpiflow::sample::config::SampleConfig,
    kernels: &[Resample],
) -> Result<(), CliError> {
    use mpiflow::sample::background::Background;
    use mpiflow::sample::config::SampleConfig;
    use mpiflow::sample::merge::{LabelRule, MergeRule};
    println!(
        "| resample | merge | fill | objects | labels | photometric | background | holes law | label law | depth law | hole fraction | lines img2 / img1 | sharpness | valid | occluded | flow p5 / p50 / p95 / p99 / max px | < 1 px |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    for &resample in kernels {
        let rules = [
            (MergeRule::DepthAware, Background::Planes),
            (MergeRule::DepthAware, Background::Inpaint),
            (MergeRule::Reference, Background::Inpaint),
        ];
        for (merge, background) in rules {
            for (objects, labels) in [(0, LabelRule::Honest), (1, LabelRule::Honest), (1, LabelRule::DepthOnly)] {
                let c = SampleConfig {
                    merge,
                    background,
                    max_objects: objects,
                    label_rule: labels,
                    resample,
                    ..base.clone()
                };
                let r = run(&c)?;
                rule_row(&c, &r);
            }
        }
    }
    Ok(())
}

/// One row of [`rules_table`]: the report `r` of the configuration `c`.
fn rule_row(c: &mpiflow::sample::config::SampleConfig, r: &mpiflow::bench::quality::QualityReport) {
    use mpiflow::bench::quality::QualityReport;
    use mpiflow::sample::merge::{LabelRule, MergeRule};
    let (resample, merge, background, objects, labels) =
        (c.resample, c.merge, c.background, c.max_objects, c.label_rule);
    let pct = |r: &QualityReport, n: u64| format!("{:.3}%", 100.0 * r.laws.rate(n));
    println!(
        "| {resample} | {} | {background} | {} ({} moved) | {} | {:.4} | {:.4} | {} | {} | {} | {:.4} | {} / {} | {:.3} | {:.3} | {:.3} | {:.2} / {:.2} / {:.2} / {:.1} / {:.1} | {:.2}% |",
        match merge {
            MergeRule::DepthAware => "depth-aware",
            MergeRule::Reference => "reference",
        },
        objects,
        r.with_objects,
        match labels {
            LabelRule::Honest => "honest",
            LabelRule::DepthOnly => "depth-only",
        },
        r.photometric,
        r.photometric_background,
        pct(r, r.laws.holes),
        pct(r, r.laws.label),
        pct(r, r.laws.depth),
        r.hole_fraction,
        r.lines2,
        r.lines1,
        r.sharpness,
        r.valid_fraction,
        r.occluded_fraction,
        r.flow_p5,
        r.flow_p50,
        r.flow_p95,
        r.flow_p99,
        r.flow_max,
        100.0 * r.below_1px
    );
}

fn accuracy(a: AccuracyBench) -> Result<(), CliError> {
    if a.width < 8 || a.height < 8 || a.width * a.height > 4 << 20 || a.runs == 0 || a.runs > 1000 {
        return Err(CliError("accuracy bench: the size must be 8x8 to 4 Mpx and runs 1 to 1000".into()));
    }
    if !cfg!(feature = "plots") {
        return Err(CliError(
            "accuracy bench: this build has no plotting; run it as `cargo run --release --features plots -- bench accuracy ...`"
                .into(),
        ));
    }
    let start = std::time::Instant::now();
    let photo = load_photo_scene(&a.photo, a.width, a.height)?;
    let scenes = [tilted_plane_scene(a.width, a.height), sphere_scene(a.width, a.height), photo];
    let cfg = AccuracyConfig::new(a.width, a.height, a.runs);
    let report = run_accuracy(&cfg, &scenes, &mut |line: &str| eprintln!("{line}"))?;
    let plot = a.out.with_extension("png");
    if let Some(dir) = a.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|e| CliError(format!("{}: {e}", dir.display())))?;
    }
    write_plot(&report, &plot, 1500, 620)?;
    let meta = ReportMeta {
        command: format!(
            "cargo run --release --features plots -- bench accuracy --out {} --width {} --height {} --runs {} --photo {}",
            a.out.display(),
            a.width,
            a.height,
            a.runs,
            a.photo.display()
        ),
        machine: machine_description(),
        plot: plot.file_name().map_or_else(String::new, |n| n.to_string_lossy().into_owned()),
        total_s: start.elapsed().as_secs_f64(),
    };
    std::fs::write(&a.out, markdown(&report, &meta)).map_err(|e| CliError(format!("{}: {e}", a.out.display())))?;
    println!("wrote {} and {} in {:.0} s", a.out.display(), plot.display(), start.elapsed().as_secs_f64());
    Ok(())
}

fn render(b: RenderBench) -> Result<(), CliError> {
    if b.width == 0 || b.height == 0 || b.planes == 0 || b.width * b.height > 64 << 20 || b.planes > 256 {
        return Err(CliError("bench sizes must be positive, at most 64 Mpx and 256 planes".into()));
    }
    let threads = b.threads.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, std::num::NonZero::get));
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build()?;
    let skip = if b.mode == Mode::Exact { Skip::DEFAULT } else { Skip::NONE };
    let mut variants = vec![("default", skip)];
    if b.variants && b.mode == Mode::Exact {
        variants = vec![
            ("no skipping", Skip::NONE),
            ("tile skipping", Skip { tiles: true, ..Skip::NONE }),
            ("early stop T<1e-4", Skip { transmittance_eps: 1e-4, ..Skip::NONE }),
            ("both (default)", Skip::DEFAULT),
        ];
    }
    let kernels = if b.resample.is_empty() { vec![Resample::default()] } else { b.resample.clone() };
    for (name, skip) in variants {
        for &resample in &kernels {
            let cfg = RenderBenchConfig {
                width: b.width,
                height: b.height,
                planes: b.planes,
                true_depth: b.true_depth,
                runs: b.runs,
                mode: b.mode,
                skip,
                resample,
                fields: mpiflow::render::Fields {
                    target: b.pass != "source",
                    flow: b.pass != "target",
                    occlusion: false,
                },
            };
            let (t, stats) = pool.install(|| bench_render(&cfg));
            if b.variants {
                print!("{name:>20}: ");
            }
            println!(
                "{resample:>9}: median {:.1} ms (min {:.1}, max {:.1}) over {} runs, {threads} threads, {} pass{}; {} target-view plane samples per render",
                t.median,
                t.min,
                t.max,
                t.runs,
                b.pass,
                if b.pass == "both" { "es" } else { "" },
                stats.samples
            );
        }
    }
    if let Some(m) = peak_rss_mib() {
        println!(
            "peak memory {m:.0} MiB ({}x{}, {} planes, mode {:?}, simd {})",
            b.width,
            b.height,
            b.planes,
            b.mode,
            mpiflow::isa::current()
        );
    }
    Ok(())
}

fn sample(b: SampleBench) -> Result<(), CliError> {
    use mpiflow::bench::sample::{bench_sample, SampleBenchConfig};
    use mpiflow::sample::config::SampleConfig;
    let d = mpiflow::scene::models::ModelConfig::default();
    let models = mpiflow::scene::models::ModelConfig {
        planes: b.planes.unwrap_or(d.planes),
        placement: b.placement.unwrap_or(d.placement),
        layering: b.layering.unwrap_or(d.layering),
        backdrop: b.backdrop.unwrap_or(d.backdrop),
        ..d
    };
    if b.width < 16 || b.height < 16 || b.width * b.height > 16 << 20 || models.planes == 0 || models.planes > 256 {
        return Err(CliError("bench sizes must be 16x16 to 16 Mpx and 1 to 256 planes".into()));
    }
    if b.samples == 0 || b.samples > 10_000 {
        return Err(CliError("--samples must be 1 to 10000".into()));
    }
    let threads = b.threads.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, std::num::NonZero::get));
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build()?;
    let augment = match &b.augment {
        Some(t) => Some(mpiflow::sample::augment::Augment::parse(t).map_err(|e| CliError(format!("--augment: {e}")))?),
        None => None,
    };
    for object in [true, false] {
        let sample = SampleConfig {
            merge: b.merge,
            windowed: !b.full_frame,
            max_objects: usize::from(object),
            frames: b.frames as usize,
            backward: b.backward,
            restore_noise: b.restore_noise,
            minify: b.minify,
            occlusion: !b.no_occlusion,
            inpaint_method: b.inpaint,
            ..SampleConfig::with_preset(b.preset)
        };
        let cfg = SampleBenchConfig {
            width: b.width,
            height: b.height,
            layering: models.layering_options(),
            samples: b.samples,
            object,
            seed: b.seed,
            sample,
            augment: augment.clone(),
        };
        let r = pool.install(|| bench_sample(&cfg))?;
        println!(
            "{}x{}, {} planes ({} placement{}), {} moving object{}, {:?} merge, {} motions, {}, {} frames{}{}{}{}:",
            b.width,
            b.height,
            models.planes,
            models.placement,
            if models.backdrop { ", completed background" } else { "" },
            r.objects,
            if r.objects == 1 { "" } else { "s" },
            b.merge,
            b.preset,
            if b.full_frame { "full-frame object renders" } else { "windowed object renders" },
            b.frames,
            if b.backward { ", backward fields" } else { "" },
            if b.restore_noise { ", noise restored" } else { "" },
            if b.minify { ", minify" } else { "" },
            if b.no_occlusion { ", no occlusion mask" } else { "" }
        );
        println!(
            "median {:.1} ms (min {:.1}, max {:.1}) over {} samples, {threads} threads; median {} holes inpainted",
            r.wall.median, r.wall.min, r.wall.max, r.wall.runs, r.holes_median
        );
        println!("  {:<8} {:>10} {:>10} {:>7}", "stage", "median ms", "mean ms", "share");
        for (name, median, mean, share) in r.stage_table() {
            println!("  {name:<8} {median:>10.2} {mean:>10.2} {:>6.1}%", 100.0 * share);
        }
        if let (Some(t), Some(text)) = (&r.augment, &b.augment) {
            println!(
                "  augment {}: median {:.2} ms (min {:.2}, max {:.2}) per sample on one thread",
                text.trim(),
                t.median,
                t.min,
                t.max
            );
        }
        println!();
    }
    if let Some(m) = peak_rss_mib() {
        println!("peak memory {m:.0} MiB (simd {})", mpiflow::isa::current());
    }
    Ok(())
}
