//! The stereo layout (`--format stereo`) for rectified pairs of a stereo motion law: the
//! SceneFlow-style folders `OUT/left/I.png`, `OUT/right/I.png`, `OUT/disparity/I.pfm` (the left
//! view's disparity `d = x1 - x2 >= 0` as a one-channel little-endian PFM, rows bottom to top,
//! which SceneFlow readers such as RAFT-Stereo's `readPFM` load unchanged), `OUT/occlusion/I.png`
//! and `OUT/valid/I.png` (255 = occluded in the right view / disparity valid), `OUT/holes/I.png`
//! (255 = right-view pixel filled by inpainting) and the JSON record `OUT/records/I.json`.
//!
//! Only rectified pairs are written: a sample whose camera motion has a rotation or a vertical
//! or depth translation, or that moved objects, is refused with its reason.

use std::path::{Path, PathBuf};

use ::image::ExtendedColorType;

use super::fields::{binary_png, check_sample, encode_png, finish_record, EncodedSample, Field, FlowEncoding};
use super::layout::write_fields;
use super::ExportError;
use crate::sample::Sample;
use crate::source::pfm::encode_pfm;

/// Why a sample is not a rectified stereo pair; `None` when it is one.
pub fn not_rectified(s: &Sample) -> Option<String> {
    let m = &s.camera;
    if m.angles.iter().chain(&m.axis_angle).any(|&a| a != 0.0) {
        return Some("its camera motion rotates".into());
    }
    if m.translation[1] != 0.0 || m.translation[2] != 0.0 {
        return Some("its camera moves off the x axis".into());
    }
    if m.translation[0] > 0.0 {
        return Some("image 2 lies left of image 1 (translation x > 0)".into());
    }
    if !s.objects.is_empty() {
        return Some("objects moved".into());
    }
    None
}

/// Encodes a rectified pair in the stereo layout's writing order: `left.png`, `right.png`,
/// `disparity.pfm`, `occlusion.png`, `valid.png`, `holes.png` and the JSON record.
pub fn encode_stereo(index: u64, s: &Sample) -> Result<EncodedSample, ExportError> {
    check_sample(index, s)?;
    if let Some(why) = not_rectified(s) {
        let reason = format!("not a rectified stereo pair ({why}): make it with the stereo motion preset");
        return Err(ExportError::InvalidSample { index, reason });
    }
    let (w, h) = (s.width, s.height);
    let fields = vec![
        Field { name: "left", ext: "png", bytes: encode_png(w, h, &s.image1, ExtendedColorType::Rgb8)? },
        Field { name: "right", ext: "png", bytes: encode_png(w, h, &s.image2, ExtendedColorType::Rgb8)? },
        Field { name: "disparity", ext: "pfm", bytes: encode_pfm(w, h, 1, &s.disparity(), true) },
        Field { name: "occlusion", ext: "png", bytes: binary_png(w, h, &s.occlusion)? },
        Field { name: "valid", ext: "png", bytes: binary_png(w, h, &s.valid)? },
        Field { name: "holes", ext: "png", bytes: binary_png(w, h, &s.holes)? },
    ];
    finish_record(index, s, FlowEncoding::DisparityPfm, fields)
}

/// `OUT/<field>/I.ext`, the record in `OUT/records/I.json`.
pub fn stereo_path(dir: &Path, key: &str, field: &Field) -> PathBuf {
    let folder = if field.name.is_empty() { "records" } else { field.name };
    dir.join(folder).join(format!("{key}.{}", field.ext))
}

/// The folders of the layout, created by the exporter.
pub const FOLDERS: [&str; 7] = ["left", "right", "disparity", "occlusion", "valid", "holes", "records"];

/// Writes one encoded pair into the layout (each file atomically, the record last).
pub fn write_stereo(dir: &Path, sample: &EncodedSample) -> Result<Vec<PathBuf>, ExportError> {
    write_fields(sample, |field| Ok(stereo_path(dir, &sample.key, field)))
}
