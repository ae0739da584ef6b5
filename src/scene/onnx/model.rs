//! What the three ONNX scene models share: one session per model file behind a mutex, tensor
//! look-up with errors that name the model and list its real tensors, input preparation
//! (resizing, normalisation, planar layout), output extraction with shape and NaN/Inf checks, and
//! the inference timer.

use std::borrow::Cow;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use ort::session::{Session, SessionInputValue};
use ort::value::{Outlet, TensorElementType, TensorRef, ValueType};

use super::runtime;
use crate::io::image::RgbImage;
use crate::raster::resize_bilinear;
use crate::scene::SceneError;
use crate::source::Fnv64;

/// How the image is sized for the network (the result is always resized back to the image).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum SizePolicy {
    /// The model's own input size when its input declares a static height and width, else the
    /// image's size (the default).
    #[default]
    Model,
    /// Always the image's size.
    AsIs,
    /// A fixed `width x height`.
    Fixed { width: usize, height: usize },
    /// Each side rounded to the nearest multiple of `m` (at least `m`); AdaMPI wants `m = 128`.
    MultipleOf(usize),
    /// The image scaled (up or down) so that its longer side is `side`, keeping its aspect ratio,
    /// each side then rounded to the nearest multiple of `multiple` (at least `multiple`).
    LongSide { side: usize, multiple: usize },
}

impl SizePolicy {
    /// The network size for an image of `width x height`, given the model's static size if any.
    pub fn network_size(&self, width: usize, height: usize, model_static: Option<(usize, usize)>) -> (usize, usize) {
        match *self {
            SizePolicy::Model => model_static.unwrap_or((width, height)),
            SizePolicy::AsIs => (width, height),
            SizePolicy::Fixed { width, height } => (width, height),
            SizePolicy::MultipleOf(m) => {
                let m = m.max(1);
                let round = |v: usize| (((v + m / 2) / m) * m).max(m);
                (round(width), round(height))
            }
            SizePolicy::LongSide { side, multiple } => {
                let m = multiple.max(1) as f64;
                let scale = side as f64 / width.max(height).max(1) as f64;
                let round = |v: usize| (((v as f64 * scale / m).round() * m) as usize).max(m as usize);
                (round(width), round(height))
            }
        }
    }

    /// The size of the dummy image of the warm-up run.
    pub(crate) fn warmup_size(&self, model_static: Option<(usize, usize)>) -> (usize, usize) {
        match *self {
            SizePolicy::Model => model_static.unwrap_or((64, 64)),
            SizePolicy::AsIs => (64, 64),
            SizePolicy::Fixed { width, height } => (width, height),
            SizePolicy::MultipleOf(m) => {
                let m = m.max(1);
                let s = m * 64usize.div_ceil(m);
                (s, s)
            }
            SizePolicy::LongSide { .. } => self.network_size(4, 3, model_static),
        }
    }
}

/// Per-channel input normalisation, `(x - mean) / std` on values in [0, 1].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Normalization {
    pub mean: [f32; 3],
    pub std: [f32; 3],
}

impl Normalization {
    /// No change (the default: the export recipes in `tools/export/` put each network's own
    /// normalisation inside the graph, so their models take [0, 1] input).
    pub const IDENTITY: Normalization = Normalization { mean: [0.0; 3], std: [1.0; 3] };
    /// torchvision's ImageNet statistics (MiDaS v2.1 and most CNN backbones without baked-in
    /// normalisation).
    pub const IMAGENET: Normalization = Normalization { mean: [0.485, 0.456, 0.406], std: [0.229, 0.224, 0.225] };
    /// Mean 0.5, std 0.5, i.e. [-1, 1] (DPT / MiDaS v3 checkpoints).
    pub const HALF: Normalization = Normalization { mean: [0.5; 3], std: [0.5; 3] };

    fn check(&self) -> Result<(), String> {
        if self.mean.iter().chain(&self.std).any(|v| !v.is_finite()) || self.std.contains(&0.0) {
            return Err(format!("invalid normalisation {self:?}: mean and std must be finite and std non-zero"));
        }
        Ok(())
    }
}

impl Default for Normalization {
    fn default() -> Self {
        Normalization::IDENTITY
    }
}

/// Inference time of one model: only `Session::run` (not resizing or post-processing, not the
/// wait for the session's lock), warm-up excluded.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct InferenceStats {
    /// Number of runs (warm-up excluded).
    pub runs: u64,
    /// Total time of those runs.
    pub total: Duration,
    /// Time of the warm-up run done by the constructor.
    pub warmup: Duration,
}

impl InferenceStats {
    pub fn total_ms(&self) -> f64 {
        self.total.as_secs_f64() * 1e3
    }
}

/// A tensor's declared type and shape (dimensions < 0 are dynamic; `symbols` their names).
#[derive(Clone, Debug)]
pub(crate) struct TensorInfo {
    pub name: String,
    pub ty: Option<TensorElementType>,
    pub dims: Option<Vec<i64>>,
    pub symbols: Vec<String>,
}

impl TensorInfo {
    fn from_outlet(o: &Outlet) -> Self {
        match o.dtype() {
            ValueType::Tensor { ty, shape, dimension_symbols } => TensorInfo {
                name: o.name().to_string(),
                ty: Some(*ty),
                dims: Some(shape.to_vec()),
                symbols: dimension_symbols.to_vec(),
            },
            _ => TensorInfo { name: o.name().to_string(), ty: None, dims: None, symbols: Vec::new() },
        }
    }

    /// `name f32 [1,3,h,w]`.
    pub fn describe(&self) -> String {
        let ty = self.ty.map_or("non-tensor".to_string(), |t| t.to_string());
        match &self.dims {
            Some(dims) => format!("`{}` {ty} {}", self.name, self.shape_string(dims)),
            None => format!("`{}` {ty}", self.name),
        }
    }

    fn shape_string(&self, dims: &[i64]) -> String {
        let parts: Vec<String> = dims
            .iter()
            .enumerate()
            .map(|(i, &d)| {
                if d >= 0 {
                    d.to_string()
                } else {
                    self.symbols.get(i).filter(|s| !s.is_empty()).cloned().unwrap_or_else(|| "?".into())
                }
            })
            .collect();
        format!("[{}]", parts.join(","))
    }

    pub fn rank(&self) -> Option<usize> {
        self.dims.as_ref().map(Vec::len)
    }

    /// The static (height, width) of a rank-4 NCHW tensor, when both are fixed.
    pub fn static_hw(&self) -> Option<(usize, usize)> {
        let d = self.dims.as_ref()?;
        (d.len() == 4 && d[2] > 0 && d[3] > 0).then(|| (d[3] as usize, d[2] as usize))
    }
}

/// A model output copied out of ONNX Runtime.
pub(crate) struct Output {
    pub dims: Vec<usize>,
    pub data: Vec<f32>,
}

/// One input: name, NCHW shape, data.
pub(crate) struct Input<'a> {
    pub name: &'a str,
    pub shape: [usize; 4],
    pub data: &'a [f32],
}

/// A loaded model: the session (behind a mutex, since `Session::run` takes `&mut self`; one
/// inference at a time per model, ONNX Runtime parallelises inside it), its declared tensors,
/// the timer.
pub(crate) struct OnnxModel {
    kind: &'static str,
    path: PathBuf,
    session: Mutex<Session>,
    pub inputs: Vec<TensorInfo>,
    pub outputs: Vec<TensorInfo>,
    /// FNV-1a 64 of the model file's bytes: the bytes ONNX Runtime loaded (the session is made
    /// from this very buffer), so two files with the same name but other weights differ here.
    content_hash: u64,
    runs: AtomicU64,
    nanos: AtomicU64,
    warmup_nanos: AtomicU64,
}

impl std::fmt::Debug for OnnxModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("OnnxModel").field("kind", &self.kind).field("path", &self.path).finish_non_exhaustive()
    }
}

impl OnnxModel {
    /// Loads ONNX Runtime (if not yet loaded) and the model file.
    pub fn open(
        kind: &'static str,
        path: &Path,
        library: Option<&Path>,
        intra_threads: usize,
        normalization: &Normalization,
    ) -> Result<Self, SceneError> {
        let err = |message: String| SceneError::Model { kind, model: path.display().to_string(), message };
        normalization.check().map_err(err)?;
        let env = runtime::environment(library)?;
        if !path.is_file() {
            return Err(err("the model file does not exist".into()));
        }
        let mut builder = Session::builder(env).map_err(|e| err(format!("cannot create a session: {e}")))?;
        if intra_threads > 0 {
            builder = builder
                .with_intra_threads(intra_threads)
                .map_err(|e| err(format!("cannot set {intra_threads} threads: {e}")))?;
        }
        // read once: the hash covers exactly the bytes the session is made from
        let bytes = std::fs::read(path).map_err(|e| err(format!("cannot read the model file: {e}")))?;
        let content_hash = Fnv64::new().bytes(&bytes).finish();
        let session =
            builder.commit_from_memory(&bytes).map_err(|e| err(format!("ONNX Runtime cannot load the model: {e}")))?;
        drop(bytes);
        let inputs = session.inputs().iter().map(TensorInfo::from_outlet).collect();
        let outputs = session.outputs().iter().map(TensorInfo::from_outlet).collect();
        Ok(OnnxModel {
            kind,
            path: path.to_path_buf(),
            session: Mutex::new(session),
            inputs,
            outputs,
            content_hash,
            runs: AtomicU64::new(0),
            nanos: AtomicU64::new(0),
            warmup_nanos: AtomicU64::new(0),
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// FNV-1a 64 of the model file's bytes (the bytes the session was made from).
    pub fn content_hash(&self) -> u64 {
        self.content_hash
    }

    /// `onnx:FILE_NAME`.
    pub fn short_name(&self) -> String {
        format!(
            "onnx:{}",
            self.path.file_name().map_or_else(|| self.path.display().to_string(), |n| n.to_string_lossy().into())
        )
    }

    /// What makes this model's outputs what they are, for fingerprints: the kind, the content
    /// hash of the file and the contract (`contract`: the configuration without paths, thread
    /// counts or the runtime library, which change no output). The file's name and folder are
    /// not part of it: the same weights anywhere give the same identity.
    pub fn identity(&self, contract: &str) -> String {
        format!("onnx {} content {:016x} contract {contract}", self.kind, self.content_hash)
    }

    pub fn err(&self, message: impl Into<String>) -> SceneError {
        SceneError::Model { kind: self.kind, model: self.path.display().to_string(), message: message.into() }
    }

    fn list(tensors: &[TensorInfo]) -> String {
        tensors.iter().map(TensorInfo::describe).collect::<Vec<_>>().join(", ")
    }

    /// The declared input `name` (an f32 tensor of rank 4 when its rank is declared).
    pub fn image_input(&self, name: &str, channels: usize) -> Result<&TensorInfo, SceneError> {
        let info = self.inputs.iter().find(|t| t.name == name).ok_or_else(|| {
            self.err(format!("has no input tensor `{name}`; its inputs are: {}", Self::list(&self.inputs)))
        })?;
        if info.ty != Some(TensorElementType::Float32) {
            return Err(self.err(format!("input {} must be a float32 tensor", info.describe())));
        }
        if let Some(dims) = &info.dims {
            let ok = dims.len() == 4 && dims[0] <= 1 && (dims[1] < 0 || dims[1] as usize == channels);
            if !ok {
                return Err(self.err(format!(
                    "input {} has the wrong rank or shape; expected [1,{channels},h,w]",
                    info.describe()
                )));
            }
        }
        Ok(info)
    }

    /// Every input must be one the contract feeds.
    pub fn check_no_other_inputs(&self, fed: &[&str]) -> Result<(), SceneError> {
        if let Some(extra) = self.inputs.iter().find(|t| !fed.contains(&t.name.as_str())) {
            return Err(self.err(format!(
                "has an input {} that the contract does not provide (it feeds {}); its inputs are: {}",
                extra.describe(),
                fed.iter().map(|n| format!("`{n}`")).collect::<Vec<_>>().join(", "),
                Self::list(&self.inputs)
            )));
        }
        Ok(())
    }

    pub fn has_output(&self, name: &str) -> bool {
        self.outputs.iter().any(|t| t.name == name)
    }

    /// The declared output `name`, with one of the `ranks` when its rank is declared.
    pub fn output(&self, name: &str, ranks: &[usize], expected: &str) -> Result<&TensorInfo, SceneError> {
        let info = self.outputs.iter().find(|t| t.name == name).ok_or_else(|| {
            self.err(format!("has no output tensor `{name}`; its outputs are: {}", Self::list(&self.outputs)))
        })?;
        if let Some(r) = info.rank() {
            if !ranks.contains(&r) {
                return Err(self.err(format!("output {} has rank {r}; expected {expected}", info.describe())));
            }
        }
        Ok(info)
    }

    /// Runs the session on `inputs` and copies out `outputs` (as f32; integer outputs are
    /// converted), refusing NaN or infinite values in float outputs.
    pub fn run(&self, inputs: &[Input<'_>], outputs: &[&str], warmup: bool) -> Result<Vec<Output>, SceneError> {
        let mut values: Vec<(Cow<'_, str>, SessionInputValue<'_>)> = Vec::with_capacity(inputs.len());
        for input in inputs {
            let tensor = TensorRef::from_array_view((input.shape, input.data))
                .map_err(|e| self.err(format!("cannot make input tensor `{}`: {e}", input.name)))?;
            values.push((Cow::Borrowed(input.name), tensor.into()));
        }
        let mut session = self.session.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        let start = Instant::now();
        let result = session.run(values);
        let elapsed = start.elapsed();
        let shapes = || inputs.iter().map(|i| format!("`{}` {:?}", i.name, i.shape)).collect::<Vec<_>>().join(", ");
        let result = result.map_err(|e| self.err(format!("inference failed on inputs {}: {e}", shapes())))?;
        let mut copied = Vec::with_capacity(outputs.len());
        for &name in outputs {
            let value =
                result.get(name).ok_or_else(|| self.err(format!("ONNX Runtime returned no output `{name}`")))?;
            let (dims, data, is_float) = if let Ok((shape, data)) = value.try_extract_tensor::<f32>() {
                (shape.to_vec(), data.to_vec(), true)
            } else if let Ok((shape, data)) = value.try_extract_tensor::<i64>() {
                (shape.to_vec(), data.iter().map(|&v| v as f32).collect(), false)
            } else if let Ok((shape, data)) = value.try_extract_tensor::<i32>() {
                (shape.to_vec(), data.iter().map(|&v| v as f32).collect(), false)
            } else {
                return Err(self.err(format!(
                    "output `{name}` has type {:?}; expected a float32 (or integer) tensor",
                    value.dtype()
                )));
            };
            if is_float && data.iter().any(|v| !v.is_finite()) {
                let nan = data.iter().filter(|v| v.is_nan()).count();
                let inf = data.iter().filter(|v| v.is_infinite()).count();
                return Err(self
                    .err(format!("output `{name}` contains {nan} NaN and {inf} infinite values (of {})", data.len())));
            }
            let dims = dims.iter().map(|&d| d.max(0) as usize).collect();
            copied.push(Output { dims, data });
        }
        drop(result);
        drop(session);
        let nanos = elapsed.as_nanos().min(u64::MAX as u128) as u64;
        if warmup {
            self.warmup_nanos.store(nanos, Ordering::Relaxed);
        } else {
            self.runs.fetch_add(1, Ordering::Relaxed);
            self.nanos.fetch_add(nanos, Ordering::Relaxed);
        }
        Ok(copied)
    }

    pub fn stats(&self) -> InferenceStats {
        InferenceStats {
            runs: self.runs.load(Ordering::Relaxed),
            total: Duration::from_nanos(self.nanos.load(Ordering::Relaxed)),
            warmup: Duration::from_nanos(self.warmup_nanos.load(Ordering::Relaxed)),
        }
    }

    pub fn reset_stats(&self) {
        self.runs.store(0, Ordering::Relaxed);
        self.nanos.store(0, Ordering::Relaxed);
    }

    /// Refuses a fixed size that contradicts the model's static input size.
    pub fn check_policy(&self, policy: &SizePolicy, input: &TensorInfo) -> Result<(), SceneError> {
        if let (SizePolicy::Fixed { width, height }, Some((w, h))) = (policy, input.static_hw()) {
            if (*width, *height) != (w, h) {
                return Err(self.err(format!(
                    "the configured input size {width}x{height} does not match input {} ({w}x{h})",
                    input.describe()
                )));
            }
        }
        if let SizePolicy::Fixed { width: 0, .. }
        | SizePolicy::Fixed { height: 0, .. }
        | SizePolicy::MultipleOf(0)
        | SizePolicy::LongSide { side: 0, .. }
        | SizePolicy::LongSide { multiple: 0, .. } = policy
        {
            return Err(self.err(format!("invalid input size policy {policy:?}")));
        }
        Ok(())
    }
}

/// `f32` planes `[3, h, w]` of the image resized (bilinear) to `w x h`, normalised.
pub(crate) fn image_tensor(image: &RgbImage, w: usize, h: usize, norm: &Normalization) -> Vec<f32> {
    let (iw, ih) = (image.width, image.height);
    let mut out = Vec::with_capacity(3 * w * h);
    for c in 0..3 {
        let plane: Vec<f32> = image.data.iter().skip(c).step_by(3).copied().collect();
        let plane = if (iw, ih) == (w, h) { plane } else { resize_bilinear(&plane, iw, ih, w, h) };
        let (m, s) = (norm.mean[c], norm.std[c]);
        out.extend(plane.iter().map(|&v| (v - m) / s));
    }
    out
}

/// A single `w x h` map resized (bilinear) to `nw x nh` (a copy when the sizes agree).
pub(crate) fn resize_map(data: &[f32], w: usize, h: usize, nw: usize, nh: usize) -> Vec<f32> {
    if (w, h) == (nw, nh) {
        data.to_vec()
    } else {
        resize_bilinear(data, w, h, nw, nh)
    }
}

/// `[a,b,c]` for messages.
pub(crate) fn dims_string(dims: &[usize]) -> String {
    let mut s = String::from("[");
    for (i, d) in dims.iter().enumerate() {
        if i > 0 {
            s.push(',');
        }
        let _ = write!(s, "{d}");
    }
    s.push(']');
    s
}

/// Checks that an image is non-empty and its data fits its size.
pub(crate) fn check_image(model: &OnnxModel, image: &RgbImage) -> Result<(), SceneError> {
    if image.width == 0 || image.height == 0 || image.data.len() != image.width * image.height * 3 {
        return Err(model.err(format!(
            "invalid input image {}x{} with {} values",
            image.width,
            image.height,
            image.data.len()
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn size_policies() {
        assert_eq!(SizePolicy::Model.network_size(100, 60, Some((32, 24))), (32, 24));
        assert_eq!(SizePolicy::Model.network_size(100, 60, None), (100, 60));
        assert_eq!(SizePolicy::AsIs.network_size(100, 60, Some((32, 24))), (100, 60));
        assert_eq!(SizePolicy::Fixed { width: 7, height: 5 }.network_size(100, 60, None), (7, 5));
        assert_eq!(SizePolicy::MultipleOf(128).network_size(640, 480, None), (640, 512));
        assert_eq!(SizePolicy::MultipleOf(128).network_size(384, 256, None), (384, 256));
        assert_eq!(SizePolicy::MultipleOf(128).network_size(10, 190, None), (128, 128));
        assert_eq!(SizePolicy::MultipleOf(128).network_size(10, 192, None), (128, 256));
        assert_eq!(SizePolicy::MultipleOf(128).warmup_size(None), (128, 128));
        assert_eq!(SizePolicy::MultipleOf(16).warmup_size(None), (64, 64));
        let long = SizePolicy::LongSide { side: 640, multiple: 32 };
        assert_eq!(long.network_size(451, 300, None), (640, 416));
        assert_eq!(long.network_size(3000, 4000, Some((9, 9))), (480, 640));
        assert_eq!(long.network_size(4000, 10, None), (640, 32));
        assert_eq!(long.warmup_size(None), (640, 480));
    }

    #[test]
    fn image_tensor_is_planar_and_normalised() {
        let image = RgbImage { width: 2, height: 1, data: vec![0.1, 0.2, 0.3, 0.4, 0.5, 0.6] };
        let norm = Normalization { mean: [0.1, 0.0, 0.0], std: [1.0, 2.0, 1.0] };
        let t = image_tensor(&image, 2, 1, &norm);
        let expect = [0.0, 0.3, 0.1, 0.25, 0.3, 0.6];
        for (a, b) in t.iter().zip(expect) {
            assert!((a - b).abs() < 1e-6, "{t:?}");
        }
        assert!(Normalization { mean: [0.0; 3], std: [1.0, 0.0, 1.0] }.check().is_err());
    }
}
