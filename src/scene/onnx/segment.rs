//! [`OnnxSegmenter`]: an instance segmentation network (torchvision Mask R-CNN export style) as
//! a [`Segmenter`].

use std::path::PathBuf;

use super::model::{
    check_image, dims_string, image_tensor, resize_map, InferenceStats, Input, Normalization, OnnxModel, SizePolicy,
};
use crate::io::image::RgbImage;
use crate::raster::{Instance, InstanceMasks, MAX_INSTANCES};
use crate::scene::{SceneError, Segmenter};

/// Configuration of [`OnnxSegmenter`].
#[derive(Clone, Debug, PartialEq)]
pub struct OnnxSegmenterConfig {
    /// The `.onnx` file.
    pub model: PathBuf,
    /// The ONNX Runtime library; `None` = `ORT_DYLIB_PATH`.
    pub runtime_library: Option<PathBuf>,
    /// Input tensor, f32 `[1,3,h,w]` (default `image`).
    pub input: String,
    /// Mask probabilities `[K,1,h,w]` (or `[K,h,w]`), K >= 0 (default `masks`).
    pub masks_output: String,
    /// Scores `[K]` (default `scores`).
    pub scores_output: String,
    /// Class labels `[K]` (integer or float), stored as the instances' category when the model
    /// has an output of this name (default `labels`).
    pub labels_output: Option<String>,
    /// Instances with a score below this are dropped (default 0.5).
    pub score_threshold: f32,
    /// At most this many instances, the highest scores first (default 100, at most
    /// [`MAX_INSTANCES`]).
    pub max_instances: usize,
    /// Applied to the [0, 1] image before inference (default: none).
    pub normalization: Normalization,
    /// Network input size (default: the model's static size, else the image's).
    pub size: SizePolicy,
    /// ONNX Runtime intra-op threads; 0 = ONNX Runtime's default (one per core).
    pub intra_threads: usize,
}

impl OnnxSegmenterConfig {
    /// The default contract (docs/models.md) for `model`.
    pub fn new(model: impl Into<PathBuf>) -> Self {
        OnnxSegmenterConfig {
            model: model.into(),
            runtime_library: None,
            input: "image".into(),
            masks_output: "masks".into(),
            scores_output: "scores".into(),
            labels_output: Some("labels".into()),
            score_threshold: 0.5,
            max_instances: 100,
            normalization: Normalization::IDENTITY,
            size: SizePolicy::Model,
            intra_threads: 0,
        }
    }
}

/// An instance segmentation network through ONNX Runtime; see
/// [`OnnxDepth`](super::OnnxDepth) for the life cycle.
///
/// [`Segmenter::segment`]: image resized to the network size, run; instances with
/// `score >= score_threshold` kept, ordered by decreasing score (ties: model order), at most
/// `max_instances`, given ids 1, 2, ... in that order; each mask resized to the image (bilinear)
/// and clamped to [0, 1]. Zero instances is a valid result.
#[derive(Debug)]
pub struct OnnxSegmenter {
    config: OnnxSegmenterConfig,
    model: OnnxModel,
    static_size: Option<(usize, usize)>,
    labels_output: Option<String>,
}

impl OnnxSegmenter {
    pub fn new(config: OnnxSegmenterConfig) -> Result<Self, SceneError> {
        let model = OnnxModel::open(
            "segmentation",
            &config.model,
            config.runtime_library.as_deref(),
            config.intra_threads,
            &config.normalization,
        )?;
        if !config.score_threshold.is_finite() {
            return Err(model.err(format!("invalid score threshold {}", config.score_threshold)));
        }
        if config.max_instances > MAX_INSTANCES {
            return Err(model.err(format!("max_instances {} exceeds {MAX_INSTANCES}", config.max_instances)));
        }
        let input = model.image_input(&config.input, 3)?.clone();
        model.check_no_other_inputs(&[&config.input])?;
        model.output(&config.masks_output, &[3, 4], "[K,1,h,w] or [K,h,w]")?;
        model.output(&config.scores_output, &[1], "[K]")?;
        let labels_output = match &config.labels_output {
            Some(name) if model.has_output(name) => {
                model.output(name, &[1], "[K]")?;
                Some(name.clone())
            }
            _ => None,
        };
        model.check_policy(&config.size, &input)?;
        let static_size = input.static_hw();
        let (w, h) = config.size.warmup_size(static_size);
        let seg = OnnxSegmenter { config, model, static_size, labels_output };
        let dummy = RgbImage { width: w, height: h, data: vec![0.5; w * h * 3] };
        seg.infer(&dummy, true)?;
        Ok(seg)
    }

    pub fn config(&self) -> &OnnxSegmenterConfig {
        &self.config
    }

    /// Inference time so far (warm-up excluded).
    pub fn stats(&self) -> InferenceStats {
        self.model.stats()
    }

    pub fn reset_stats(&self) {
        self.model.reset_stats();
    }

    fn infer(&self, image: &RgbImage, warmup: bool) -> Result<InstanceMasks, SceneError> {
        check_image(&self.model, image)?;
        let (iw, ih) = (image.width, image.height);
        let (w, h) = self.config.size.network_size(iw, ih, self.static_size);
        let data = image_tensor(image, w, h, &self.config.normalization);
        let input = Input { name: &self.config.input, shape: [1, 3, h, w], data: &data };
        let mut names: Vec<&str> = vec![&self.config.masks_output, &self.config.scores_output];
        if let Some(l) = &self.labels_output {
            names.push(l);
        }
        let mut outs = self.model.run(&[input], &names, warmup)?.into_iter();
        let (masks, scores) = (outs.next().expect("masks"), outs.next().expect("scores"));
        let labels = outs.next();
        let (k, mh, mw) = match masks.dims.as_slice() {
            [k, 1, mh, mw] | [k, mh, mw] => (*k, *mh, *mw),
            _ => {
                return Err(self.model.err(format!(
                    "output `{}` has shape {}; expected [K,1,h,w] or [K,h,w]",
                    self.config.masks_output,
                    dims_string(&masks.dims)
                )))
            }
        };
        if k > 0 && (mh == 0 || mw == 0) {
            return Err(self.model.err(format!(
                "output `{}` has empty masks: shape {}",
                self.config.masks_output,
                dims_string(&masks.dims)
            )));
        }
        if scores.dims != [k] {
            return Err(self.model.err(format!(
                "output `{}` has shape {}; expected [{k}] to match `{}` {}",
                self.config.scores_output,
                dims_string(&scores.dims),
                self.config.masks_output,
                dims_string(&masks.dims)
            )));
        }
        if let (Some(l), Some(name)) = (&labels, &self.labels_output) {
            if l.dims != [k] {
                return Err(self
                    .model
                    .err(format!("output `{name}` has shape {}; expected [{k}]", dims_string(&l.dims))));
            }
        }
        let mut order: Vec<usize> = (0..k).filter(|&i| scores.data[i] >= self.config.score_threshold).collect();
        order.sort_by(|&a, &b| scores.data[b].total_cmp(&scores.data[a]));
        order.truncate(self.config.max_instances);
        let plane = mh * mw;
        let mut result = InstanceMasks::new(iw, ih);
        for (n, &i) in order.iter().enumerate() {
            let mut mask = resize_map(&masks.data[i * plane..][..plane], mw, mh, iw, ih);
            for v in &mut mask {
                *v = v.clamp(0.0, 1.0);
            }
            let mut instance = Instance::new(n as u32 + 1, scores.data[i], mask);
            if let Some(l) = &labels {
                let c = l.data[i];
                if c >= 0.0 && c <= u32::MAX as f32 {
                    instance.category = Some(c as u32);
                }
            }
            result.masks.push(instance);
        }
        Ok(result)
    }
}

impl Segmenter for OnnxSegmenter {
    fn inference_runs(&self) -> Option<u64> {
        Some(self.model.stats().runs)
    }

    fn content_hash(&self) -> Option<u64> {
        Some(self.model.content_hash())
    }

    fn name(&self) -> String {
        self.model.short_name()
    }

    /// The file's content hash and the contract (tensor names, normalisation, sizes,
    /// thresholds); not the path, threads or runtime library, which change no output.
    fn identity(&self) -> String {
        let contract = OnnxSegmenterConfig {
            model: std::path::PathBuf::new(),
            runtime_library: None,
            intra_threads: 0,
            ..self.config.clone()
        };
        self.model.identity(&format!("{contract:?}"))
    }

    fn segment(&self, image: &RgbImage) -> Result<InstanceMasks, SceneError> {
        self.infer(image, false)
    }
}
