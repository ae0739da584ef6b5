//! What a request wants of each sample: the fields (their wire names, their bytes per pixel) and
//! the output spec (f16 flow, lz4, the crop, the augmentation).

use crate::sample::augment::Augment;
use crate::sample::crop::CropSpec;
use crate::service::pb;

/// The default fields of a request that names none.
pub const DEFAULT_FIELDS: [pb::Field; 4] = [pb::Field::Image1, pb::Field::Image2, pb::Field::Flow, pb::Field::Valid];

/// What a request wants of each sample.
#[derive(Clone, Debug, PartialEq)]
pub struct OutputSpec {
    /// In wire order (the enum's order), without duplicates.
    pub fields: Vec<pb::Field>,
    pub flow_f16: bool,
    pub lz4: bool,
    /// The crop without augmentation (with it, the augmentation crops).
    pub crop: Option<CropSpec>,
    /// The training augmentation, applied before encoding (its crop replaces `crop`).
    pub augment: Option<Augment>,
}

impl Default for OutputSpec {
    fn default() -> Self {
        Self { fields: DEFAULT_FIELDS.to_vec(), flow_f16: false, lz4: false, crop: None, augment: None }
    }
}

/// The wire name of a field.
pub fn field_name(f: pb::Field) -> &'static str {
    match f {
        pb::Field::Unspecified => "unspecified",
        pb::Field::Image1 => "image1",
        pb::Field::Image2 => "image2",
        pb::Field::Flow => "flow",
        pb::Field::Valid => "valid",
        pb::Field::Occlusion => "occlusion",
        pb::Field::Mask1 => "mask1",
        pb::Field::Mask2 => "mask2",
        pb::Field::Depth1 => "depth1",
        pb::Field::Depth2 => "depth2",
        pb::Field::Holes => "holes",
        pb::Field::FlowBackward => "flow_backward",
        pb::Field::ValidBackward => "valid_backward",
        pb::Field::OcclusionBackward => "occlusion_backward",
        pb::Field::Disparity => "disparity",
    }
}

/// The wire name of a field in a clip of more than two frames (stacked over the frames or the
/// pairs), or None for the fields that stay those of the first pair.
pub fn clip_field_name(f: pb::Field) -> Option<&'static str> {
    Some(match f {
        pb::Field::Image1 | pb::Field::Image2 => "images",
        pb::Field::Flow => "flows",
        pb::Field::Valid => "valids",
        pb::Field::Occlusion => "occlusions",
        pb::Field::FlowBackward => "flows_backward",
        pb::Field::ValidBackward => "valids_backward",
        pb::Field::OcclusionBackward => "occlusions_backward",
        _ => return None,
    })
}

/// Bytes per pixel of each field on the wire, for a sample of `frames` frames (2 = a pair) with
/// f16 or f32 flow, before compression (lz4 may add up to 1/255 and 16 bytes per tensor): the
/// images 3 per frame, a flow 4 or 8 and a mask 1 per pair of frames (for the linked fields of
/// a clip), depth and disparity 4, the object masks and holes 1.
pub fn bytes_per_pixel(fields: &[pb::Field], frames: usize, flow_f16: bool) -> Vec<(&'static str, u64)> {
    let k = frames.max(2) as u64;
    let pairs = k - 1;
    let flow = if flow_f16 { 2 } else { 4 } * 2;
    let mut out = Vec::with_capacity(fields.len());
    for &f in fields {
        let per_pixel = match f {
            pb::Field::Unspecified => continue,
            // a clip stacks both images into one tensor: counted once, with the first
            pb::Field::Image1 => 3 * if k > 2 { k } else { 1 },
            pb::Field::Image2 if k > 2 && fields.contains(&pb::Field::Image1) => continue,
            pb::Field::Image2 => 3 * if k > 2 { k } else { 1 },
            pb::Field::Flow | pb::Field::FlowBackward => flow * pairs,
            pb::Field::Valid | pb::Field::Occlusion | pb::Field::ValidBackward | pb::Field::OcclusionBackward => pairs,
            pb::Field::Mask1 | pb::Field::Mask2 | pb::Field::Holes => 1,
            pb::Field::Depth1 | pb::Field::Depth2 | pb::Field::Disparity => 4,
        };
        let name = if k > 2 { clip_field_name(f).unwrap_or(field_name(f)) } else { field_name(f) };
        out.push((name, per_pixel));
    }
    out
}

/// Every field a request may name, in wire order.
pub const ALL_FIELDS: [pb::Field; 14] = [
    pb::Field::Image1,
    pb::Field::Image2,
    pb::Field::Flow,
    pb::Field::Valid,
    pb::Field::Occlusion,
    pb::Field::Mask1,
    pb::Field::Mask2,
    pb::Field::Depth1,
    pb::Field::Depth2,
    pb::Field::Holes,
    pb::Field::FlowBackward,
    pb::Field::ValidBackward,
    pb::Field::OcclusionBackward,
    pb::Field::Disparity,
];

/// Whether the fields ask for the (forward) occlusion mask.
pub fn wants_occlusion(fields: &[pb::Field]) -> bool {
    fields.contains(&pb::Field::Occlusion)
}

/// Whether the fields ask for the backward flow or its masks.
pub fn wants_backward(fields: &[pb::Field]) -> bool {
    fields
        .iter()
        .any(|f| matches!(f, pb::Field::FlowBackward | pb::Field::ValidBackward | pb::Field::OcclusionBackward))
}
