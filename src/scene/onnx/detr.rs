//! [`OnnxDetr`]: a DETR panoptic segmentation network (`DetrForSegmentation`, as the Hugging Face
//! exports have it: `pixel_values` -> `logits`, `pred_masks`) as a [`Segmenter`], with the
//! post-processing that turns its queries into mpiflow's instance masks ([`detr_instances`]).

use std::ops::RangeInclusive;
use std::path::PathBuf;

use super::model::{
    check_image, dims_string, image_tensor, resize_map, InferenceStats, Input, Normalization, OnnxModel, SizePolicy,
};
use crate::io::image::RgbImage;
use crate::raster::{Instance, InstanceMasks, MAX_INSTANCES};
use crate::scene::{SceneError, Segmenter};

/// Which of a DETR network's queries become moving instances (docs/models.md, "Which instances
/// move").
#[derive(Clone, Debug, PartialEq)]
pub struct DetrSelection {
    /// The class ids that are countable objects ("things"); every other class (stuff: sky,
    /// road, wall, ...) never moves. COCO panoptic: 1 to 90.
    pub things: RangeInclusive<u32>,
    /// A query is kept when its class probability (softmax over all classes, the no-object class
    /// included) is at least this (default 0.85, DETR's panoptic threshold).
    pub score_threshold: f32,
    /// An instance keeps at least this fraction of the image's pixels after the overlaps are
    /// resolved, else it is dropped (default 0.002).
    pub min_area: f32,
    /// An instance keeps at least this fraction of its own mask (probability >= 0.5) after the
    /// higher-scoring instances took theirs, else it is dropped as mostly hidden (default 0.8,
    /// DETR's panoptic overlap threshold).
    pub min_visible: f32,
    /// At most this many instances, the highest scores first (default 20, at most
    /// [`MAX_INSTANCES`]).
    pub max_instances: usize,
}

impl Default for DetrSelection {
    fn default() -> Self {
        DetrSelection { things: 1..=90, score_threshold: 0.85, min_area: 0.002, min_visible: 0.8, max_instances: 20 }
    }
}

impl DetrSelection {
    fn check(&self) -> Result<(), String> {
        let unit = |v: f32| v.is_finite() && (0.0..=1.0).contains(&v);
        if !unit(self.score_threshold) || !unit(self.min_area) || !unit(self.min_visible) {
            return Err(format!(
                "score_threshold {}, min_area {} and min_visible {} must lie in [0, 1]",
                self.score_threshold, self.min_area, self.min_visible
            ));
        }
        if self.max_instances > MAX_INSTANCES {
            return Err(format!("max_instances {} exceeds {MAX_INSTANCES}", self.max_instances));
        }
        Ok(())
    }
}

/// The network outputs of one image, batch dimension dropped.
#[derive(Clone, Debug, PartialEq)]
pub struct DetrOutputs {
    /// `[Q, C + 1]` class logits per query; the last class is "no object".
    pub logits: Vec<f32>,
    pub classes: usize,
    /// `[Q, mh, mw]` mask logits per query (sigmoid = probability).
    pub masks: Vec<f32>,
    pub mask_width: usize,
    pub mask_height: usize,
}

impl DetrOutputs {
    pub fn queries(&self) -> usize {
        self.logits.len() / self.classes.max(1)
    }
}

fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// A query's class: the argmax of the softmax over all classes and its probability.
fn best_class(logits: &[f32]) -> (usize, f32) {
    let (mut best, mut max) = (0, f32::NEG_INFINITY);
    for (c, &v) in logits.iter().enumerate() {
        if v > max {
            (best, max) = (c, v);
        }
    }
    let sum: f64 = logits.iter().map(|&v| f64::from(v - max).exp()).sum();
    (best, (1.0 / sum) as f32)
}

/// DETR's queries to instance masks on a `width x height` image:
///
/// 1. each query's class is the argmax of the softmax over its logits; queries whose class is
///    the no-object class (the last), a class outside `things`, or whose probability is below
///    `score_threshold` are dropped;
/// 2. the rest, by decreasing score (ties: query order), get their mask logits resized to the
///    image (bilinear) and a sigmoid: the mask probability;
/// 3. overlaps: each pixel belongs to the highest-scoring kept instance whose probability there
///    is >= 0.5; an instance that keeps less than `min_visible` of its own mask, or less than
///    `min_area` of the image, is dropped and claims nothing (a lower-scoring one may take its
///    pixels);
/// 4. each kept instance's mask is its probability on its own pixels and on the pixels no
///    instance claims (the soft fringe below 0.5), 0 on another instance's pixels; ids 1, 2, ...
///    in score order, the class as the category, at most `max_instances`.
///
/// No query left is a valid result: no instance, the photo's samples move the camera only.
pub fn detr_instances(out: &DetrOutputs, width: usize, height: usize, sel: &DetrSelection) -> InstanceMasks {
    let mut result = InstanceMasks::new(width, height);
    let (classes, queries) = (out.classes, out.queries());
    let plane = out.mask_width * out.mask_height;
    if classes < 2 || plane == 0 || width == 0 || height == 0 {
        return result;
    }
    let mut candidates: Vec<(usize, u32, f32)> = (0..queries)
        .filter_map(|q| {
            let (class, p) = best_class(&out.logits[q * classes..][..classes]);
            let label = u32::try_from(class).ok()?;
            (class != classes - 1 && sel.things.contains(&label) && p >= sel.score_threshold).then_some((q, label, p))
        })
        .collect();
    candidates.sort_by(|a, b| b.2.total_cmp(&a.2).then(a.0.cmp(&b.0)));
    let pixels = width * height;
    let min_pixels = f64::from(sel.min_area) * pixels as f64;
    // the instance (index into `kept`, + 1) that owns each pixel; 0 = none
    let mut owner = vec![0u16; pixels];
    let mut kept: Vec<(u32, f32, Vec<f32>)> = Vec::new();
    for (q, label, score) in candidates {
        if kept.len() >= sel.max_instances {
            break;
        }
        let mut prob = resize_map(&out.masks[q * plane..][..plane], out.mask_width, out.mask_height, width, height);
        for v in &mut prob {
            *v = sigmoid(*v);
        }
        let own = prob.iter().filter(|&&v| v >= 0.5).count();
        let free = prob.iter().zip(&owner).filter(|(&v, &o)| v >= 0.5 && o == 0).count();
        if own == 0 || (free as f64) < min_pixels || (free as f64) < f64::from(sel.min_visible) * own as f64 {
            continue;
        }
        let n = u16::try_from(kept.len() + 1).expect("at most MAX_INSTANCES instances");
        for (o, &v) in owner.iter_mut().zip(&prob) {
            if v >= 0.5 && *o == 0 {
                *o = n;
            }
        }
        kept.push((label, score, prob));
    }
    for (i, (label, score, mut prob)) in kept.into_iter().enumerate() {
        let n = i as u16 + 1;
        for (v, &o) in prob.iter_mut().zip(&owner) {
            // its own pixels and the unclaimed fringe keep the probability; others' pixels are 0
            if o != n && (o != 0 || *v >= 0.5) {
                *v = 0.0;
            }
        }
        let mut instance = Instance::new(n.into(), score, prob);
        instance.category = Some(label);
        result.masks.push(instance);
    }
    result
}

/// Configuration of [`OnnxDetr`].
#[derive(Clone, Debug, PartialEq)]
pub struct OnnxDetrConfig {
    /// The `.onnx` file.
    pub model: PathBuf,
    /// The ONNX Runtime library; `None` = `ORT_DYLIB_PATH`.
    pub runtime_library: Option<PathBuf>,
    /// Input tensor, f32 `[1,3,h,w]` (default `pixel_values`).
    pub input: String,
    /// Class logits `[1,Q,C+1]` (default `logits`).
    pub logits_output: String,
    /// Mask logits `[1,Q,h',w']` (default `pred_masks`).
    pub masks_output: String,
    /// Applied to the [0, 1] image before inference (default: ImageNet's mean and std, DETR's).
    pub normalization: Normalization,
    /// Network input size (default: the longer side 640, multiples of 32).
    pub size: SizePolicy,
    pub selection: DetrSelection,
    /// ONNX Runtime intra-op threads; 0 = ONNX Runtime's default (one per core).
    pub intra_threads: usize,
}

impl OnnxDetrConfig {
    /// The Hugging Face export's contract for `model`.
    pub fn new(model: impl Into<PathBuf>) -> Self {
        OnnxDetrConfig {
            model: model.into(),
            runtime_library: None,
            input: "pixel_values".into(),
            logits_output: "logits".into(),
            masks_output: "pred_masks".into(),
            normalization: Normalization::IMAGENET,
            size: SizePolicy::LongSide { side: 640, multiple: 32 },
            selection: DetrSelection::default(),
            intra_threads: 0,
        }
    }
}

/// A DETR panoptic network through ONNX Runtime; see [`OnnxDepth`](super::OnnxDepth) for the
/// life cycle. [`Segmenter::segment`]: the image resized to the network size and normalised,
/// run, and its queries turned into instances by [`detr_instances`].
#[derive(Debug)]
pub struct OnnxDetr {
    config: OnnxDetrConfig,
    model: OnnxModel,
    static_size: Option<(usize, usize)>,
}

impl OnnxDetr {
    pub fn new(config: OnnxDetrConfig) -> Result<Self, SceneError> {
        let model = OnnxModel::open(
            "segmentation",
            &config.model,
            config.runtime_library.as_deref(),
            config.intra_threads,
            &config.normalization,
        )?;
        config.selection.check().map_err(|m| model.err(m))?;
        let input = model.image_input(&config.input, 3)?.clone();
        model.check_no_other_inputs(&[&config.input])?;
        model.output(&config.logits_output, &[3], "[1,Q,C+1]")?;
        model.output(&config.masks_output, &[4], "[1,Q,h,w]")?;
        model.check_policy(&config.size, &input)?;
        let static_size = input.static_hw();
        let (w, h) = config.size.warmup_size(static_size);
        let seg = OnnxDetr { config, model, static_size };
        let dummy = RgbImage { width: w, height: h, data: vec![0.5; w * h * 3] };
        seg.run(&dummy, true)?;
        Ok(seg)
    }

    pub fn config(&self) -> &OnnxDetrConfig {
        &self.config
    }

    /// Inference time so far (warm-up excluded).
    pub fn stats(&self) -> InferenceStats {
        self.model.stats()
    }

    /// The network's outputs for `image` (checked shapes, batch dimension dropped).
    pub fn outputs(&self, image: &RgbImage) -> Result<DetrOutputs, SceneError> {
        self.run(image, false)
    }

    fn run(&self, image: &RgbImage, warmup: bool) -> Result<DetrOutputs, SceneError> {
        check_image(&self.model, image)?;
        let (w, h) = self.config.size.network_size(image.width, image.height, self.static_size);
        let data = image_tensor(image, w, h, &self.config.normalization);
        let input = Input { name: &self.config.input, shape: [1, 3, h, w], data: &data };
        let names = [self.config.logits_output.as_str(), self.config.masks_output.as_str()];
        let mut outs = self.model.run(&[input], &names, warmup)?.into_iter();
        let (logits, masks) = (outs.next().expect("logits"), outs.next().expect("masks"));
        let (q, classes) = match logits.dims.as_slice() {
            [1, q, c] if *c >= 2 => (*q, *c),
            _ => {
                return Err(self.model.err(format!(
                    "output `{}` has shape {}; expected [1,Q,C+1] with at least one class and the no-object class",
                    self.config.logits_output,
                    dims_string(&logits.dims)
                )))
            }
        };
        let (mh, mw) = match masks.dims.as_slice() {
            [1, mq, mh, mw] if *mq == q && *mh > 0 && *mw > 0 => (*mh, *mw),
            _ => {
                return Err(self.model.err(format!(
                    "output `{}` has shape {}; expected [1,{q},h,w] to match `{}` {}",
                    self.config.masks_output,
                    dims_string(&masks.dims),
                    self.config.logits_output,
                    dims_string(&logits.dims)
                )))
            }
        };
        Ok(DetrOutputs { logits: logits.data, classes, masks: masks.data, mask_width: mw, mask_height: mh })
    }
}

impl Segmenter for OnnxDetr {
    fn inference_runs(&self) -> Option<u64> {
        Some(self.model.stats().runs)
    }

    fn content_hash(&self) -> Option<u64> {
        Some(self.model.content_hash())
    }

    fn name(&self) -> String {
        self.model.short_name()
    }

    /// The file's content hash and the contract (tensor names, normalisation, size, selection);
    /// not the path, threads or runtime library, which change no output.
    fn identity(&self) -> String {
        let contract =
            OnnxDetrConfig { model: PathBuf::new(), runtime_library: None, intra_threads: 0, ..self.config.clone() };
        self.model.identity(&format!("detr {contract:?}"))
    }

    fn segment(&self, image: &RgbImage) -> Result<InstanceMasks, SceneError> {
        let out = self.run(image, false)?;
        Ok(detr_instances(&out, image.width, image.height, &self.config.selection))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Three classes (0 = a stuff class outside `things`, 1 and 2 things) and no-object (3).
    fn sel() -> DetrSelection {
        DetrSelection { things: 1..=2, ..DetrSelection::default() }
    }

    /// Query logits that give `class` the probability `p` and share the rest evenly.
    fn logits_for(class: usize, p: f32, classes: usize) -> Vec<f32> {
        let rest = (1.0 - p) / (classes - 1) as f32;
        (0..classes).map(|c| if c == class { p.ln() } else { rest.ln() }).collect()
    }

    /// Mask logits on an 8 x 4 grid: +10 inside the columns `x0..x1`, -10 outside.
    fn columns(x0: usize, x1: usize) -> Vec<f32> {
        (0..32).map(|i| if (x0..x1).contains(&(i % 8)) { 10.0 } else { -10.0 }).collect()
    }

    fn outputs(queries: &[(usize, f32, Vec<f32>)]) -> DetrOutputs {
        DetrOutputs {
            logits: queries.iter().flat_map(|(c, p, _)| logits_for(*c, *p, 4)).collect(),
            classes: 4,
            masks: queries.iter().flat_map(|(_, _, m)| m.clone()).collect(),
            mask_width: 8,
            mask_height: 4,
        }
    }

    fn area(m: &Instance) -> usize {
        m.mask.iter().filter(|&&v| v >= 0.5).count()
    }

    #[test]
    fn queries_below_the_threshold_or_of_no_object_are_dropped() {
        let out = outputs(&[(1, 0.9, columns(0, 2)), (2, 0.8, columns(2, 4)), (3, 0.99, columns(4, 6))]);
        let m = detr_instances(&out, 8, 4, &sel());
        assert_eq!(m.masks.len(), 1, "{:?}", m.masks.iter().map(|i| i.score).collect::<Vec<_>>());
        let i = &m.masks[0];
        assert_eq!((i.id, i.category), (1, Some(1)));
        assert!((i.score - 0.9).abs() < 1e-5, "{}", i.score);
        assert_eq!(area(i), 8);
        let lower = DetrSelection { score_threshold: 0.75, ..sel() };
        assert_eq!(detr_instances(&out, 8, 4, &lower).masks.len(), 2, "the 0.8 query passes a 0.75 threshold");
    }

    #[test]
    fn only_thing_classes_move() {
        let out = outputs(&[(0, 0.99, columns(0, 4)), (2, 0.95, columns(4, 8))]);
        let m = detr_instances(&out, 8, 4, &sel());
        assert_eq!(m.masks.iter().map(|i| i.category).collect::<Vec<_>>(), [Some(2)]);
        let all = DetrSelection { things: 0..=2, ..sel() };
        assert_eq!(detr_instances(&out, 8, 4, &all).masks.len(), 2);
    }

    #[test]
    fn overlapping_instances_give_each_pixel_to_the_higher_score() {
        // the second query (higher score) covers columns 2..6, the first 0..4; the third lies
        // mostly under the second and is dropped as hidden
        let out = outputs(&[(1, 0.9, columns(0, 4)), (2, 0.97, columns(2, 6)), (1, 0.88, columns(3, 6))]);
        let m = detr_instances(&out, 8, 4, &DetrSelection { min_visible: 0.5, ..sel() });
        assert_eq!(m.masks.len(), 2);
        let (a, b) = (&m.masks[0], &m.masks[1]);
        assert_eq!((a.id, a.category, b.id, b.category), (1, Some(2), 2, Some(1)), "ids in score order");
        assert_eq!((area(a), area(b)), (16, 8), "columns 2..6 to the first, 0..2 to the second");
        assert!(a.mask.iter().zip(&b.mask).all(|(x, y)| !(*x >= 0.5 && *y >= 0.5)), "disjoint");
        // at the default 0.8 the first query keeps 2 of its 4 columns: dropped
        let strict = detr_instances(&out, 8, 4, &sel());
        assert_eq!(strict.masks.iter().map(|i| i.category).collect::<Vec<_>>(), [Some(2)]);
        // a dropped instance claims nothing: the third query (columns 3..6) is all under the
        // first, and the first one's columns 0..2 stay free
        assert!(strict.masks[0].mask.iter().enumerate().all(|(i, &v)| (v >= 0.5) == (2..6).contains(&(i % 8))));
    }

    #[test]
    fn small_instances_are_dropped_and_masks_are_resized_to_the_image() {
        let out = outputs(&[(1, 0.9, columns(0, 1)), (2, 0.9, columns(4, 8))]);
        // one column of eight is 1/8 of the image
        let m = detr_instances(&out, 16, 8, &DetrSelection { min_area: 0.2, ..sel() });
        assert_eq!(m.masks.len(), 1);
        let i = &m.masks[0];
        assert_eq!((i.category, i.mask.len(), area(i)), (Some(2), 128, 64));
        assert!(i.mask.iter().all(|v| v.is_finite() && (0.0..=1.0).contains(v)));
        let kept = detr_instances(&out, 16, 8, &DetrSelection { min_area: 0.1, ..sel() });
        assert_eq!(kept.masks.len(), 2);
    }

    #[test]
    fn no_query_left_is_no_instance() {
        let none = outputs(&[(3, 0.99, columns(0, 8)), (0, 0.99, columns(0, 8)), (1, 0.3, columns(0, 8))]);
        let m = detr_instances(&none, 8, 4, &sel());
        assert_eq!((m.width, m.height, m.masks.len()), (8, 4, 0));
        let empty = DetrOutputs { logits: vec![], classes: 4, masks: vec![], mask_width: 8, mask_height: 4 };
        assert!(detr_instances(&empty, 8, 4, &sel()).masks.is_empty());
        // a mask that is nowhere >= 0.5 is no instance either
        let blank = outputs(&[(1, 0.99, vec![-10.0; 32])]);
        assert!(detr_instances(&blank, 8, 4, &sel()).masks.is_empty());
    }

    #[test]
    fn at_most_max_instances_the_best_first() {
        let queries: Vec<_> = (0..4).map(|k| (1, 0.86 + 0.03 * k as f32, columns(2 * k, 2 * k + 2))).collect();
        let m = detr_instances(&outputs(&queries), 8, 4, &DetrSelection { max_instances: 2, ..sel() });
        let scores: Vec<f32> = m.masks.iter().map(|i| i.score).collect();
        assert_eq!(scores.len(), 2);
        assert!((scores[0] - 0.95).abs() < 1e-5 && (scores[1] - 0.92).abs() < 1e-5, "{scores:?}");
    }

    #[test]
    fn extreme_logits_give_finite_scores() {
        let (c, p) = best_class(&[1e30, -1e30, 0.0]);
        assert_eq!(c, 0);
        assert!(p.is_finite() && (p - 1.0).abs() < 1e-6);
        assert!(DetrSelection { min_area: f32::NAN, ..sel() }.check().is_err());
    }
}
