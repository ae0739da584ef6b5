//! [`OnnxDepth`]: a monocular depth network (MiDaS / DPT style, relative inverse depth) as a
//! [`DepthEstimator`].

use std::path::PathBuf;

use super::model::{
    check_image, dims_string, image_tensor, resize_map, InferenceStats, Input, Normalization, OnnxModel, SizePolicy,
};
use crate::io::image::RgbImage;
use crate::scene::{DepthEstimator, Disparity, SceneError};

/// The smallest disparity a normalised depth map holds (the reference's farthest plane, depth
/// 1000): the min-max normalisation maps the farthest pixel to 0, which would be infinitely far.
pub const DEFAULT_DISPARITY_FLOOR: f32 = 0.001;

/// Configuration of [`OnnxDepth`].
#[derive(Clone, Debug, PartialEq)]
pub struct OnnxDepthConfig {
    /// The `.onnx` file.
    pub model: PathBuf,
    /// The ONNX Runtime library; `None` = `ORT_DYLIB_PATH`.
    pub runtime_library: Option<PathBuf>,
    /// Input tensor, f32 `[1,3,h,w]` (default `image`).
    pub input: String,
    /// Output tensor, relative inverse depth `[1,h,w]` or `[1,1,h,w]` (default `depth`).
    pub output: String,
    /// Applied to the [0, 1] image before inference (default: none).
    pub normalization: Normalization,
    /// Network input size (default: the model's static size, else the image's).
    pub size: SizePolicy,
    /// Lower bound of the normalised disparity (default [`DEFAULT_DISPARITY_FLOOR`]).
    pub floor: f32,
    /// ONNX Runtime intra-op threads; 0 = ONNX Runtime's default (one per core).
    pub intra_threads: usize,
}

impl OnnxDepthConfig {
    /// The default contract (docs/models.md) for `model`.
    pub fn new(model: impl Into<PathBuf>) -> Self {
        OnnxDepthConfig {
            model: model.into(),
            runtime_library: None,
            input: "image".into(),
            output: "depth".into(),
            normalization: Normalization::IDENTITY,
            size: SizePolicy::Model,
            floor: DEFAULT_DISPARITY_FLOOR,
            intra_threads: 0,
        }
    }
}

/// A model output resized to the image, before normalisation.
#[derive(Clone, Debug, PartialEq)]
pub struct RawDepth {
    pub width: usize,
    pub height: usize,
    pub data: Vec<f32>,
}

/// A depth network through ONNX Runtime. Built once (loading the library if needed, checking
/// the tensors, one warm-up run) and shared by all workers; inferences on one instance are
/// serialised by a mutex (ONNX Runtime itself uses several threads per inference).
///
/// [`DepthEstimator::estimate`]: resize the image to the network size (bilinear, pixel centres
/// aligned), normalise, run, resize the output back to the image size (bilinear), then bring it
/// to the scene scale by min-max normalisation to [0, 1] (1 = nearest, as the reference's
/// disparity PNGs) with values below `floor` raised to it. A constant output becomes 1 (all
/// content at the nearest depth).
#[derive(Debug)]
pub struct OnnxDepth {
    config: OnnxDepthConfig,
    model: OnnxModel,
    static_size: Option<(usize, usize)>,
}

impl OnnxDepth {
    pub fn new(config: OnnxDepthConfig) -> Result<Self, SceneError> {
        let model = OnnxModel::open(
            "depth",
            &config.model,
            config.runtime_library.as_deref(),
            config.intra_threads,
            &config.normalization,
        )?;
        if !(0.0..1.0).contains(&config.floor) {
            return Err(model.err(format!("disparity floor {} is outside [0, 1)", config.floor)));
        }
        let input = model.image_input(&config.input, 3)?.clone();
        model.check_no_other_inputs(&[&config.input])?;
        model.output(&config.output, &[3, 4], "[1,h,w] or [1,1,h,w]")?;
        model.check_policy(&config.size, &input)?;
        let static_size = input.static_hw();
        let (w, h) = config.size.warmup_size(static_size);
        let depth = OnnxDepth { config, model, static_size };
        let dummy = RgbImage { width: w, height: h, data: vec![0.5; w * h * 3] };
        depth.infer(&dummy, true)?;
        Ok(depth)
    }

    pub fn config(&self) -> &OnnxDepthConfig {
        &self.config
    }

    /// Inference time so far (warm-up excluded).
    pub fn stats(&self) -> InferenceStats {
        self.model.stats()
    }

    pub fn reset_stats(&self) {
        self.model.reset_stats();
    }

    /// The network output resized to the image, not normalised.
    pub fn estimate_raw(&self, image: &RgbImage) -> Result<RawDepth, SceneError> {
        self.infer(image, false)
    }

    fn infer(&self, image: &RgbImage, warmup: bool) -> Result<RawDepth, SceneError> {
        check_image(&self.model, image)?;
        let (w, h) = self.config.size.network_size(image.width, image.height, self.static_size);
        let data = image_tensor(image, w, h, &self.config.normalization);
        let input = Input { name: &self.config.input, shape: [1, 3, h, w], data: &data };
        let out = self.model.run(&[input], &[&self.config.output], warmup)?.pop().expect("one output");
        let (oh, ow) = match out.dims.as_slice() {
            [1, oh, ow] | [1, 1, oh, ow] if *oh > 0 && *ow > 0 => (*oh, *ow),
            _ => {
                return Err(self.model.err(format!(
                    "output `{}` has shape {}; expected [1,h,w] or [1,1,h,w] (input was {w}x{h})",
                    self.config.output,
                    dims_string(&out.dims)
                )))
            }
        };
        let data = resize_map(&out.data, ow, oh, image.width, image.height);
        Ok(RawDepth { width: image.width, height: image.height, data })
    }
}

/// Min-max normalisation to [0, 1] with a floor (a constant map becomes all 1).
pub(crate) fn normalize_disparity(raw: &[f32], floor: f32) -> Vec<f32> {
    let (lo, hi) = raw.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &v| (lo.min(v), hi.max(v)));
    let range = hi - lo;
    if range <= 0.0 || !range.is_finite() {
        return vec![1.0; raw.len()];
    }
    raw.iter().map(|&v| ((v - lo) / range).clamp(floor, 1.0)).collect()
}

impl DepthEstimator for OnnxDepth {
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
        let contract = OnnxDepthConfig {
            model: std::path::PathBuf::new(),
            runtime_library: None,
            intra_threads: 0,
            ..self.config.clone()
        };
        self.model.identity(&format!("{contract:?}"))
    }

    fn estimate(&self, image: &RgbImage) -> Result<Disparity, SceneError> {
        let raw = self.infer(image, false)?;
        Ok(Disparity { width: raw.width, height: raw.height, data: normalize_disparity(&raw.data, self.config.floor) })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn normalisation_is_min_max_with_floor() {
        let d = normalize_disparity(&[2.0, 4.0, 3.0, 2.001], 0.001);
        assert_eq!(d[0], 0.001);
        assert_eq!(d[1], 1.0);
        assert!((d[2] - 0.5).abs() < 1e-6);
        assert!((d[3] - 0.001).abs() < 1e-6);
        assert_eq!(normalize_disparity(&[5.0, 5.0], 0.001), vec![1.0, 1.0]);
    }
}
