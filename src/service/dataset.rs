//! The dataset registry: each name maps to sources, the shared scene stage and scene cache, and a
//! default sample configuration; per-request overrides make generators that share the loader and
//! the cache. A dataset's fingerprint covers its sources, the scene stage and the effective
//! sample configuration, and is the dataset word of every sample address.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, RwLock};

use crate::sample::config::{MotionSpec, SampleConfig};
use crate::sample::error::SampleError;
use crate::sample::motion::{MotionPreset, MotionRanges};
use crate::sample::pipeline::Generator;
use crate::sample::pipeline::{open_source, OpenOptions, Pipeline};
use crate::scene::cache::SceneCache;
use crate::scene::stage::{SceneStage, SourceScenes};
use crate::source::dir::SourceOptions;
use crate::source::upload::{UploadLimits, UploadStore, UploadSummary};
use crate::source::{FailureKind, Source};

use super::config::{DatasetConfig, ServiceConfig};
use super::error::ServiceError;

pub use crate::sample::pipeline::dataset_fingerprint;

/// Most generators with overridden configurations kept per dataset.
const MAX_GENERATORS: usize = 16;

/// One named dataset: a [`Pipeline`] and the generators of request overrides.
pub struct Dataset {
    pub name: String,
    pub description: String,
    pub source: Arc<dyn Source>,
    pub loader: Arc<SourceScenes>,
    pub cache: Arc<SceneCache>,
    /// The generator of the default configuration.
    pub generator: Arc<Generator>,
    /// Generators of overridden configurations, most recent last.
    overrides: Mutex<Vec<Arc<Generator>>>,
}

impl std::fmt::Debug for Dataset {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Dataset").field("name", &self.name).field("fingerprint", &self.fingerprint()).finish()
    }
}

/// Per-request changes to a dataset's sample configuration.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Overrides {
    pub motion_preset: Option<MotionPreset>,
    pub motion_ranges: Option<MotionRanges>,
    pub max_objects: Option<usize>,
    pub motions_per_image: Option<u64>,
    /// Frames per sample (`frames`; part of the fingerprint).
    pub frames: Option<usize>,
    /// The request asks for a backward field (not part of the fingerprint).
    pub backward: bool,
    /// The request asks for the occlusion field (not part of the fingerprint; the datasets'
    /// own configurations leave it out).
    pub occlusion: bool,
    pub resample: Option<crate::render::Resample>,
}

impl Overrides {
    pub fn is_empty(&self) -> bool {
        *self == Overrides::default()
    }
}

impl Dataset {
    pub fn new(
        name: String,
        source: Arc<dyn Source>,
        stage: Arc<SceneStage>,
        cache: Arc<SceneCache>,
        mut config: SampleConfig,
    ) -> Result<Self, ServiceError> {
        // the occlusion mask only for the requests that ask for it (`Overrides::occlusion`)
        config.occlusion = false;
        let pipeline = Pipeline::new(source, stage, cache.clone(), config).map_err(|e| match e {
            SampleError::Unusable(source) => ServiceError::Unusable { dataset: name.clone(), source },
            e => ServiceError::Config(format!("dataset {name}: {e}")),
        })?;
        Ok(Self {
            name,
            description: pipeline.describe(),
            source: pipeline.source().clone(),
            loader: pipeline.loader().clone(),
            cache,
            generator: pipeline.generator().clone(),
            overrides: Mutex::new(Vec::new()),
        })
    }

    /// Scenes built for this dataset so far (all its configurations together).
    pub fn scene_builds(&self) -> u64 {
        self.generator.scene_builds()
    }

    /// The fingerprint of the default configuration.
    pub fn fingerprint(&self) -> u64 {
        self.generator.fingerprint()
    }

    pub fn sources(&self) -> usize {
        self.source.len()
    }

    /// What the source left out when it was opened (e.g. a truncated shard's last sample), counted
    /// by failure kind.
    pub fn opened_skips(&self) -> BTreeMap<FailureKind, u64> {
        let mut out = BTreeMap::new();
        for s in self.source.skipped() {
            *out.entry(s.kind).or_insert(0) += 1;
        }
        out
    }

    /// The generator for the default configuration changed by `o` (shared with earlier requests
    /// asking for the same configuration). Errors name the request field.
    pub fn generator(&self, o: &Overrides) -> Result<Arc<Generator>, ServiceError> {
        if o.is_empty() {
            return Ok(self.generator.clone());
        }
        let mut config = self.generator.config().clone();
        if let Some(p) = o.motion_preset {
            config.motion = MotionSpec::Preset(p);
        }
        if let Some(r) = &o.motion_ranges {
            r.validate().map_err(|e| ServiceError::invalid("motion_ranges_json", e.to_string()))?;
            config.motion = MotionSpec::Ranges(Box::new(r.clone()));
        }
        if let Some(m) = o.max_objects {
            config.max_objects = m;
        }
        if let Some(m) = o.motions_per_image {
            config.motions_per_image = m;
        }
        if let Some(f) = o.frames {
            config.frames = f;
        }
        config.backward |= o.backward;
        config.occlusion |= o.occlusion;
        if let Some(r) = o.resample {
            config.resample = r;
        }
        if let Err(e) = config.validate() {
            // the default configuration was valid, so the field at fault is an overridden one,
            // and the request's overrides are named as the configuration's fields
            let field = match &e {
                SampleError::Config { field, .. } => *field,
                _ => "motion_ranges_json",
            };
            return Err(ServiceError::invalid(field, e.to_string()));
        }
        if config == *self.generator.config() {
            return Ok(self.generator.clone());
        }
        let mut list = self.overrides.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        if let Some(pos) = list.iter().position(|g| *g.config() == config) {
            let g = list.remove(pos);
            list.push(g.clone());
            return Ok(g);
        }
        let g = Arc::new(
            self.generator
                .with_config(config)
                .map_err(|e| ServiceError::invalid("motion_ranges_json", e.to_string()))?,
        );
        if list.len() >= MAX_GENERATORS {
            list.remove(0);
        }
        list.push(g.clone());
        Ok(g)
    }
}

/// All datasets of a server: the configured ones (fixed at start) and the uploaded ones (added
/// or replaced by `UploadSources`).
pub struct Datasets {
    pub list: Vec<Arc<Dataset>>,
    pub cache: Arc<SceneCache>,
    pub stage: Arc<SceneStage>,
    /// The received upload files.
    pub uploads: Arc<UploadStore>,
    /// Datasets made from uploads, by name.
    uploaded: RwLock<BTreeMap<String, Arc<Dataset>>>,
    /// The sample configuration of uploaded datasets.
    upload_sample: SampleConfig,
}

impl Datasets {
    /// Opens every configured dataset (the bundled scenes when none is configured) and loads the
    /// models. Slow (models, directory scans): call it off the async runtime.
    pub fn open(config: &ServiceConfig) -> Result<Self, ServiceError> {
        let stage = Arc::new(config.models.build_stage().map_err(ServiceError::Config)?);
        let cache_bytes = usize::try_from(config.cache_mb.saturating_mul(1 << 20)).unwrap_or(usize::MAX);
        let cache = Arc::new(SceneCache::new(cache_bytes));
        let resize = config.resize()?;
        let open = OpenOptions {
            resize,
            limits: config.image_limits(),
            photo_limits: Some(config.photo_limits()),
            follow_links: config.follow_source_links,
            ..OpenOptions::default()
        };
        let builtin = [DatasetConfig { name: None, path: "builtin".into(), sample: None }];
        let specs: &[DatasetConfig] = if config.datasets.is_empty() { &builtin } else { &config.datasets };
        let mut list = Vec::with_capacity(specs.len());
        for spec in specs {
            let name = spec.name();
            let source = open_source(&spec.source_spec(), &open)
                .map_err(|e| ServiceError::Config(format!("dataset {name}: {e}")))?;
            for s in source.skipped() {
                tracing::warn!(dataset = %name, item = %s.item, kind = %s.kind, reason = %s.reason, "source item left out");
            }
            if source.is_empty() {
                return Err(ServiceError::Config(format!("dataset {name}: {} has no images", source.describe())));
            }
            // the description names the frame the samples have (a folder's working size)
            tracing::info!(dataset = %name, source = %source.describe(), "dataset opened");
            let sample = spec.sample.clone().unwrap_or_else(|| config.sample.clone());
            let ds = Dataset::new(name.clone(), source, stage.clone(), cache.clone(), sample).map_err(|e| match e {
                e @ ServiceError::Unusable { .. } => e,
                e => ServiceError::Config(format!("dataset {name}: {e}")),
            })?;
            list.push(Arc::new(ds));
        }
        let upload_options = SourceOptions { resize, limits: config.image_limits(), ..SourceOptions::default() };
        let upload_limits = UploadLimits {
            max_upload_bytes: config.max_upload_bytes,
            max_concurrent: config.max_concurrent_uploads,
            max_buffer_bytes: config.max_upload_buffer_mb.saturating_mul(1 << 20),
            ..UploadLimits::default()
        };
        // items that could never make a scene with these models are rejected at the door
        let check_stage = stage.clone();
        let uploads = UploadStore::with_check(
            upload_options,
            upload_limits,
            Arc::new(move |item| check_stage.check_item(item).map_err(|e| e.to_string())),
        );
        Ok(Self {
            list,
            cache,
            stage,
            uploads,
            uploaded: RwLock::new(BTreeMap::new()),
            upload_sample: config.sample.clone(),
        })
    }

    /// The dataset called `name`; the empty name is the default (the first).
    pub fn get(&self, name: &str) -> Result<Arc<Dataset>, ServiceError> {
        if let Some(d) = if name.is_empty() { self.list.first() } else { self.list.iter().find(|d| d.name == name) } {
            return Ok(d.clone());
        }
        let up = self.uploaded.read().unwrap_or_else(std::sync::PoisonError::into_inner);
        if let Some(d) = up.get(name) {
            return Ok(d.clone());
        }
        // the known names, the first few (a long list of uploads is cut short)
        const SHOWN: usize = 8;
        let names: Vec<&str> = self.list.iter().map(|d| d.name.as_str()).chain(up.keys().map(String::as_str)).collect();
        let mut known = names.iter().take(SHOWN).map(|n| crate::failure::echo(n)).collect::<Vec<_>>().join(", ");
        if names.len() > SHOWN {
            known.push_str(&format!(" and {} more", names.len() - SHOWN));
        }
        Err(ServiceError::UnknownDataset { name: name.into(), known })
    }

    /// Every dataset: the configured ones (the default first), then the uploaded ones by name.
    pub fn all(&self) -> Vec<Arc<Dataset>> {
        let mut out = self.list.clone();
        out.extend(self.uploaded.read().unwrap_or_else(std::sync::PoisonError::into_inner).values().cloned());
        out
    }

    /// After an upload to `summary.dataset`: (re)makes that dataset from the upload store's
    /// current content. A name of a configured dataset cannot be uploaded to.
    pub fn refresh_upload(&self, summary: &UploadSummary) -> Result<Arc<Dataset>, ServiceError> {
        let name = &summary.dataset;
        let source = self
            .uploads
            .dyn_source(name)
            .ok_or_else(|| ServiceError::invalid("dataset", format!("upload dataset {name} holds no images")))?;
        let ds = Arc::new(Dataset::new(
            name.clone(),
            source,
            self.stage.clone(),
            self.cache.clone(),
            self.upload_sample.clone(),
        )?);
        self.uploaded.write().unwrap_or_else(std::sync::PoisonError::into_inner).insert(name.clone(), ds.clone());
        Ok(ds)
    }

    /// Whether `name` is a configured (not uploaded) dataset.
    pub fn is_configured(&self, name: &str) -> bool {
        self.list.iter().any(|d| d.name == name)
    }

    pub fn default_dataset(&self) -> &Arc<Dataset> {
        &self.list[0]
    }
}
