//! `mpiflow bench sample`: the time of whole samples (scene from the cache, scene render, object
//! renders, merge, inpainting) on a synthetic RGB-D scene with one object, and the same without
//! the object, so the object stage's cost (and its absence) shows.

use std::sync::Arc;
use std::time::Instant;

use super::Timing;
use crate::geometry::Intrinsics;
use crate::io::image::RgbImage;
use crate::mpi::layering::{build_mpi_for_scene, LayeringOptions};
use crate::raster::{Grid, Instance, InstanceMasks};
use crate::sample::augment::Augment;
use crate::sample::config::SampleConfig;
use crate::sample::error::SampleError;
use crate::sample::pipeline::Generator;
use crate::sample::StageTimings;
use crate::scene::cache::SceneCache;
use crate::scene::{Disparity, Scene, SceneError, SceneLoader};
use crate::source::Fnv64;

/// A synthetic RGB-D scene: a textured ground receding to a far wall, and (with `object`) an
/// upright rounded box (about 7% of the image, soft 1.5-pixel mask edge) standing on the ground
/// at depth 1.8, laid out by the built-in layering with `opts`.
pub fn synthetic_scene(width: usize, height: usize, opts: &LayeringOptions, object: bool) -> Result<Scene, SceneError> {
    let k = Intrinsics::reference_default(width, height);
    let (w, h) = (width, height);
    let mut rgb = vec![0.0f32; w * h * 3];
    let mut depth = vec![0.0f32; w * h];
    let mut mask = vec![0.0f32; w * h];
    // the object: a box of 0.2 W x 0.45 H with rounded corners, centre (0.42 W, 0.55 H)
    let (ox, oy, hw, hh, r) = (0.42 * w as f32, 0.55 * h as f32, 0.1 * w as f32, 0.225 * h as f32, 0.05 * w as f32);
    let g = Grid::new(w, h);
    for y in 0..h {
        for x in 0..w {
            let i = g.index(x, y);
            let (s, t) = (x as f32 / w as f32, y as f32 / h as f32);
            // ground from depth 1.2 at the bottom to a wall at depth 6 above the horizon
            let d_ground = if t > 0.35 { 1.2 / ((t - 0.35) / 0.65).max(0.2) } else { 6.0 };
            let mut d = d_ground.min(6.0);
            let mut c = [
                0.45 + 0.35 * (23.0 * s + 4.0 * t).sin() * (11.0 * t).cos(),
                0.5 + 0.3 * (17.0 * t - 5.0 * s).sin(),
                0.4 + 0.25 * (31.0 * s * t).cos(),
            ];
            let (dx, dy) = (((x as f32 - ox).abs() - (hw - r)).max(0.0), ((y as f32 - oy).abs() - (hh - r)).max(0.0));
            let m = if object { ((r - (dx * dx + dy * dy).sqrt()) / 1.5 + 0.5).clamp(0.0, 1.0) } else { 0.0 };
            if m > 0.0 {
                d = d.min(1.8);
                c = [0.85, 0.3 + 0.25 * (40.0 * t).sin(), 0.2 + 0.1 * (25.0 * s).cos()];
            }
            mask[i] = m;
            depth[i] = d;
            rgb[3 * i..3 * i + 3].copy_from_slice(&c);
        }
    }
    let union: Vec<bool> = mask.iter().map(|&m| m >= 0.5).collect();
    let mpi = build_mpi_for_scene(&rgb, &depth, w, h, opts, &k, &union)?;
    let near = depth.iter().copied().fold(f32::MAX, f32::min);
    let masks = if object {
        InstanceMasks { width: w, height: h, masks: vec![Instance::new(1, 1.0, mask)] }
    } else {
        InstanceMasks::new(w, h)
    };
    Ok(Scene {
        id: format!("synthetic-{w}x{h}{}", if object { "-object" } else { "" }),
        image: RgbImage { width: w, height: h, data: rgb },
        disparity: Disparity { width: w, height: h, data: depth.iter().map(|d| near / d).collect() },
        mpi: Arc::new(mpi),
        masks,
        intrinsics: k,
        provenance: vec!["depth: synthetic".into(), format!("mpi: builtin {} {}", opts.layering, opts.planes)],
    })
}

/// A loader of the one synthetic scene.
struct Synthetic {
    width: usize,
    height: usize,
    layering: LayeringOptions,
    object: bool,
}

impl SceneLoader for Synthetic {
    fn len(&self) -> usize {
        1
    }

    fn id(&self, _i: usize) -> String {
        "synthetic".into()
    }

    fn fingerprint(&self) -> u64 {
        let mut f = Fnv64::new();
        // the same with and without the object, so that both cases draw the same motions
        let o = &self.layering;
        f.str("bench-sample").u64(self.width as u64).u64(self.height as u64).u64(o.planes as u64);
        f.str(&format!("{} {} {}", o.layering, o.placement, o.backdrop)).finish()
    }

    fn load_scene(&self, _i: usize) -> Result<Scene, SceneError> {
        synthetic_scene(self.width, self.height, &self.layering, self.object)
    }
}

#[derive(Clone, Debug)]
pub struct SampleBenchConfig {
    pub width: usize,
    pub height: usize,
    /// The built-in layering of the scene.
    pub layering: LayeringOptions,
    /// Timed samples (after one warm-up sample that loads the scene into the cache).
    pub samples: usize,
    /// Whether the scene has the moving object.
    pub object: bool,
    pub seed: u64,
    pub sample: SampleConfig,
    /// An augmentation to time on each finished sample (on the calling thread, as a server worker
    /// runs it).
    pub augment: Option<Augment>,
}

/// Wall time per sample and the stage timings of each.
#[derive(Clone, Debug)]
pub struct SampleBenchReport {
    pub wall: Timing,
    pub stages: Vec<StageTimings>,
    /// The moved objects per sample (0 or 1 here).
    pub objects: usize,
    /// Holes inpainted, median over the samples.
    pub holes_median: u64,
    /// The augmentation's time per sample (without the sample), with `augment`.
    pub augment: Option<Timing>,
}

impl SampleBenchReport {
    /// (name, median ms, mean ms, share of the mean total) per stage.
    pub fn stage_table(&self) -> Vec<(&'static str, f64, f64, f64)> {
        type Pick = (&'static str, fn(&StageTimings) -> f64);
        let pick: [Pick; 5] = [
            ("scene", |t| t.scene_ms),
            ("render", |t| t.render_ms),
            ("objects", |t| t.objects_ms),
            ("merge", |t| t.merge_ms),
            ("inpaint", |t| t.inpaint_ms),
        ];
        let n = self.stages.len().max(1) as f64;
        let total: f64 = self.stages.iter().map(|t| t.total_ms).sum::<f64>() / n;
        pick.iter()
            .map(|(name, f)| {
                let v: Vec<f64> = self.stages.iter().map(f).collect();
                let mean = v.iter().sum::<f64>() / n;
                let median = if v.is_empty() { 0.0 } else { Timing::from_samples(v).median };
                (*name, median, mean, if total > 0.0 { mean / total } else { 0.0 })
            })
            .collect()
    }
}

/// Makes `samples` samples (indices 1..=samples after a warm-up at index 0) of the synthetic
/// scene in the current rayon pool, each timed from the request to the finished sample.
pub fn bench_sample(cfg: &SampleBenchConfig) -> Result<SampleBenchReport, SampleError> {
    let loader = Synthetic { width: cfg.width, height: cfg.height, layering: cfg.layering, object: cfg.object };
    let cache = Arc::new(SceneCache::new(4 << 30));
    let g = Generator::new(Arc::new(loader), cache, cfg.sample.clone())?;
    g.sample(cfg.seed, 0)?;
    let mut wall = Vec::with_capacity(cfg.samples);
    let mut stages = Vec::with_capacity(cfg.samples);
    let mut holes = Vec::with_capacity(cfg.samples);
    let mut objects = 0;
    let mut augment = Vec::new();
    for index in 1..=cfg.samples.max(1) as u64 {
        let t = Instant::now();
        let s = g.sample(cfg.seed, index)?;
        wall.push(t.elapsed().as_secs_f64() * 1e3);
        if let Some(a) = &cfg.augment {
            let copy = s.clone();
            let t = Instant::now();
            std::hint::black_box(a.apply(copy));
            augment.push(t.elapsed().as_secs_f64() * 1e3);
        }
        objects = objects.max(s.objects.len());
        holes.push(s.inpainted_pixels);
        stages.push(s.timings);
        std::hint::black_box(&s);
    }
    holes.sort_unstable();
    Ok(SampleBenchReport {
        wall: Timing::from_samples(wall),
        stages,
        objects,
        holes_median: holes[holes.len() / 2],
        augment: (!augment.is_empty()).then(|| Timing::from_samples(augment)),
    })
}
