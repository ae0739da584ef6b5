//! The one pipeline: sources, scene models and a sample configuration make a dataset with one
//! fingerprint, and samples by address. `mpiflow serve` (every dataset, every request override),
//! `mpiflow generate`, the benches and the tests all build it here, so the same source, models,
//! options, seed and index give the same bytes on every path:
//!
//! - [`open_source`]: a [`SourceSpec`] (the bundled scenes or a path) with [`OpenOptions`]
//!   (resize, intrinsics, limits) to a [`Source`];
//! - [`crate::scene::models::ModelConfig::build_stage`]: the models to a scene stage;
//! - [`Pipeline::new`]: source + stage + cache + [`SampleConfig`] to the default [`Generator`];
//!   [`Generator::with_config`] for other configurations over the same scenes;
//! - [`dataset_fingerprint`]: the dataset word of every address, FNV-1a of the loader's
//!   fingerprint (source content and options, each model's content hash and contract) and the
//!   configuration's JSON (every option that changes a sample).
//!
//! The [`Generator`] makes the sample at an address: it loads the address's scene through the
//! shared [`SceneCache`] (once per scene, see [`crate::scene::cache`]), keeps each cached
//! scene's tile occupancy, passes over bad source items deterministically and runs
//! [`super::recipe::assemble_with_target_depth`] (the sample and its target depth).

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::time::Instant;

use super::config::SampleConfig;
use super::crop::CropSpec;
use super::error::SampleError;
use super::recipe::{assemble_cropped, check_scene, ms, prepare_scene, Cropped};
use super::types::{Sample, SampleAddress};
use crate::io::image::ImageLimits;
use crate::render::{Mode, Occupancy};
use crate::scene::cache::{SceneCache, SceneKey};
use crate::scene::stage::{SceneStage, SourceScenes};
use crate::scene::{Scene, SceneLoader};
use crate::source::builtin::{BuiltinOptions, BuiltinSource};
use crate::source::dir::{IntrinsicsSpec, SourceOptions};
use crate::source::{FailureKind, Fnv64, Source, SourceError};

/// The fingerprint of a dataset under a sample configuration: FNV-1a of the loader's fingerprint
/// (sources + scene stage) and the configuration's JSON. Never change the formula without a
/// reason: it is the dataset word of every address, so changing it changes every sample.
/// The version word (`v7`) names the sample bytes' rules: v2 marks the depth-aware merge that
/// fills one-pixel dips of the scene mask and depth before its occlusion test (`sample::merge`),
/// v3 the higher-order colour kernels that sum each column of taps first, then the columns
/// (`render::resample`, four values per vector operation), v4 the merge's seams (a pixel the
/// scene and an object cover together shows the larger share instead of a hole), v5 the presets'
/// object motion as drawn (no reveal budget unless a law asks for one), v6 a request's crop made
/// over its window (its holes filled from the window alone; the occlusion cleared, like `valid`,
/// where the flow leaves the crop), v7 a moved object taken out of the scene over its footprint
/// (its masks grown past their soft edges and fringes, `sample::object::object_footprint`, with
/// the depth-aware merge) and the holes' Telea fill reading the frame's background only (never
/// an object's pixels, `sample::holes::inpaint_background`). An opt-in rule
/// whose bytes changed after it shipped adds its own revision word (`rule_revisions`), so only
/// the configurations that use it get new fingerprints. CHANGELOG.md lists the changes.
pub fn dataset_fingerprint(loader_fingerprint: u64, config: &SampleConfig) -> u64 {
    // serialising a plain struct of numbers and strings cannot fail
    let json = serde_json::to_string(config).unwrap_or_default();
    let mut f = Fnv64::new();
    f.str("mpiflow dataset v7");
    for word in rule_revisions(config) {
        f.str(word);
    }
    f.u64(loader_fingerprint).str(&json).finish()
}

/// The revision words of the opt-in rules a configuration uses: the `exemplar` fill's third
/// revision (its second continues a moved object that reaches image1's border into what enters
/// the frame beside it and labels it in the frame's mask; its third keeps every source
/// `TEXTURE_MASK_GROW` pixels from every object, however thin).
fn rule_revisions(config: &SampleConfig) -> Vec<&'static str> {
    let mut words = Vec::new();
    if config.inpaint_method == super::config::InpaintMethod::Exemplar {
        words.push("exemplar r3");
    }
    words
}

/// `WxH`, both sides 16 to 16384 pixels (the `--size` of every command and the `size` key).
pub fn parse_size(s: &str) -> Result<(usize, usize), String> {
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(|| format!("expected WxH (e.g. 640x480), got `{s}`"))?;
    let side = |v: &str| -> Result<usize, String> {
        let n: usize = v.trim().parse().map_err(|_| format!("`{v}` is not a whole number of pixels"))?;
        if !(16..=16384).contains(&n) {
            return Err(format!("{n} pixels is outside 16 to 16384"));
        }
        Ok(n)
    };
    Ok((side(w)?, side(h)?))
}

/// Where a dataset's items come from.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum SourceSpec {
    /// The bundled procedural scenes (`examples/photos`).
    Builtin,
    /// A folder of photos or the reference layout, one image, a WebDataset `.tar` shard or a
    /// folder of shards.
    Path(PathBuf),
}

/// How a source is opened: what changes its items (and so its fingerprint) and the limits.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct OpenOptions {
    /// Resize every image to `(W, H)`; none = keep sizes (the bundled scenes are 640x480).
    pub resize: Option<(usize, usize)>,
    /// Camera intrinsics of every image (not for the bundled scenes, which have their own).
    pub intrinsics: Option<IntrinsicsSpec>,
    /// Limits on each image, checked before decoding.
    pub limits: ImageLimits,
    /// Follow symbolic links out of a folder source's root (see [`SourceOptions::follow_links`]).
    pub follow_links: bool,
    /// Limits of a folder's photos, fitted to the working size before use
    /// ([`SourceOptions::photo_limits`]); `None` = `limits`.
    pub photo_limits: Option<ImageLimits>,
}

/// Opens the source of `spec` with `options`.
pub fn open_source(spec: &SourceSpec, options: &OpenOptions) -> Result<Arc<dyn Source>, SourceError> {
    match spec {
        SourceSpec::Builtin => {
            if options.intrinsics.is_some() {
                return Err(SourceError::Invalid(
                    "intrinsics cannot be set for the bundled scenes (they are composed for their own camera)".into(),
                ));
            }
            let mut o = BuiltinOptions { limits: options.limits, ..BuiltinOptions::default() };
            if let Some((w, h)) = options.resize {
                o.width = w;
                o.height = h;
            }
            Ok(Arc::new(BuiltinSource::open(&o)?))
        }
        SourceSpec::Path(path) => {
            let o = SourceOptions {
                resize: options.resize,
                intrinsics: options.intrinsics,
                limits: options.limits,
                follow_links: options.follow_links,
                photo_limits: options.photo_limits,
                ..SourceOptions::default()
            };
            crate::source::open_source(path, &o)
        }
    }
}

/// A dataset: its source, the scenes it loads through the stage, and the generator of its
/// default sample configuration.
pub struct Pipeline {
    source: Arc<dyn Source>,
    loader: Arc<SourceScenes>,
    generator: Arc<Generator>,
}

impl std::fmt::Debug for Pipeline {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Pipeline").field("fingerprint", &self.fingerprint()).field("items", &self.source.len()).finish()
    }
}

impl Pipeline {
    /// The pipeline of `source` through `stage`, caching scenes in `cache` (which may be shared
    /// with other pipelines), making samples by `config` (checked here). A collection that cannot
    /// make scenes with this stage ([`SourceScenes::check_can_make_scenes`]) is refused here.
    pub fn new(
        source: Arc<dyn Source>,
        stage: Arc<SceneStage>,
        cache: Arc<SceneCache>,
        config: SampleConfig,
    ) -> Result<Self, SampleError> {
        let loader = Arc::new(SourceScenes::new(source.clone(), stage));
        loader.check_can_make_scenes().map_err(SampleError::Unusable)?;
        let generator = Arc::new(Generator::new(loader.clone() as Arc<dyn SceneLoader>, cache, config)?);
        Ok(Self { source, loader, generator })
    }

    pub fn source(&self) -> &Arc<dyn Source> {
        &self.source
    }

    pub fn loader(&self) -> &Arc<SourceScenes> {
        &self.loader
    }

    /// The generator of the default configuration.
    pub fn generator(&self) -> &Arc<Generator> {
        &self.generator
    }

    /// The fingerprint of the default configuration.
    pub fn fingerprint(&self) -> u64 {
        self.generator.fingerprint()
    }

    /// `SOURCE; depth: ..., mpi: ..., masks: ...`.
    pub fn describe(&self) -> String {
        self.loader.describe()
    }
}

/// Most scene occupancies the generator keeps (those of scenes no longer alive are dropped
/// first).
const MAX_OCCUPANCIES: usize = 256;

/// A cached tile occupancy: the scene's key, the scene it was built from, the occupancy.
type OccupancyEntry = (SceneKey, Weak<Scene>, Arc<Occupancy>);

/// Makes samples by address from a scene loader, through a shared scene cache.
pub struct Generator {
    loader: Arc<dyn SceneLoader>,
    cache: Arc<SceneCache>,
    config: SampleConfig,
    /// The dataset word of the addresses ([`dataset_fingerprint`]).
    fingerprint: u64,
    /// The loader's fingerprint: the dataset word of the scene cache keys.
    loader_fingerprint: u64,
    /// Scenes built (shared with the generators made by [`Generator::with_config`]).
    builds: Arc<AtomicU64>,
    /// Tile occupancy of each cached scene's MPI (small: N x (W/8) x (H/8) counts), keyed by the
    /// scene's cache key and checked against the scene itself.
    occupancies: Mutex<Vec<OccupancyEntry>>,
    /// Source items known to fail, by item: (id, failure kind, reason).
    bad: Mutex<BTreeMap<usize, BadItem>>,
}

/// A source item that failed to load: its id, failure kind and reason.
#[derive(Clone, Debug)]
struct BadItem {
    id: String,
    kind: FailureKind,
    reason: String,
}

impl std::fmt::Debug for Generator {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Generator")
            .field("fingerprint", &self.fingerprint)
            .field("items", &self.loader.len())
            .field("config", &self.config)
            .finish()
    }
}

impl Generator {
    /// A generator over `loader`'s items; the configuration is checked here. Its fingerprint
    /// (the dataset word of every address) is [`dataset_fingerprint`] of the loader's fingerprint
    /// and the configuration: the one fingerprint of every path that makes samples.
    pub fn new(
        loader: Arc<dyn SceneLoader>,
        cache: Arc<SceneCache>,
        config: SampleConfig,
    ) -> Result<Self, SampleError> {
        Self::with_counter(loader, cache, config, Arc::new(AtomicU64::new(0)))
    }

    fn with_counter(
        loader: Arc<dyn SceneLoader>,
        cache: Arc<SceneCache>,
        config: SampleConfig,
        builds: Arc<AtomicU64>,
    ) -> Result<Self, SampleError> {
        config.validate()?;
        let loader_fingerprint = loader.fingerprint();
        let fingerprint = dataset_fingerprint(loader_fingerprint, &config);
        Ok(Self {
            loader,
            cache,
            config,
            fingerprint,
            loader_fingerprint,
            builds,
            occupancies: Mutex::new(Vec::new()),
            bad: Mutex::new(BTreeMap::new()),
        })
    }

    /// A generator of the same items under another configuration: it shares the loader, the
    /// scene cache (scenes are keyed by the loader's fingerprint, so both reuse each other's
    /// scenes) and the scene build counter; its fingerprint covers the new configuration.
    pub fn with_config(&self, config: SampleConfig) -> Result<Self, SampleError> {
        Self::with_counter(self.loader.clone(), self.cache.clone(), config, self.builds.clone())
    }

    /// Scenes this generator (and those made from it by [`with_config`](Self::with_config))
    /// actually built, failed builds included; cache hits and waits for another caller's build
    /// are not counted.
    pub fn scene_builds(&self) -> u64 {
        self.builds.load(Ordering::Relaxed)
    }

    pub fn config(&self) -> &SampleConfig {
        &self.config
    }

    /// The dataset word of every address this generator makes ([`dataset_fingerprint`]).
    pub fn fingerprint(&self) -> u64 {
        self.fingerprint
    }

    pub fn cache(&self) -> &Arc<SceneCache> {
        &self.cache
    }

    /// The source item of sample `index` (None for an empty collection).
    pub fn source_item(&self, index: u64) -> Option<usize> {
        self.config.source_item(index, self.loader.len())
    }

    fn key(&self, item: usize) -> SceneKey {
        SceneKey::new(self.loader_fingerprint, item as u64, self.config.scene_variant())
    }

    /// The prepared scene of source item `item`, from the cache or loaded into it.
    pub fn scene(&self, item: usize) -> Result<Arc<Scene>, SampleError> {
        self.cache.get_or_load(self.key(item), || self.build(item))
    }

    /// Builds the prepared scene of `item` (counted in [`scene_builds`](Self::scene_builds)).
    fn build(&self, item: usize) -> Result<Scene, SampleError> {
        self.builds.fetch_add(1, Ordering::Relaxed);
        let scene = self.loader.load_scene(item).map_err(|e| SampleError::Scene {
            item,
            id: self.loader.id(item),
            source: Box::new(e),
        })?;
        prepare_scene(scene, &self.config)
    }

    /// Prepares the scene of sample `index` off the caller's thread: `true` when there is
    /// nothing to wait for (the scene is cached, its item is known bad, or no scene pool can
    /// run, or the builds in progress already fill half the cache budget: then the sample builds
    /// its scene itself); otherwise starts the build on the scene pool
    /// ([`crate::scene::cache::load_pool`], one build per scene however many samples ask),
    /// returns `false` and calls `done` from that pool once the build finished or failed.
    pub fn prepare(self: &Arc<Self>, index: u64, done: Box<dyn FnOnce() + Send>) -> bool {
        let Some(item) = self.source_item(index) else { return true };
        if self.cache.contains(&self.key(item)) || self.bad_items().contains_key(&item) {
            return true;
        }
        let Some(pool) = crate::scene::cache::load_pool() else { return true };
        // builds ahead are bounded by the cache: scenes built ahead must still be there when
        // their samples run
        let stats = self.cache.stats();
        let per_scene = stats.bytes.checked_div(stats.entries).unwrap_or(0);
        if per_scene > 0 && (self.cache.loading() + 1) * per_scene > stats.max_bytes / 2 {
            return true;
        }
        let me = self.clone();
        pool.spawn_fifo(move || {
            // never waits for another load (that one may be queued behind this thread); an
            // error is the sample's to report (it passes the bad item over)
            let _ = me.cache.load_absent(me.key(item), || me.build(item));
            done();
        });
        false
    }

    fn occupancy(&self, key: SceneKey, scene: &Arc<Scene>) -> Option<Arc<Occupancy>> {
        if self.config.mode != Mode::Exact || !self.config.skip.tiles {
            return None;
        }
        let found = {
            let list = self.occupancies.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
            list.iter()
                .find(|(k, s, _)| *k == key && s.upgrade().is_some_and(|s| Arc::ptr_eq(&s, scene)))
                .map(|(_, _, o)| o.clone())
        };
        if found.is_some() {
            return found;
        }
        let occ = Arc::new(Occupancy::build(&scene.mpi, self.config.skip.tile_sigma_eps));
        let mut list = self.occupancies.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        list.retain(|(k, s, _)| s.strong_count() > 0 && *k != key);
        if list.len() >= MAX_OCCUPANCIES {
            list.remove(0);
        }
        list.push((key, Arc::downgrade(scene), occ.clone()));
        Some(occ)
    }

    fn bad_items(&self) -> std::sync::MutexGuard<'_, BTreeMap<usize, BadItem>> {
        self.bad.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Records a bad item (once).
    fn mark_bad(&self, item: usize, kind: FailureKind, error: &SampleError) {
        let mut bad = self.bad_items();
        bad.entry(item).or_insert_with(|| BadItem { id: self.loader.id(item), kind, reason: error.to_string() });
    }

    /// The scene of a source item that loads and fits the recipe, or the error.
    fn good_scene(&self, item: usize) -> Result<Arc<Scene>, SampleError> {
        let scene = self.scene(item)?;
        check_scene(&scene)?;
        Ok(scene)
    }

    /// The sample at (fingerprint, `seed`, `index`).
    ///
    /// **Bad sources are skipped deterministically.** If the address's source item `k` fails to
    /// load (a corrupt, truncated or too large image, bad depth or masks: an error of the item's
    /// data, not of the runtime, a model or the configuration), items `k + 1, k + 2, ...` (mod the
    /// number of items) are tried in turn and the first that loads makes the sample, with the
    /// address's own motions (the random streams stay keyed by (fingerprint, seed, index)), so a
    /// sample never depends on what was asked before. Failed items are remembered (not loaded
    /// again; failures are never cached as scenes) and recorded once each
    /// ([`skipped`](Self::skipped), [`skip_counts`](Self::skip_counts));
    /// [`Sample::skipped_sources`] counts the items passed over for this sample. When every
    /// item fails the error is [`SampleError::NoGoodSource`].
    pub fn sample(&self, seed: u64, index: u64) -> Result<Sample, SampleError> {
        self.sample_with_target_depth(seed, index).map(|(s, _)| s)
    }

    /// [`sample`](Self::sample) with the expected target depth of every image1 pixel (see
    /// [`assemble_with_target_depth`](super::recipe::assemble_with_target_depth)), for checking the labels.
    pub fn sample_with_target_depth(&self, seed: u64, index: u64) -> Result<(Sample, Vec<f32>), SampleError> {
        self.sample_within(seed, index, None).map(|(s, z, _)| (s, z))
    }

    /// [`sample_with_target_depth`](Self::sample_with_target_depth) cut to a request's crop and
    /// made over its window only ([`assemble_cropped`]), with the window's corner in the frame.
    pub fn sample_cropped(
        &self,
        seed: u64,
        index: u64,
        crop: &CropSpec,
    ) -> Result<(Sample, (usize, usize)), SampleError> {
        self.sample_within(seed, index, Some(crop)).map(|(s, _, corner)| (s, corner))
    }

    fn sample_within(&self, seed: u64, index: u64, crop: Option<&CropSpec>) -> Result<Cropped, SampleError> {
        let start = Instant::now();
        let first = self.source_item(index).ok_or(SampleError::EmptySource)?;
        let len = self.loader.len();
        let mut passed = 0u32;
        for step in 0..len {
            let item = (first + step) % len;
            if self.bad_items().contains_key(&item) {
                passed += 1;
                continue;
            }
            let scene = match self.good_scene(item) {
                Ok(scene) => scene,
                Err(e) => match e.bad_source_kind() {
                    Some(kind) => {
                        self.mark_bad(item, kind, &e);
                        passed += 1;
                        continue;
                    }
                    None => return Err(e),
                },
            };
            let occ = self.occupancy(self.key(item), &scene);
            let scene_ms = ms(start);
            let address = SampleAddress { dataset: self.fingerprint, seed, index };
            let (mut s, z, corner) = assemble_cropped(&scene, address, &self.config, occ.as_deref(), crop)?;
            s.skipped_sources = passed;
            if passed > 0 {
                // the record says whose slot this sample fills, and why
                let why = self.bad_items().get(&first).map_or_else(String::new, |b| format!(": {}", b.reason));
                s.provenance.push(format!(
                    "source: {} stands in for item {first} ({}), passed over{why}",
                    s.source_id,
                    self.loader.id(first)
                ));
            }
            s.timings.scene_ms = scene_ms;
            s.timings.total_ms += scene_ms;
            return Ok((s, z, corner));
        }
        let bad = self.bad_items();
        let first_reason = bad.values().next().map(|b| b.reason.clone()).unwrap_or_default();
        Err(SampleError::NoGoodSource { items: len, first: first_reason })
    }

    /// The source items found bad so far, in item order: (item, id, reason).
    pub fn skipped(&self) -> Vec<(usize, String, String)> {
        self.bad_items().iter().map(|(&i, b)| (i, b.id.clone(), b.reason.clone())).collect()
    }

    /// How many source items were found bad so far, by failure kind (`decode`, `truncated`,
    /// `too-large`, `depth`, `mask`, `mpi`, `scene`: [`FailureKind::as_str`]), as set where each
    /// failure happened ([`SampleError::bad_source_kind`]).
    pub fn skip_counts(&self) -> BTreeMap<FailureKind, u64> {
        let mut out = BTreeMap::new();
        for b in self.bad_items().values() {
            *out.entry(b.kind).or_insert(0) += 1;
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sample::config::InpaintMethod;

    /// The fingerprint without any revision word.
    fn unrevised(loader: u64, config: &SampleConfig) -> u64 {
        let json = serde_json::to_string(config).unwrap();
        Fnv64::new().str("mpiflow dataset v7").u64(loader).str(&json).finish()
    }

    #[test]
    fn only_the_configurations_using_a_revised_rule_take_its_word() {
        let plain = SampleConfig::default();
        assert_eq!(dataset_fingerprint(7, &plain), unrevised(7, &plain));
        let texture = SampleConfig { inpaint_method: InpaintMethod::Exemplar, ..plain };
        assert_ne!(dataset_fingerprint(7, &texture), unrevised(7, &texture));
    }
}
