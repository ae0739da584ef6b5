//! Named scene models: the registry compiled into mpiflow (`registry.toml`: hub location, pinned
//! revision, SHA-256, licence and tensor contract of each name), and resolving a `NAME|FILE`
//! model argument to a file on disk (fetched into the hub cache on first use, [`super::hub`]) and
//! the contract to run it with (a FILE's optional manifest `FILE.toml` beside it).

use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::{Deserialize, Serialize};

use super::hub::{Hub, HubError, HubFile};
use super::onnx::{
    normalize_disparity, Normalization, OnnxDepth, OnnxDepthConfig, OnnxDetr, OnnxDetrConfig, OnnxSegmenter,
    OnnxSegmenterConfig, RawDepth, SizePolicy,
};
use super::{DepthEstimator, Disparity, SceneError, Segmenter};
use crate::io::image::RgbImage;
use crate::raster::InstanceMasks;

/// The built-in registry.
const BUILTIN: &str = include_str!("registry.toml");

/// The largest registry file read (bytes).
pub const MAX_REGISTRY_BYTES: u64 = 1 << 20;

pub use super::hub::REGISTRY_ENV;

#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    #[error(
        "{role} model {}: no such file, and no model of that name (named models: {names}; `mpiflow models list`, \
         docs/models.md)",
        .spec.display()
    )]
    NotFound { role: Role, spec: PathBuf, names: String },
    #[error("{role} model {name}: the registry names it a {actual} model")]
    WrongRole { role: Role, name: String, actual: Role },
    #[error("model registry {path}: {message}")]
    Registry { path: String, message: String },
    #[error("model manifest {}: {message}", .path.display())]
    Manifest { path: PathBuf, message: String },
    #[error("{role} model {name}: {source}")]
    Fetch {
        role: Role,
        name: String,
        #[source]
        source: HubError,
    },
}

/// What a model is for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    Depth,
    Segment,
}

impl std::fmt::Display for Role {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Role::Depth => "depth",
            Role::Segment => "segment",
        })
    }
}

/// What a network's output is.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum OutputKind {
    /// Depth: larger = nearer, any scale and shift (MiDaS, Depth Anything): normalised as it is.
    #[default]
    RelativeInverseDepth,
    /// Depth in metres (larger = farther): inverted before the normalisation.
    MetricDepth,
    /// Segmentation: DETR's queries (`logits` [1,Q,C+1], `pred_masks` [1,Q,h,w]), turned into
    /// instances by [`super::onnx::detr_instances`].
    DetrPanoptic,
}

impl OutputKind {
    /// The role whose outputs this kind describes.
    pub fn role(self) -> Role {
        match self {
            OutputKind::RelativeInverseDepth | OutputKind::MetricDepth => Role::Depth,
            OutputKind::DetrPanoptic => Role::Segment,
        }
    }

    fn name(self) -> &'static str {
        match self {
            OutputKind::RelativeInverseDepth => "relative-inverse-depth",
            OutputKind::MetricDepth => "metric-depth",
            OutputKind::DetrPanoptic => "detr-panoptic",
        }
    }
}

/// The tensor contract of a model; every field left out keeps mpiflow's default (docs/models.md).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Contract {
    /// The image input tensor.
    pub input: Option<String>,
    /// The depth output tensor.
    pub output: Option<String>,
    pub output_kind: Option<OutputKind>,
    /// A fixed network input size `[width, height]`.
    pub size: Option<[usize; 2]>,
    /// With no `size`: the image scaled to this longer side, keeping its aspect ratio (each side
    /// then rounded to `multiple_of`).
    pub long_side: Option<usize>,
    /// With no `size`: each side rounded to a multiple of this; with `size`, what the network
    /// needs of any other size (documentation; `size` is a multiple of it).
    pub multiple_of: Option<usize>,
    /// Per-channel `(x - mean) / std` of the [0, 1] RGB image.
    pub mean: Option<[f32; 3]>,
    pub std: Option<[f32; 3]>,
    /// Segmentation outputs.
    pub masks_output: Option<String>,
    pub scores_output: Option<String>,
    pub labels_output: Option<String>,
    /// `detr-panoptic`: the class logits output.
    pub logits_output: Option<String>,
    /// `detr-panoptic`: the first and last class id of the countable objects ("things"), the
    /// classes that may move.
    pub thing_labels: Option<[u32; 2]>,
}

impl Contract {
    fn size_policy(&self) -> Option<SizePolicy> {
        match (self.size, self.long_side, self.multiple_of) {
            (Some([width, height]), _, _) => Some(SizePolicy::Fixed { width, height }),
            (None, Some(side), m) => Some(SizePolicy::LongSide { side, multiple: m.unwrap_or(1) }),
            (None, None, Some(m)) => Some(SizePolicy::MultipleOf(m)),
            (None, None, None) => None,
        }
    }

    fn normalization(&self) -> Option<Normalization> {
        (self.mean.is_some() || self.std.is_some())
            .then(|| Normalization { mean: self.mean.unwrap_or([0.0; 3]), std: self.std.unwrap_or([1.0; 3]) })
    }

    /// The depth configuration of `model` under this contract.
    pub fn depth_config(&self, model: &Path) -> OnnxDepthConfig {
        let mut c = OnnxDepthConfig::new(model);
        if let Some(i) = &self.input {
            c.input.clone_from(i);
        }
        if let Some(o) = &self.output {
            c.output.clone_from(o);
        }
        if let Some(s) = self.size_policy() {
            c.size = s;
        }
        if let Some(n) = self.normalization() {
            c.normalization = n;
        }
        c
    }

    /// The segmentation configuration of `model` under this contract.
    pub fn segment_config(&self, model: &Path) -> OnnxSegmenterConfig {
        let mut c = OnnxSegmenterConfig::new(model);
        if let Some(i) = &self.input {
            c.input.clone_from(i);
        }
        if let Some(o) = &self.masks_output {
            c.masks_output.clone_from(o);
        }
        if let Some(o) = &self.scores_output {
            c.scores_output.clone_from(o);
        }
        if let Some(o) = &self.labels_output {
            c.labels_output = Some(o.clone());
        }
        if let Some(s) = self.size_policy() {
            c.size = s;
        }
        if let Some(n) = self.normalization() {
            c.normalization = n;
        }
        c
    }

    /// The DETR configuration of `model` under this contract (`output_kind = "detr-panoptic"`).
    pub fn detr_config(&self, model: &Path) -> OnnxDetrConfig {
        let mut c = OnnxDetrConfig::new(model);
        if let Some(i) = &self.input {
            c.input.clone_from(i);
        }
        if let Some(o) = &self.logits_output {
            c.logits_output.clone_from(o);
        }
        if let Some(o) = &self.masks_output {
            c.masks_output.clone_from(o);
        }
        if let Some([first, last]) = self.thing_labels {
            c.selection.things = first..=last;
        }
        if let Some(s) = self.size_policy() {
            c.size = s;
        }
        if let Some(n) = self.normalization() {
            c.normalization = n;
        }
        c
    }

    /// One line: the tensors, size, normalisation and output kind.
    pub fn describe(&self, role: Role) -> String {
        let name = |v: &Option<String>, d: &str| v.clone().unwrap_or_else(|| d.to_string());
        let size = match (self.size, self.long_side, self.multiple_of) {
            (Some([w, h]), _, _) => format!("{w}x{h}"),
            (None, Some(side), Some(m)) => format!("longer side {side} (multiples of {m})"),
            (None, Some(side), None) => format!("longer side {side}"),
            (None, None, Some(m)) => format!("multiples of {m}"),
            (None, None, None) => "the model's static size, else the image's".into(),
        };
        let norm = match self.normalization() {
            Some(n) => format!("mean {:?} std {:?}", n.mean, n.std),
            None => "none ([0, 1] RGB)".into(),
        };
        match role {
            Role::Depth => format!(
                "input `{}` [1,3,h,w] at {size}, normalisation {norm}; output `{}` [1,h,w] or [1,1,h,w], {}",
                name(&self.input, "image"),
                name(&self.output, "depth"),
                match self.output_kind.unwrap_or_default() {
                    OutputKind::RelativeInverseDepth => "relative inverse depth",
                    OutputKind::MetricDepth => "metric depth",
                    OutputKind::DetrPanoptic => "(a segmentation output)",
                }
            ),
            Role::Segment if self.output_kind == Some(OutputKind::DetrPanoptic) => {
                let [first, last] = self.thing_labels.unwrap_or([1, 90]);
                format!(
                    "input `{}` [1,3,h,w] at {size}, normalisation {norm}; outputs `{}` [1,Q,C+1], `{}` [1,Q,h,w]: \
                     DETR panoptic queries, classes {first} to {last} are objects that may move",
                    name(&self.input, "pixel_values"),
                    name(&self.logits_output, "logits"),
                    name(&self.masks_output, "pred_masks"),
                )
            }
            Role::Segment => format!(
                "input `{}` [1,3,h,w] at {size}, normalisation {norm}; outputs `{}`, `{}`, `{}`",
                name(&self.input, "image"),
                name(&self.masks_output, "masks"),
                name(&self.scores_output, "scores"),
                name(&self.labels_output, "labels"),
            ),
        }
    }
}

/// One named model.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Entry {
    pub name: String,
    pub role: Role,
    #[serde(default)]
    pub description: String,
    /// The hub repository, `ORG/NAME`.
    pub repo: String,
    /// A commit (40 hex digits) or a branch or tag name.
    pub revision: String,
    /// The file in the repository.
    pub file: String,
    /// The SHA-256 of the file, lower-case hex.
    pub sha256: String,
    /// The file's size in bytes: a download stops there (without it, at
    /// [`super::hub::MAX_MODEL_BYTES`]).
    #[serde(default)]
    pub size: Option<u64>,
    pub licence: String,
    #[serde(default)]
    pub contract: Contract,
}

impl Entry {
    /// The file in the hub this entry names.
    pub fn hub_file(&self) -> HubFile {
        HubFile {
            name: self.name.clone(),
            repo: self.repo.clone(),
            revision: self.revision.clone(),
            file: self.file.clone(),
            sha256: self.sha256.clone(),
            size: self.size,
        }
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RegistryFile {
    #[serde(default)]
    model: Vec<Entry>,
}

fn parse(text: &str, path: &str) -> Result<Vec<Entry>, ModelError> {
    let f: RegistryFile =
        toml::from_str(text).map_err(|e| ModelError::Registry { path: path.into(), message: e.to_string() })?;
    for e in &f.model {
        super::hub::check_file(&e.hub_file())
            .map_err(|m| ModelError::Registry { path: path.into(), message: format!("{}: {m}", e.name) })?;
    }
    Ok(f.model)
}

/// The registry: the built-in entries, then those of [`REGISTRY_ENV`]'s file (an entry with a
/// built-in name replaces it in place; an empty variable is none).
pub fn registry() -> Result<Vec<Entry>, ModelError> {
    let mut out = parse(BUILTIN, "(built in)")?;
    if let Some(p) = std::env::var_os(REGISTRY_ENV).filter(|p| !p.is_empty()) {
        let path = PathBuf::from(p);
        let text = crate::io::bounded::read_to_string(&path, MAX_REGISTRY_BYTES)
            .map_err(|e| ModelError::Registry { path: path.display().to_string(), message: e.to_string() })?;
        for e in parse(&text, &path.display().to_string())? {
            match out.iter_mut().find(|o| o.name == e.name) {
                Some(o) => *o = e,
                None => out.push(e),
            }
        }
    }
    Ok(out)
}

/// The registry entry called `name`.
pub fn find(name: &str) -> Result<Option<Entry>, ModelError> {
    Ok(registry()?.into_iter().find(|e| e.name == name))
}

/// A model argument resolved to a file and the contract to run it with.
#[derive(Clone, Debug, PartialEq)]
pub struct Resolved {
    pub path: PathBuf,
    pub contract: Contract,
    /// The registry entry, for a name.
    pub entry: Option<Entry>,
}

/// The manifest beside a model file: `FILE.toml` (e.g. `model.onnx.toml`).
pub fn manifest_path(file: &Path) -> PathBuf {
    let mut s = file.as_os_str().to_owned();
    s.push(".toml");
    PathBuf::from(s)
}

/// Resolves `spec` for `role`: an existing file (with its manifest's contract, if any), else a
/// registry name (fetched into the hub cache on first use, with a progress bar on stderr when
/// `progress`), else an error naming both ways.
pub fn resolve(spec: &Path, role: Role, hub: &Hub, progress: bool) -> Result<Resolved, ModelError> {
    if spec.is_file() {
        let manifest = manifest_path(spec);
        let contract = if manifest.is_file() {
            let text = crate::io::bounded::read_to_string(&manifest, MAX_REGISTRY_BYTES)
                .map_err(|e| ModelError::Manifest { path: manifest.clone(), message: e.to_string() })?;
            toml::from_str(&text)
                .map_err(|e| ModelError::Manifest { path: manifest.clone(), message: e.to_string() })?
        } else {
            Contract::default()
        };
        return Ok(Resolved { path: spec.to_path_buf(), contract, entry: None });
    }
    let entries = registry()?;
    let name = spec.to_str().unwrap_or_default();
    let Some(entry) = entries.iter().find(|e| e.name == name).cloned() else {
        let names = entries.iter().filter(|e| e.role == role).map(|e| e.name.as_str()).collect::<Vec<_>>();
        let names = if names.is_empty() { "none".to_string() } else { names.join(", ") };
        return Err(ModelError::NotFound { role, spec: spec.to_path_buf(), names });
    };
    if entry.role != role {
        return Err(ModelError::WrongRole { role, name: entry.name.clone(), actual: entry.role });
    }
    let path = hub.fetch(&entry.hub_file(), progress).map_err(|source| ModelError::Fetch {
        role,
        name: entry.name.clone(),
        source,
    })?;
    Ok(Resolved { path, contract: entry.contract.clone(), entry: Some(entry) })
}

/// A depth model whose output is metric depth: the network's output inverted (non-positive or
/// non-finite values become the farthest), then normalised as relative inverse depth is.
#[derive(Debug)]
pub struct MetricDepth(pub OnnxDepth);

impl MetricDepth {
    fn inverse(raw: RawDepth) -> Vec<f32> {
        let inv: Vec<f32> = raw.data.iter().map(|&d| if d > 0.0 && d.is_finite() { 1.0 / d } else { 0.0 }).collect();
        inv
    }
}

impl DepthEstimator for MetricDepth {
    fn name(&self) -> String {
        self.0.name()
    }

    fn identity(&self) -> String {
        format!("{}; output: metric depth, inverted", self.0.identity())
    }

    fn estimate(&self, image: &RgbImage) -> Result<Disparity, SceneError> {
        let raw = self.0.estimate_raw(image)?;
        let (width, height) = (raw.width, raw.height);
        let data = normalize_disparity(&Self::inverse(raw), self.0.config().floor);
        Ok(Disparity { width, height, data })
    }

    fn inference_runs(&self) -> Option<u64> {
        self.0.inference_runs()
    }

    fn content_hash(&self) -> Option<u64> {
        self.0.content_hash()
    }
}

/// A depth model known by its registry name: shown as `NAME (onnx:FILE)` in logs, `GetInfo` and
/// bake manifests; its identity (and so every fingerprint) is the model's own.
struct NamedDepth {
    name: String,
    inner: Arc<dyn DepthEstimator>,
}

impl DepthEstimator for NamedDepth {
    fn name(&self) -> String {
        format!("{} ({})", self.name, self.inner.name())
    }

    fn identity(&self) -> String {
        self.inner.identity()
    }

    fn estimate(&self, image: &RgbImage) -> Result<Disparity, SceneError> {
        self.inner.estimate(image)
    }

    fn inference_runs(&self) -> Option<u64> {
        self.inner.inference_runs()
    }

    fn content_hash(&self) -> Option<u64> {
        self.inner.content_hash()
    }
}

/// Refuses a contract whose `output_kind` belongs to another role than `role`.
fn check_kind(r: &Resolved, role: Role) -> Result<(), SceneError> {
    match r.contract.output_kind {
        Some(kind) if kind.role() != role => Err(SceneError::Model {
            kind: if role == Role::Depth { "depth" } else { "segmentation" },
            model: r.path.display().to_string(),
            message: format!(
                "output_kind `{}` is a {} output: use the model as --{}-model, or fix its manifest",
                kind.name(),
                kind.role(),
                kind.role()
            ),
        }),
        _ => Ok(()),
    }
}

/// Loads a resolved depth model with its contract (sessions created and warmed here).
pub fn load_depth(r: &Resolved) -> Result<Arc<dyn DepthEstimator>, SceneError> {
    check_kind(r, Role::Depth)?;
    let model = OnnxDepth::new(r.contract.depth_config(&r.path))?;
    let model: Arc<dyn DepthEstimator> = match r.contract.output_kind.unwrap_or_default() {
        OutputKind::MetricDepth => Arc::new(MetricDepth(model)),
        OutputKind::RelativeInverseDepth | OutputKind::DetrPanoptic => Arc::new(model),
    };
    Ok(match &r.entry {
        Some(e) => Arc::new(NamedDepth { name: e.name.clone(), inner: model }),
        None => model,
    })
}

/// A segmenter known by its registry name: shown as `NAME (onnx:FILE)`; its identity is the
/// model's own.
struct NamedSegmenter {
    name: String,
    inner: Arc<dyn Segmenter>,
}

impl Segmenter for NamedSegmenter {
    fn name(&self) -> String {
        format!("{} ({})", self.name, self.inner.name())
    }

    fn identity(&self) -> String {
        self.inner.identity()
    }

    fn segment(&self, image: &RgbImage) -> Result<InstanceMasks, SceneError> {
        self.inner.segment(image)
    }

    fn inference_runs(&self) -> Option<u64> {
        self.inner.inference_runs()
    }

    fn content_hash(&self) -> Option<u64> {
        self.inner.content_hash()
    }
}

/// Loads a resolved segmentation model with its contract: a DETR network for
/// `output_kind = "detr-panoptic"`, else the masks-scores-labels contract (sessions created and
/// warmed here).
pub fn load_segmenter(r: &Resolved) -> Result<Arc<dyn Segmenter>, SceneError> {
    check_kind(r, Role::Segment)?;
    let model: Arc<dyn Segmenter> = match r.contract.output_kind {
        Some(OutputKind::DetrPanoptic) => Arc::new(OnnxDetr::new(r.contract.detr_config(&r.path))?),
        _ => Arc::new(OnnxSegmenter::new(r.contract.segment_config(&r.path))?),
    };
    Ok(match &r.entry {
        Some(e) => Arc::new(NamedSegmenter { name: e.name.clone(), inner: model }),
        None => model,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_built_in_registry_parses_and_names_two_depth_models_and_a_segmenter() {
        let r = parse(BUILTIN, "(built in)").unwrap();
        let names: Vec<&str> = r.iter().map(|e| e.name.as_str()).collect();
        assert_eq!(names, ["depth-anything-v2-small", "dpt-hybrid-midas", "detr-resnet-50-panoptic"]);
        let da = &r[0];
        let c = da.contract.depth_config(Path::new("m.onnx"));
        assert_eq!((c.input.as_str(), c.output.as_str()), ("pixel_values", "predicted_depth"));
        assert_eq!(c.size, SizePolicy::Fixed { width: 518, height: 518 });
        assert_eq!(c.normalization, Normalization::IMAGENET);
        assert_eq!(r[1].contract.depth_config(Path::new("m.onnx")).normalization, Normalization::HALF);
        let detr = &r[2];
        assert_eq!((detr.role, detr.licence.as_str()), (Role::Segment, "Apache-2.0"));
        assert_eq!(detr.contract.output_kind.map(OutputKind::role), Some(Role::Segment));
        let c = detr.contract.detr_config(Path::new("m.onnx"));
        assert_eq!(
            (c.input.as_str(), c.logits_output.as_str(), c.masks_output.as_str()),
            ("pixel_values", "logits", "pred_masks")
        );
        assert_eq!(c.size, SizePolicy::LongSide { side: 640, multiple: 32 });
        assert_eq!(c.normalization, Normalization::IMAGENET);
        assert_eq!(c.selection.things, 1..=90);
    }

    #[test]
    fn a_bad_checksum_in_a_registry_is_refused() {
        let text = BUILTIN.replace("afb6a5c28f3b6bf1618c6e43f02073ef9dfdc70e937502d51603e57b0a1df10c", "abc");
        let e = parse(&text, "x.toml").unwrap_err();
        assert!(e.to_string().contains("depth-anything-v2-small: sha256 must be 64"), "{e}");
    }

    /// Registry paths that would leave the hub cache or the repository's URL are refused: `..`,
    /// `.`, empty and absolute components in `file` and `revision`, and a `repo` that is not
    /// `ORG/NAME`.
    #[test]
    fn registry_paths_with_dot_dot_or_absolute_parts_are_refused() {
        let with = |key: &str, from: &str, to: &str| {
            let text = BUILTIN.replacen(&format!("{key} = \"{from}\""), &format!("{key} = \"{to}\""), 1);
            assert_ne!(text, BUILTIN, "{key} {from}");
            parse(&text, "x.toml").map(|_| ()).map_err(|e| e.to_string())
        };
        let file = "onnx/model.onnx";
        let revision = "4472b7362082ad9968fee890ca0f1e5aca36b93d";
        let repo = "onnx-community/depth-anything-v2-small";
        for bad in ["../model.onnx", "onnx/../../x", "/etc/passwd", "onnx//model.onnx", "./model.onnx", "a\\\\b", ""] {
            let e = with("file", file, bad).unwrap_err();
            assert!(e.contains("depth-anything-v2-small: file"), "{bad}: {e}");
        }
        for bad in ["..", "../../x", "/abs", "main/.."] {
            let e = with("revision", revision, bad).unwrap_err();
            assert!(e.contains("depth-anything-v2-small: revision"), "{bad}: {e}");
        }
        for bad in ["../x", "a/b/c", "a/..", "a b/c"] {
            let e = with("repo", repo, bad).unwrap_err();
            assert!(e.contains("depth-anything-v2-small: repo"), "{bad}: {e}");
        }
        with("revision", revision, "refs/pr/1").unwrap();
        with("file", file, "model.onnx").unwrap();
    }
}
