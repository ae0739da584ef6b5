//! [`OnnxMpi`]: an MPI network (AdaMPI style) as an [`MpiBuilder`].

use std::borrow::Cow;
use std::path::PathBuf;

use super::model::{
    check_image, dims_string, image_tensor, resize_map, InferenceStats, Input, Normalization, OnnxModel, SizePolicy,
};
use crate::geometry::Intrinsics;
use crate::io::image::RgbImage;
use crate::mpi::Mpi;
use crate::scene::{Disparity, MpiBuilder, SceneError};

/// Configuration of [`OnnxMpi`].
#[derive(Clone, Debug, PartialEq)]
pub struct OnnxMpiConfig {
    /// The `.onnx` file.
    pub model: PathBuf,
    /// The ONNX Runtime library; `None` = `ORT_DYLIB_PATH`.
    pub runtime_library: Option<PathBuf>,
    /// Image input, f32 `[1,3,H,W]` in [0, 1] (default `image`).
    pub image_input: String,
    /// Disparity input, f32 `[1,1,H,W]`, the scene-scale disparity in [0, 1] (default `disparity`).
    pub disparity_input: String,
    /// MPI output, `[1,S,4,H,W]`: rgb in [0, 1], density sigma >= 0 (default `mpi`).
    pub output: String,
    /// Plane disparities output `[1,S]` or `[S]`, near to far, used when the model has an
    /// output of this name (default `plane_disparity`); otherwise, or with `None`, the planes
    /// are at the public generator's fixed `linspace(1.0, 0.001, S+2)[1:-1]`.
    pub plane_disparity_output: Option<String>,
    /// Applied to the image before inference (default: none; the disparity is never changed).
    pub normalization: Normalization,
    /// Network input size (default: the model's static size, else the image's; AdaMPI exported
    /// with dynamic size wants `MultipleOf(128)`).
    pub size: SizePolicy,
    /// ONNX Runtime intra-op threads; 0 = ONNX Runtime's default (one per core).
    pub intra_threads: usize,
}

impl OnnxMpiConfig {
    /// The default contract (docs/models.md) for `model`.
    pub fn new(model: impl Into<PathBuf>) -> Self {
        OnnxMpiConfig {
            model: model.into(),
            runtime_library: None,
            image_input: "image".into(),
            disparity_input: "disparity".into(),
            output: "mpi".into(),
            plane_disparity_output: Some("plane_disparity".into()),
            normalization: Normalization::IDENTITY,
            size: SizePolicy::Model,
            intra_threads: 0,
        }
    }
}

/// An MPI network through ONNX Runtime; see [`OnnxDepth`](super::OnnxDepth) for the life cycle.
///
/// [`MpiBuilder::build`]: image and disparity resized to the network size (bilinear), run, every
/// plane channel resized back to the image size (bilinear), planes at the model's
/// `plane_disparity` (validated: finite, >= 0, strictly decreasing) or the fixed reference
/// disparities. Negative densities are an error (the contract says sigma >= 0). The intrinsics
/// are not used by the network and not stored in the MPI.
#[derive(Debug)]
pub struct OnnxMpi {
    config: OnnxMpiConfig,
    model: OnnxModel,
    static_size: Option<(usize, usize)>,
    planes_output: Option<String>,
}

impl OnnxMpi {
    pub fn new(config: OnnxMpiConfig) -> Result<Self, SceneError> {
        let model = OnnxModel::open(
            "MPI",
            &config.model,
            config.runtime_library.as_deref(),
            config.intra_threads,
            &config.normalization,
        )?;
        let image = model.image_input(&config.image_input, 3)?.clone();
        let disparity = model.image_input(&config.disparity_input, 1)?.clone();
        model.check_no_other_inputs(&[&config.image_input, &config.disparity_input])?;
        if let (Some(a), Some(b)) = (image.static_hw(), disparity.static_hw()) {
            if a != b {
                return Err(model.err(format!(
                    "inputs {} and {} declare different sizes",
                    image.describe(),
                    disparity.describe()
                )));
            }
        }
        model.output(&config.output, &[5], "[1,S,4,H,W]")?;
        let planes_output = match &config.plane_disparity_output {
            Some(name) if model.has_output(name) => {
                model.output(name, &[1, 2], "[1,S] or [S]")?;
                Some(name.clone())
            }
            _ => None,
        };
        model.check_policy(&config.size, &image)?;
        let static_size = image.static_hw().or(disparity.static_hw());
        let (w, h) = config.size.warmup_size(static_size);
        let mpi = OnnxMpi { config, model, static_size, planes_output };
        let dummy = RgbImage { width: w, height: h, data: vec![0.5; w * h * 3] };
        let disp = Disparity { width: w, height: h, data: vec![0.5; w * h] };
        mpi.infer(&dummy, &disp, true)?;
        Ok(mpi)
    }

    pub fn config(&self) -> &OnnxMpiConfig {
        &self.config
    }

    /// Whether plane disparities come from the model (else the fixed reference ones).
    pub fn planes_from_model(&self) -> bool {
        self.planes_output.is_some()
    }

    /// Inference time so far (warm-up excluded).
    pub fn stats(&self) -> InferenceStats {
        self.model.stats()
    }

    pub fn reset_stats(&self) {
        self.model.reset_stats();
    }

    fn infer(&self, image: &RgbImage, disparity: &Disparity, warmup: bool) -> Result<Mpi, SceneError> {
        check_image(&self.model, image)?;
        if (disparity.width, disparity.height) != (image.width, image.height)
            || disparity.data.len() != disparity.width * disparity.height
        {
            return Err(SceneError::Invalid(format!(
                "MPI model {}: disparity {}x{} ({} values) does not match the image {}x{}",
                self.model.path().display(),
                disparity.width,
                disparity.height,
                disparity.data.len(),
                image.width,
                image.height
            )));
        }
        let (iw, ih) = (image.width, image.height);
        let (w, h) = self.config.size.network_size(iw, ih, self.static_size);
        let img = image_tensor(image, w, h, &self.config.normalization);
        let disp = resize_map(&disparity.data, iw, ih, w, h);
        let inputs = [
            Input { name: &self.config.image_input, shape: [1, 3, h, w], data: &img },
            Input { name: &self.config.disparity_input, shape: [1, 1, h, w], data: &disp },
        ];
        let mut names: Vec<&str> = vec![&self.config.output];
        if let Some(p) = &self.planes_output {
            names.push(p);
        }
        let mut outs = self.model.run(&inputs, &names, warmup)?.into_iter();
        let out = outs.next().expect("mpi output");
        let (s, oh, ow) = match out.dims.as_slice() {
            [1, s, 4, oh, ow] if *s > 0 && *oh > 0 && *ow > 0 => (*s, *oh, *ow),
            _ => {
                return Err(self.model.err(format!(
                    "output `{}` has shape {}; expected [1,S,4,H,W] with S >= 1 (input was {w}x{h})",
                    self.config.output,
                    dims_string(&out.dims)
                )))
            }
        };
        let disparities = match (outs.next(), &self.planes_output) {
            (Some(p), Some(name)) => {
                let ok = matches!(p.dims.as_slice(), [1, n] | [n] if *n == s);
                if !ok {
                    return Err(self.model.err(format!(
                        "output `{name}` has shape {}; expected [1,{s}] or [{s}] to match the {s} planes of `{}`",
                        dims_string(&p.dims),
                        self.config.output
                    )));
                }
                p.data.iter().map(|&d| d as f64).collect()
            }
            _ => Mpi::reference_disparities(s),
        };
        let mut mpi = Mpi::new(iw, ih, disparities, 0);
        if let Err(e) = mpi.validate() {
            let source =
                self.planes_output.as_deref().map_or("the fixed plane disparities".into(), |n| format!("output `{n}`"));
            return Err(self.model.err(format!("{source}: {e}")));
        }
        let plane = ow * oh;
        for si in 0..s {
            let src = &out.data[si * 4 * plane..][..4 * plane];
            let min_sigma = src[3 * plane..].iter().copied().fold(f32::INFINITY, f32::min);
            if min_sigma < 0.0 {
                return Err(self.model.err(format!(
                    "output `{}` has negative density (sigma, channel 3) on plane {si}: minimum {min_sigma}",
                    self.config.output
                )));
            }
            let ch: Vec<Cow<'_, [f32]>> = src
                .chunks_exact(plane)
                .map(
                    |c| if (ow, oh) == (iw, ih) { Cow::Borrowed(c) } else { Cow::Owned(resize_map(c, ow, oh, iw, ih)) },
                )
                .collect();
            for (i, px) in mpi.plane_rgba_mut(si).chunks_exact_mut(4).enumerate() {
                px.copy_from_slice(&[ch[0][i], ch[1][i], ch[2][i], ch[3][i]]);
            }
        }
        Ok(mpi)
    }
}

impl MpiBuilder for OnnxMpi {
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
        let contract = OnnxMpiConfig {
            model: std::path::PathBuf::new(),
            runtime_library: None,
            intra_threads: 0,
            ..self.config.clone()
        };
        self.model.identity(&format!("{contract:?}"))
    }

    fn build(&self, image: &RgbImage, disparity: &Disparity, _k: &Intrinsics) -> Result<Mpi, SceneError> {
        self.infer(image, disparity, false)
    }
}
