//! The scene stage: turns a loaded source item into a [`Scene`] (disparity in the scene scale, MPI,
//! instance masks, intrinsics), running each configured model only where the item does not
//! already carry its result; and [`SourceScenes`], a source plus a stage as a [`SceneLoader`].
//!
//! # Rules (leave out what a scene does not need)
//!
//! 1. **MPI given** ([`SourceItem::mpi`], e.g. `mpis/NAME.npz`): neither the depth model nor the
//!    MPI builder runs. The MPI is sanitised and validated; if its nearest plane has a disparity
//!    above 1 all plane disparities are scaled so that it is 1 (and densities by the same factor,
//!    which keeps every plane's opacity), otherwise it is used as is (the reference's MPIs already
//!    live in the scene scale). The scene's disparity is the MPI's own: the source-view
//!    composite `sum_i w_i disp_i` (plus the remaining transmittance times the farthest plane's
//!    disparity) with the renderer's plane gaps, at unit ray length.
//! 2. **Depth or disparity given**: brought to the scene scale by
//!    [`scale::disparity_from_given`]; the depth model does not run.
//! 3. **Otherwise** the depth model runs (its output must already be in the scene scale, see
//!    [`DepthEstimator`]); with no depth model the item is an error: "source X has no depth and no
//!    depth model is configured".
//! 4. Without a given MPI, the MPI builder lifts image + disparity into an MPI (unless the
//!    caller does not need it: [`SceneStage::parts`], for `mpiflow bake`).
//! 5. **Masks given**: used (resized to the image by nearest neighbour if needed); the segmenter
//!    does not run. No masks and no segmenter: no instances (objects simply do not move); a
//!    segmenter that finds none says so ("no object found: only the camera moves").
//! 6. **Intrinsics**: the item's, else the given MPI's `K`, else the reference default
//!    (`0.58 W, 0.58 H`, centre).
//!
//! [`Scene::provenance`] records which rule produced each part, e.g.
//! `["depth: given metric depth, nearest 2.5 -> disparity 1", "mpi: builtin soft 32",
//! "masks: given (3 instances)"]`.

use super::scale::{self, DISPARITY_FLOOR};
use super::{DepthEstimator, Disparity, MpiBuilder, Scene, SceneError, SceneLoader, Segmenter};
use crate::geometry::Intrinsics;
use crate::io::image::RgbImage;
use crate::mpi::planes::plane_gaps;
use crate::mpi::Mpi;
use crate::raster::InstanceMasks;
use crate::source::{Carried, FailureKind, Fnv64, GivenDepth, Source, SourceError, SourceItem};
use std::sync::Arc;

impl From<SourceError> for SceneError {
    fn from(e: SourceError) -> Self {
        match e {
            SourceError::File { path, kind, message } => SceneError::Given { path, kind, message },
            other @ (SourceError::Invalid(_) | SourceError::Limit(_) | SourceError::Upload { .. }) => {
                SceneError::Invalid(other.to_string())
            }
        }
    }
}

/// The configured models of the scene stage.
#[derive(Clone)]
pub struct SceneStage {
    /// Depth model, used for items without depth, disparity or MPI.
    pub depth: Option<Arc<dyn DepthEstimator>>,
    /// MPI builder, used for items without an MPI.
    pub mpi: Arc<dyn MpiBuilder>,
    /// Instance segmenter, used for items without masks.
    pub segmenter: Option<Arc<dyn Segmenter>>,
}

impl std::fmt::Debug for SceneStage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.describe())
    }
}

impl SceneStage {
    /// A stage with only an MPI builder (items must carry depth or an MPI).
    pub fn new(mpi: Arc<dyn MpiBuilder>) -> Self {
        SceneStage { depth: None, mpi, segmenter: None }
    }

    /// The plain built-in layering (32 soft planes uniform in disparity, no completed background),
    /// no depth model, no segmenter: a light stage for tests and tools. The commands build theirs
    /// from the default model configuration instead.
    pub fn builtin() -> Self {
        Self::new(Arc::new(super::builtin::BuiltinMpi::default()))
    }

    pub fn with_depth(mut self, depth: Arc<dyn DepthEstimator>) -> Self {
        self.depth = Some(depth);
        self
    }

    pub fn with_segmenter(mut self, segmenter: Arc<dyn Segmenter>) -> Self {
        self.segmenter = Some(segmenter);
        self
    }

    /// `depth: NAME, mpi: NAME, masks: NAME` (`none` where no model is configured).
    pub fn describe(&self) -> String {
        format!(
            "depth: {}, mpi: {}, masks: {}",
            self.depth.as_ref().map_or("none".into(), |d| d.name()),
            self.mpi.name(),
            self.segmenter.as_ref().map_or("none".into(), |s| s.name())
        )
    }

    /// Whether the scenes of a collection whose every item carries `carried` need a model to
    /// run: a depth model for items without depth or MPI, an MPI network for items without an
    /// MPI, a segmenter for items without masks (a built-in rule is not a model). A baked
    /// folder carries what the models made, so its scenes need none.
    pub fn needs_models(&self, carried: Carried) -> bool {
        let model = |runs: Option<u64>| runs.is_some();
        let depth = self.depth.as_ref().is_some_and(|d| model(d.inference_runs())) && !(carried.depth || carried.mpi);
        let mpi = model(self.mpi.inference_runs()) && !carried.mpi;
        let segment = self.segmenter.as_ref().is_some_and(|s| model(s.inference_runs())) && !carried.masks;
        depth || mpi || segment
    }

    /// Inferences each configured model ran so far, as (role, runs): `depth`, `mpi`, `segment`
    /// (built-in rules, which run no model, are left out).
    pub fn model_runs(&self) -> Vec<(&'static str, u64)> {
        let mut out = Vec::with_capacity(3);
        if let Some(n) = self.depth.as_ref().and_then(|d| d.inference_runs()) {
            out.push(("depth", n));
        }
        if let Some(n) = self.mpi.inference_runs() {
            out.push(("mpi", n));
        }
        if let Some(n) = self.segmenter.as_ref().and_then(|s| s.inference_runs()) {
            out.push(("segment", n));
        }
        out
    }

    /// A fingerprint of everything in the configuration that changes scenes: each part's
    /// [`identity`](DepthEstimator::identity) (for an ONNX model the content hash of its file
    /// and its contract, never its file name; for the built-in layering its planes and layering).
    pub fn config_fingerprint(&self) -> u64 {
        let mut h = Fnv64::new();
        h.str("mpiflow scene stage v1");
        h.str(&self.depth.as_ref().map_or("none".into(), |d| d.identity()));
        h.str(&self.mpi.identity());
        h.str(&self.segmenter.as_ref().map_or("none".into(), |s| s.identity()));
        h.finish()
    }

    /// Whether `item` can make a scene with this stage, checked without running any model or
    /// building the MPI: it has depth (or an MPI), or a depth model is configured, and its given
    /// depth can be brought to the scene scale (some finite positive value). Uploads run it at
    /// the door so that an item that would fail every sample is rejected, not accepted.
    pub fn check_item(&self, item: &SourceItem) -> Result<(), SceneError> {
        let (w, h) = (item.image.width, item.image.height);
        if item.mpi.is_some() {
            return Ok(());
        }
        match &item.depth {
            Some(GivenDepth::Depth(d)) => {
                scale::disparity_from_depth(d, w, h).map(|_| ()).map_err(|e| in_source(&item.id, e))
            }
            Some(GivenDepth::Disparity(d)) => {
                scale::disparity_from_unit(d, w, h).map(|_| ()).map_err(|e| in_source(&item.id, e))
            }
            None if self.depth.is_some() => Ok(()),
            None => Err(SceneError::Data {
                kind: FailureKind::Depth,
                message: format!("source {} has no depth and no depth model is configured", item.id),
            }),
        }
    }

    /// Builds the scene of one item (see the module documentation for which parts are computed).
    pub fn scene(&self, item: SourceItem) -> Result<Scene, SceneError> {
        let p = self.parts(item, true)?;
        let Some(mpi) = p.mpi else {
            return Err(SceneError::Invalid(format!("source {}: no MPI was built", p.id)));
        };
        let SceneParts { id, image, disparity, masks, intrinsics, provenance, .. } = p;
        Ok(Scene { id, image, disparity, mpi, masks, intrinsics, provenance })
    }

    /// The parts of one item's scene as [`Self::scene`] makes them, with the MPI only when the
    /// item carries one or `build_mpi` holds: `mpiflow bake` without an MPI network stores the
    /// disparity and masks, and the server's layering rebuilds the MPI from them, so the bake
    /// does not build it (it was most of a baked item's time).
    pub fn parts(&self, item: SourceItem, build_mpi: bool) -> Result<SceneParts, SceneError> {
        let SourceItem { id, image, depth, masks, mpi, intrinsics } = item;
        let (w, h) = (image.width, image.height);
        if w == 0 || h == 0 || Some(image.data.len()) != w.checked_mul(h).and_then(|n| n.checked_mul(3)) {
            return Err(SceneError::Invalid(format!(
                "source {id}: image of {w} x {h} holds {} values",
                image.data.len()
            )));
        }
        let mut provenance = Vec::with_capacity(3);

        let (mut masks, masks_note) = self.masks(&id, masks, &image)?;

        let (disparity, mpi, intrinsics) = if let Some(given) = mpi {
            let (mpi, note) = prepare_given_mpi(&id, given, w, h)?;
            let k = intrinsics.or(mpi.intrinsics).unwrap_or_else(|| Intrinsics::reference_default(w, h));
            let disparity = composite_disparity(&mpi);
            provenance.push("depth: composited from the given MPI".to_string());
            provenance.push(format!("mpi: given ({} planes{note})", mpi.planes()));
            (disparity, Some(Arc::new(mpi)), k)
        } else {
            let disparity = self.disparity(&id, depth, &image, &mut provenance)?;
            let k = intrinsics.unwrap_or_else(|| Intrinsics::reference_default(w, h));
            let mpi = if build_mpi {
                // a scene's masks follow its depth edges; parts without the MPI (what a bake
                // writes) keep the masks as given, and are aligned when their scene is built
                if self.mpi.aligns_masks() {
                    super::matte::align_to_depth(&mut masks, &disparity.data);
                }
                let mpi = self.mpi.build_with_masks(&image, &disparity, &masks, &k)?;
                if (mpi.width, mpi.height) != (w, h) {
                    return Err(SceneError::Invalid(format!(
                        "MPI builder {} made a {} x {} MPI for the {w} x {h} image of source {id}",
                        self.mpi.name(),
                        mpi.width,
                        mpi.height
                    )));
                }
                provenance.push(format!("mpi: {}", self.mpi.name()));
                Some(Arc::new(mpi))
            } else {
                None
            };
            (disparity, mpi, k)
        };

        provenance.push(masks_note);
        Ok(SceneParts { id, image, disparity, mpi, masks, intrinsics, provenance })
    }

    /// The item's instance masks (given, resized to the image, or the segmenter's; none without
    /// either) and the provenance line that says which.
    fn masks(
        &self,
        id: &str,
        masks: Option<InstanceMasks>,
        image: &RgbImage,
    ) -> Result<(InstanceMasks, String), SceneError> {
        let (w, h) = (image.width, image.height);
        let masks_note;
        let masks = match masks {
            Some(m) => {
                let m = if (m.width, m.height) != (w, h) { m.resize_nearest(w, h) } else { m };
                masks_note = format!("masks: given ({} instances)", m.masks.len());
                m
            }
            None => match &self.segmenter {
                Some(seg) => {
                    let m = seg.segment(image)?;
                    if (m.width, m.height) != (w, h) || m.masks.iter().any(|i| i.mask.len() != w * h) {
                        return Err(SceneError::Model {
                            kind: "segmentation",
                            model: seg.name(),
                            message: format!(
                                "source {id}: masks of {} x {} for an image of {w} x {h}",
                                m.width, m.height
                            ),
                        });
                    }
                    masks_note = match m.masks.len() {
                        0 => format!("masks: {} (no object found: only the camera moves)", seg.name()),
                        n => format!("masks: {} ({n} instances)", seg.name()),
                    };
                    m
                }
                None => {
                    masks_note = "masks: none (no masks given and no segmenter configured)".to_string();
                    InstanceMasks::new(w, h)
                }
            },
        };
        Ok((masks, masks_note))
    }

    /// The item's disparity when it carries no MPI: from its given depth or disparity, or the
    /// depth model's (checked and clamped to the scene scale); its provenance line pushed.
    fn disparity(
        &self,
        id: &str,
        depth: Option<GivenDepth>,
        image: &RgbImage,
        provenance: &mut Vec<String>,
    ) -> Result<Disparity, SceneError> {
        let (w, h) = (image.width, image.height);
        let disparity = match depth {
            Some(GivenDepth::Depth(d)) => {
                let (disp, d_min) = scale::disparity_from_depth(&d, w, h).map_err(|e| in_source(id, e))?;
                provenance.push(format!("depth: given metric depth, nearest {d_min} -> disparity 1"));
                disp
            }
            Some(GivenDepth::Disparity(d)) => {
                let disp = scale::disparity_from_unit(&d, w, h).map_err(|e| in_source(id, e))?;
                provenance.push("depth: given disparity".to_string());
                disp
            }
            None => match &self.depth {
                Some(est) => {
                    let mut disp = est.estimate(image)?;
                    let bad = |message: String| SceneError::Model { kind: "depth", model: est.name(), message };
                    if (disp.width, disp.height) != (w, h) {
                        return Err(bad(format!(
                            "source {id}: disparity of {} x {} for an image of {w} x {h}",
                            disp.width, disp.height
                        )));
                    }
                    scale::check_scene_scale(&disp).map_err(|m| bad(format!("source {id}: {m}")))?;
                    scale::clamp_to_scale(&mut disp.data);
                    provenance.push(format!("depth: {}", est.name()));
                    disp
                }
                None => {
                    return Err(SceneError::Data {
                        kind: FailureKind::Depth,
                        message: format!("source {id} has no depth and no depth model is configured"),
                    })
                }
            },
        };
        Ok(disparity)
    }
}

/// A scene's parts ([`SceneStage::parts`]): a [`Scene`] whose MPI may not be built.
pub struct SceneParts {
    pub id: String,
    pub image: RgbImage,
    pub disparity: Disparity,
    /// The item's own MPI or the builder's; `None` when it was not asked for.
    pub mpi: Option<Arc<Mpi>>,
    pub masks: InstanceMasks,
    pub intrinsics: Intrinsics,
    pub provenance: Vec<String>,
}

fn in_source(id: &str, e: SceneError) -> SceneError {
    match e {
        SceneError::Invalid(m) => SceneError::Invalid(format!("source {id}: {m}")),
        SceneError::Data { kind, message } => SceneError::Data { kind, message: format!("source {id}: {message}") },
        other => other,
    }
}

/// Sanitises, validates and (if needed) rescales a given MPI; returns it and a provenance note.
fn prepare_given_mpi(id: &str, mut mpi: Mpi, w: usize, h: usize) -> Result<(Mpi, String), SceneError> {
    if (mpi.width, mpi.height) != (w, h) {
        return Err(SceneError::Data {
            kind: FailureKind::Mpi,
            message: format!("source {id}: the given MPI is {} x {} but the image is {w} x {h}", mpi.width, mpi.height),
        });
    }
    let report = mpi.sanitize();
    mpi.validate()?;
    let mut note = String::new();
    if report.total() > 0 {
        note.push_str(&format!(", {} values repaired", report.total()));
    }
    let near = mpi.disparity[0];
    if near > 1.0 {
        let s = 1.0 / near;
        for d in mpi.disparity.iter_mut() {
            *d *= s;
        }
        mpi.disparity[0] = 1.0;
        // depths grow by 1/s, so densities shrink by s: sigma * delta (each plane's opacity) is kept
        let sf = s as f32;
        for px in mpi.rgba.chunks_exact_mut(4) {
            px[3] *= sf;
        }
        note.push_str(&format!(", disparities scaled by {s} to put the nearest plane at 1"));
    }
    Ok((mpi, note))
}

/// The MPI's own disparity as seen from the source camera: per pixel, front-to-back compositing
/// with `alpha_i = 1 - exp(-sigma_i delta_i)`, `delta_i` the gap to the next plane's depth (capped
/// at `DELTA_LAST`, the last plane `DELTA_LAST`, depths capped at `DEPTH_MAX`, the shared rule of
/// [`crate::mpi::planes`], as the renderer does at unit ray length), the light left after the last plane given the farthest plane's
/// disparity; clamped to the scene scale.
pub fn composite_disparity(mpi: &Mpi) -> Disparity {
    let n = mpi.planes();
    let hw = mpi.plane_len();
    let delta: Vec<f64> = plane_gaps(&mpi.disparity);
    let mut acc = vec![0f64; hw];
    let mut trans = vec![1f64; hw];
    for (i, (&delta_i, &disp)) in delta.iter().zip(&mpi.disparity).enumerate() {
        let plane = mpi.plane_rgba(i);
        for ((px, a), t) in plane.chunks_exact(4).zip(acc.iter_mut()).zip(trans.iter_mut()) {
            let sigma = f64::from(px[3]);
            if sigma <= 0.0 || *t == 0.0 {
                continue;
            }
            let alpha = 1.0 - (-sigma * delta_i).exp();
            *a += *t * alpha * disp;
            *t *= 1.0 - alpha;
        }
    }
    let last = mpi.disparity[n - 1];
    let mut data: Vec<f32> = acc.iter().zip(&trans).map(|(&a, &t)| (a + t * last) as f32).collect();
    scale::clamp_to_scale(&mut data);
    debug_assert!(data.iter().all(|&v| v >= DISPARITY_FLOOR));
    Disparity { width: mpi.width, height: mpi.height, data }
}

/// A source plus a scene stage: the [`SceneLoader`] the sample generator uses.
#[derive(Clone)]
pub struct SourceScenes {
    pub source: Arc<dyn Source>,
    pub stage: Arc<SceneStage>,
}

impl SourceScenes {
    pub fn new(source: Arc<dyn Source>, stage: Arc<SceneStage>) -> Self {
        SourceScenes { source, stage }
    }

    /// `SOURCE; STAGE`, and `; baked: PROVENANCE` for a baked collection.
    pub fn describe(&self) -> String {
        match self.source.baked_with() {
            Some(b) => format!("{}; {}; baked: {b}", self.source.describe(), self.stage.describe()),
            None => format!("{}; {}", self.source.describe(), self.stage.describe()),
        }
    }

    /// Whether this collection's scenes need a model to run ([`SceneStage::needs_models`]).
    pub fn needs_models(&self) -> bool {
        self.stage.needs_models(self.source.carried())
    }

    /// Whether this collection can make scenes at all, as far as its listing tells: with no depth
    /// model, a collection whose every item lacks depth and an MPI cannot
    /// ([`SceneError::NoDepthModel`]). Items that fail later are skipped one by one instead.
    pub fn check_can_make_scenes(&self) -> Result<(), SceneError> {
        let n = self.source.len();
        if self.stage.depth.is_none() && n > 0 && self.source.items_without_depth() == Some(n) {
            return Err(SceneError::NoDepthModel);
        }
        Ok(())
    }
}

impl SceneLoader for SourceScenes {
    fn len(&self) -> usize {
        self.source.len()
    }

    fn id(&self, i: usize) -> String {
        self.source.id(i)
    }

    /// FNV-1a of the source's fingerprint and the stage's configuration fingerprint.
    fn fingerprint(&self) -> u64 {
        Fnv64::new()
            .str("mpiflow source scenes v1")
            .u64(self.source.fingerprint())
            .u64(self.stage.config_fingerprint())
            .finish()
    }

    fn load_scene(&self, i: usize) -> Result<Scene, SceneError> {
        let item = self.source.load(i)?;
        self.stage.scene(item)
    }
}
