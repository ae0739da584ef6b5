//! Request validation: every field of a request checked and turned into what the domain needs;
//! each refusal is INVALID_ARGUMENT with a message that starts with the field's name.

use super::config::ServiceConfig;
use super::dataset::Overrides;
use super::encode::{wants_backward, wants_occlusion, CropSpec, OutputSpec, DEFAULT_FIELDS};
use super::error::ServiceError;
use super::pb;
use crate::failure::{echo, printable, ECHO_CHARS};
use crate::render::Resample;
use crate::sample::augment::Augment;
use crate::sample::config::SampleConfig;
use crate::sample::motion::{MotionPreset, MotionRanges};

/// Largest `world_size` accepted.
pub const MAX_WORLD_SIZE: u32 = 1 << 20;

/// Most indices one GetSamples request may ask for (`Limits.max_indices`).
pub const MAX_INDICES: usize = 256;

fn invalid(field: &'static str, message: impl Into<String>) -> ServiceError {
    ServiceError::invalid(field, message)
}

/// The fields, flow dtype, compression and crop of a request.
pub fn output_spec(
    fields: &[i32],
    flow_dtype: i32,
    compression: i32,
    crop: Option<&pb::OutputCrop>,
    config: &ServiceConfig,
) -> Result<OutputSpec, ServiceError> {
    let mut list = Vec::with_capacity(fields.len());
    for &f in fields {
        let field = pb::Field::try_from(f).map_err(|_| invalid("fields", format!("unknown field value {f}")))?;
        if field == pb::Field::Unspecified {
            return Err(invalid("fields", "FIELD_UNSPECIFIED is not a field"));
        }
        list.push(field);
    }
    if list.is_empty() {
        list = DEFAULT_FIELDS.to_vec();
    }
    list.sort_by_key(|f| *f as i32);
    list.dedup();
    let flow_f16 = match pb::FlowDtype::try_from(flow_dtype) {
        Ok(pb::FlowDtype::Unspecified | pb::FlowDtype::F32) => false,
        Ok(pb::FlowDtype::F16) => true,
        Err(_) => return Err(invalid("flow_dtype", format!("unknown value {flow_dtype}"))),
    };
    let lz4 = match pb::Compression::try_from(compression) {
        Ok(pb::Compression::Unspecified | pb::Compression::None) => false,
        Ok(pb::Compression::Lz4) => true,
        Err(_) => return Err(invalid("compression", format!("unknown value {compression}"))),
    };
    let crop = match crop {
        None => None,
        Some(c) => {
            let random = match pb::CropMode::try_from(c.mode) {
                Ok(pb::CropMode::Unspecified | pb::CropMode::Center) => false,
                Ok(pb::CropMode::Random) => true,
                Err(_) => return Err(invalid("crop.mode", format!("unknown value {}", c.mode))),
            };
            let side = config.max_image_side;
            if c.width > side {
                return Err(invalid("crop.width", format!("{} is larger than the largest image side {side}", c.width)));
            }
            if c.height > side {
                return Err(invalid(
                    "crop.height",
                    format!("{} is larger than the largest image side {side}", c.height),
                ));
            }
            (c.width != 0 || c.height != 0).then_some(CropSpec { width: c.width, height: c.height, random })
        }
    };
    Ok(OutputSpec { fields: list, flow_f16, lz4, crop, augment: None })
}

/// The `augment` of a request, put into `out`: a preset name or JSON (docs/augment.md); errors
/// name the JSON key (`augment.crop`, ...). A request crop naming both sides replaces the
/// augmentation's crop (one side alone is refused: the other would depend on the drawn scale);
/// the augmentation then makes the crop, so `out.crop` is cleared.
pub fn augment(text: &str, out: &mut OutputSpec, config: &ServiceConfig) -> Result<(), ServiceError> {
    if text.trim().is_empty() {
        return Ok(());
    }
    if text.len() > 64 << 10 {
        return Err(invalid("augment", "longer than 64 KiB"));
    }
    let mut a = Augment::parse(text).map_err(|e| invalid(e.field, e.reason))?;
    if let Some(c) = out.crop.take() {
        if c.width == 0 || c.height == 0 {
            return Err(invalid(
                "crop",
                format!(
                    "{}x{}: with augment, give both sides (or none, for the augmentation's crop)",
                    c.width, c.height
                ),
            ));
        }
        a = a.with_crop((c.width, c.height));
    }
    if let Some((w, h)) = a.params.crop {
        let side = config.max_image_side;
        if w > side || h > side {
            return Err(invalid("augment.crop", format!("{w}x{h} is larger than the largest image side {side}")));
        }
        let (pixels, most) = (u64::from(w) * u64::from(h), config.max_image_pixels);
        if pixels > most {
            return Err(invalid(
                "augment.crop",
                format!("{w}x{h} is {pixels} pixels, more than the largest image (max_image_pixels {most})"),
            ));
        }
    }
    out.augment = Some(a);
    Ok(())
}

/// What the outputs of a request need of its motion law: the disparity field needs a stereo law
/// (a rectified pair), and a stereo pair takes no horizontal flip (it would swap the left and
/// right views and the sign of the disparity).
pub fn outputs_fit_motion(out: &OutputSpec, config: &SampleConfig) -> Result<(), ServiceError> {
    let stereo = config.motion.ranges().stereo;
    if out.fields.contains(&pb::Field::Disparity) && !stereo {
        return Err(invalid(
            "fields",
            "FIELD_DISPARITY needs a stereo motion law (motion_preset \"stereo\" or motion_ranges_json with \"stereo\": true)",
        ));
    }
    if let Some(a) = out.augment.as_ref().filter(|a| stereo && a.params.h_flip_prob > 0.0) {
        return Err(invalid(
            "augment.h_flip_prob",
            format!(
                "{} with a stereo motion law (a horizontal flip swaps the left and right views); set it to 0",
                a.params.h_flip_prob
            ),
        ));
    }
    Ok(())
}

/// The sample-configuration overrides of a request.
pub fn overrides(
    motion_preset: &str,
    motion_ranges_json: &str,
    max_objects: Option<u32>,
    motions_per_image: Option<u32>,
) -> Result<Overrides, ServiceError> {
    let motion_preset = if motion_preset.trim().is_empty() {
        None
    } else {
        Some(motion_preset.parse::<MotionPreset>().map_err(|_| {
            let names: Vec<&str> = MotionPreset::ALL.iter().map(|p| p.name()).collect();
            let given = echo(motion_preset);
            invalid("motion_preset", format!("unknown preset {given} (expected one of {})", names.join(", ")))
        })?)
    };
    let motion_ranges = if motion_ranges_json.trim().is_empty() {
        None
    } else {
        if motion_ranges_json.len() > 64 << 10 {
            return Err(invalid("motion_ranges_json", "longer than 64 KiB"));
        }
        // the parser's message quotes the input (unknown fields, variants): one short printable line
        let bad = |e: &dyn std::fmt::Display| invalid("motion_ranges_json", printable(&e.to_string(), ECHO_CHARS));
        let r: MotionRanges = serde_json::from_str(motion_ranges_json).map_err(|e| bad(&e))?;
        r.validate().map_err(|e| bad(&e))?;
        Some(r)
    };
    if let Some(m) = max_objects {
        if m > 255 {
            return Err(invalid("max_objects", format!("{m} (at most 255 objects fit the u8 label masks)")));
        }
    }
    if motions_per_image == Some(0) {
        return Err(invalid("motions_per_image", "0 (expected at least 1)"));
    }
    Ok(Overrides {
        motion_preset,
        motion_ranges,
        max_objects: max_objects.map(|m| m as usize),
        motions_per_image: motions_per_image.map(u64::from),
        frames: None,
        backward: false,
        occlusion: false,
        resample: None,
    })
}

/// The colour kernel of a request (`resample`; empty = the dataset's).
pub fn resample(name: &str) -> Result<Option<Resample>, ServiceError> {
    let name = name.trim();
    if name.is_empty() {
        return Ok(None);
    }
    name.parse::<Resample>().map(Some).map_err(|_| {
        let names: Vec<&str> = Resample::ALL.iter().map(|r| r.name()).collect();
        invalid("resample", format!("unknown kernel {} (expected one of {})", echo(name), names.join(", ")))
    })
}

/// The `frames` of a request (0 = 2, else 2 to 8) and whether its fields ask for the backward
/// flow and for the occlusion mask, put into `o`. Clips and backward fields are not made with `augment`.
pub fn frames(frames: u32, out: &OutputSpec, o: &mut Overrides) -> Result<(), ServiceError> {
    use crate::sample::config::{MAX_FRAMES, MIN_FRAMES};
    let k = if frames == 0 { MIN_FRAMES } else { frames as usize };
    if !(MIN_FRAMES..=MAX_FRAMES).contains(&k) {
        return Err(invalid("frames", format!("{frames} (expected {MIN_FRAMES} to {MAX_FRAMES}, or 0 for 2)")));
    }
    o.backward = wants_backward(&out.fields);
    o.occlusion = wants_occlusion(&out.fields);
    if out.augment.is_some() && (k > MIN_FRAMES || o.backward) {
        return Err(invalid("augment", "is not made for clips (frames > 2) or the backward fields yet"));
    }
    o.frames = (k != MIN_FRAMES).then_some(k);
    Ok(())
}

/// Rank, world size, start, count, batch size and prefetch of a stream request:
/// `(rank, world_size, batch_size, prefetch)`.
pub fn stream_shape(r: &pb::StreamRequest, config: &ServiceConfig) -> Result<(u32, u32, u32, u32), ServiceError> {
    let world = if r.world_size == 0 { 1 } else { r.world_size };
    if world > MAX_WORLD_SIZE {
        return Err(invalid("world_size", format!("{} is larger than {MAX_WORLD_SIZE}", r.world_size)));
    }
    if r.rank >= world {
        return Err(invalid("rank", format!("{} must be below world_size {world}", r.rank)));
    }
    let first = r
        .start_index
        .checked_add(u64::from(r.rank))
        .ok_or_else(|| invalid("start_index", format!("{} + rank {} overflows u64", r.start_index, r.rank)))?;
    // indices are 0 .. 2^64 - 1 (END_INDEX, the "after the last" cursor, is never a sample); a
    // counted request must fit as a whole
    let last = (r.count.max(1) - 1).checked_mul(u64::from(world)).and_then(|d| d.checked_add(first));
    if r.count > 0 && last.is_none_or(|l| l == super::pool::END_INDEX) {
        return Err(invalid(
            "count",
            format!("{} samples from index {first} step {world} reach the end of the index space (2^64 - 1)", r.count),
        ));
    }
    let batch = if r.batch_size == 0 { 1 } else { r.batch_size };
    if batch > config.max_batch_size {
        return Err(invalid(
            "batch_size",
            format!("{} is larger than max_batch_size {}", batch, config.max_batch_size),
        ));
    }
    let prefetch = if r.prefetch == 0 { config.default_prefetch } else { r.prefetch.min(config.max_prefetch) };
    Ok((r.rank, world, batch, prefetch.max(batch)))
}

/// The most pixels a sample of this request can have: the augmentation's crop, else the rendered
/// frame's bound (`max_sample_pixels`) scaled by the augmentation's largest resize, else the
/// request's crop (when it names both sides), else the frame's bound.
pub fn sample_pixels_bound(out: &OutputSpec, config: &ServiceConfig) -> u64 {
    let frame = config.max_sample_pixels();
    match (&out.augment, &out.crop) {
        (Some(a), _) => match a.params.crop {
            Some((w, h)) => u64::from(w) * u64::from(h),
            None => {
                let p = &a.params;
                let mut log2 = 0.0;
                if p.spatial_prob > 0.0 {
                    log2 += p.max_scale.max(0.0);
                }
                if p.stretch_prob > 0.0 {
                    log2 += p.max_stretch.max(0.0);
                }
                // both axes scale
                (frame as f64 * (2.0 * log2).exp2()).ceil().min(u64::MAX as f64) as u64
            }
        },
        (None, Some(c)) if c.width > 0 && c.height > 0 => (u64::from(c.width) * u64::from(c.height)).min(frame),
        _ => frame,
    }
}

/// Admission by size, before any work: the largest sample of the request (its pixel bound times
/// the bytes per pixel of its fields and frames, [`super::config::sample_bytes_bound`]) must fit
/// the message limit and the byte budget of made-but-unsent samples; else RESOURCE_EXHAUSTED
/// naming the fields that make it large. The bound, when admitted.
pub fn admit_size(out: &OutputSpec, frames: usize, config: &ServiceConfig, budget: u64) -> Result<u64, ServiceError> {
    use super::config::sample_bytes_bound;
    let pixels = sample_pixels_bound(out, config);
    let mut per_field = super::encode::bytes_per_pixel(&out.fields, frames, out.flow_f16);
    let per_pixel: u64 = per_field.iter().map(|(_, b)| b).sum();
    let bound = sample_bytes_bound(pixels, per_pixel, per_field.len() as u64);
    let (limit, what) = {
        let m = config.max_message_bytes();
        if budget < m {
            (budget, "the byte budget of unsent samples (max_buffered_mb)")
        } else {
            (m, "the message limit (Limits.max_message_bytes)")
        }
    };
    if bound <= limit {
        return Ok(bound);
    }
    per_field.sort_by_key(|(_, b)| std::cmp::Reverse(*b));
    let mb = |b: u64| b as f64 / 1e6;
    let largest: Vec<String> =
        per_field.iter().take(4).map(|(name, b)| format!("{name} {:.1} MB", mb(b.saturating_mul(pixels)))).collect();
    Err(ServiceError::LimitExceeded(
        super::error::Reason::SampleTooLarge,
        format!(
        "sample too large: up to {pixels} pixels x {frames} frames with {} fields is up to {:.1} MB, over {what} of \
         {:.1} MB (largest: {}); ask for fewer fields or frames, f16 flow, a smaller crop, or a server with a smaller size",
        per_field.len(),
        mb(bound),
        mb(limit),
        largest.join(", ")
    )))
}

/// The index list of a GetSamples request: 1 to [`MAX_INDICES`] indices, any order, duplicates
/// allowed.
pub fn indices(indices: &[u64]) -> Result<Vec<u64>, ServiceError> {
    if indices.is_empty() {
        return Err(invalid("indices", format!("empty (expected 1 to {MAX_INDICES} indices)")));
    }
    if indices.len() > MAX_INDICES {
        return Err(invalid("indices", format!("{} indices (at most {MAX_INDICES} per request)", indices.len())));
    }
    if let Some(k) = indices.iter().position(|&i| i == super::pool::END_INDEX) {
        return Err(invalid("indices", format!("[{k}] = 2^64 - 1 is the end of the index space, not a sample")));
    }
    Ok(indices.to_vec())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(fields: &[pb::Field]) -> OutputSpec {
        OutputSpec { fields: fields.to_vec(), ..OutputSpec::default() }
    }

    /// The bound is what the encoder sends: a sample of every field of a pair at 64x48 fits its
    /// bound, and the bound's tensors are those of `to_proto`.
    #[test]
    fn a_request_over_the_message_limit_is_refused_naming_its_largest_fields() {
        // 4096x4096 frames: a clip with every field is 3 GB, over the 1 GiB message cap
        let c = ServiceConfig { size: Some("4096x4096".into()), max_buffered_mb: 1 << 20, ..ServiceConfig::default() };
        let all = crate::service::encode::ALL_FIELDS;
        let e = admit_size(&spec(&all[..13]), 8, &c, c.buffered_budget_bytes()).unwrap_err();
        assert_eq!(e.code(), tonic::Code::ResourceExhausted);
        let m = e.to_string();
        assert!(m.contains("message limit") && m.contains("flows ") && m.contains("flows_backward"), "{m}");
        // a pair of the default fields fits, and so does f16 flow where f32 would not
        assert!(admit_size(&spec(&DEFAULT_FIELDS), 2, &c, c.buffered_budget_bytes()).is_ok());
        let mut flows = spec(&[pb::Field::Flow, pb::Field::FlowBackward]);
        assert!(admit_size(&flows, 8, &c, c.buffered_budget_bytes()).is_err());
        flows.flow_f16 = true;
        let pairs_f16 = 7 * 2 * 2 * 2 * 4096 * 4096u64;
        assert_eq!(admit_size(&flows, 8, &c, c.buffered_budget_bytes()).is_ok(), pairs_f16 < (1 << 30) - (1 << 20));
        // the budget bounds it too, and is named when it is the smaller
        let e = admit_size(&spec(&DEFAULT_FIELDS), 2, &c, 1 << 20).unwrap_err();
        assert!(e.to_string().contains("max_buffered_mb"), "{e}");
    }

    #[test]
    fn the_pixel_bound_follows_the_augmentation_and_the_crop() {
        let c = ServiceConfig { size: Some("640x480".into()), ..ServiceConfig::default() };
        let mut out = spec(&DEFAULT_FIELDS);
        assert_eq!(sample_pixels_bound(&out, &c), 640 * 480);
        out.crop = Some(CropSpec { width: 100, height: 50, random: false });
        assert_eq!(sample_pixels_bound(&out, &c), 5000);
        out.crop = Some(CropSpec { width: 0, height: 50, random: false });
        assert_eq!(sample_pixels_bound(&out, &c), 640 * 480);
        augment("raft-chairs", &mut out, &c).unwrap_err(); // one side alone with augment
        out.crop = None;
        augment("raft-chairs", &mut out, &c).unwrap();
        let (w, h) = out.augment.as_ref().unwrap().params.crop.unwrap();
        assert_eq!(sample_pixels_bound(&out, &c), u64::from(w) * u64::from(h));
        let e = augment(r#"{"preset":"raft-chairs","crop":[8192,8192]}"#, &mut spec(&DEFAULT_FIELDS), &c);
        assert!(e.unwrap_err().to_string().starts_with("augment.crop: 8192x8192 is 67108864 pixels"));
    }

    #[test]
    fn the_end_of_the_index_space_is_refused_by_position() {
        assert_eq!(indices(&[0, 1, u64::MAX - 1]).unwrap().len(), 3);
        let e = indices(&[3, u64::MAX]).unwrap_err().to_string();
        assert!(e.starts_with("indices: [1] = 2^64 - 1"), "{e}");
    }
}
