//! One sample encoded, in memory, as the fields every export format writes: PNG images and
//! masks, the flow (Middlebury `.flo`, KITTI 16-bit PNG or NumPy `.npy`) and the JSON record.
//!
//! Encoding is a pure function of the sample (plus its export index), so it can run on any
//! thread; the writers only move the bytes to disk or into a tar shard.

use ::image::codecs::png::PngEncoder;
use ::image::{ExtendedColorType, ImageEncoder};
use serde::Serialize;

use super::ExportError;
use crate::io::{colorwheel, flo, npy};
use crate::sample::motion::Motion;
use crate::sample::{disparity_of, ObjectRecord, Sample, StageTimings};
use crate::source::pfm::encode_pfm;

/// Version of the JSON record's layout (`"mpiflow_export"` in every `I.json`).
pub const JSON_VERSION: u32 = 1;

/// How the flow field is stored.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FlowEncoding {
    /// Middlebury `.flo`: float32, exact.
    Flo,
    /// KITTI 16-bit PNG (u, v, valid), 1/64 px steps, +-512 px.
    KittiPng,
    /// NumPy `.npy`, float32 H x W x 2, exact.
    Npy,
    /// The stereo layout: no flow file, the disparity `d = -u` as a one-channel PFM.
    DisparityPfm,
}

impl FlowEncoding {
    /// The file extension (without dot).
    pub fn ext(self) -> &'static str {
        match self {
            FlowEncoding::Flo => "flo",
            FlowEncoding::KittiPng => "png",
            FlowEncoding::Npy => "npy",
            FlowEncoding::DisparityPfm => "pfm",
        }
    }
}

/// One encoded field of a sample: `name` is the part between key and extension (`img1`,
/// `flow`, ...), empty for the JSON record.
#[derive(Clone, Debug, PartialEq)]
pub struct Field {
    pub name: &'static str,
    pub ext: &'static str,
    pub bytes: Vec<u8>,
}

impl Field {
    /// `I_name.ext` (the FlyingChairs-style file name), or `I.ext` for an unnamed field.
    pub fn file_name(&self, key: &str) -> String {
        if self.name.is_empty() {
            format!("{key}.{}", self.ext)
        } else {
            format!("{key}_{}.{}", self.name, self.ext)
        }
    }

    /// `I.name.ext` (the WebDataset member name: key, then the field), or `I.ext`.
    pub fn member_name(&self, key: &str) -> String {
        if self.name.is_empty() {
            format!("{key}.{}", self.ext)
        } else {
            format!("{key}.{}.{}", self.name, self.ext)
        }
    }
}

/// A sample encoded for writing: its key and its fields in writing order (the JSON record
/// last, so its presence means the sample is complete).
#[derive(Clone, Debug, PartialEq)]
pub struct EncodedSample {
    pub index: u64,
    pub key: String,
    pub fields: Vec<Field>,
}

impl EncodedSample {
    /// Total encoded size in bytes.
    pub fn byte_len(&self) -> usize {
        self.fields.iter().map(|f| f.bytes.len()).sum()
    }
}

/// The export key of a sample index: at least 8 digits, zero-padded (`00000042`).
pub fn sample_key(index: u64) -> String {
    format!("{index:08}")
}

/// Checks that every buffer of the sample has the size its width and height promise.
pub fn check_sample(index: u64, s: &Sample) -> Result<(), ExportError> {
    let bad = |reason: String| Err(ExportError::InvalidSample { index, reason });
    let n = match s.width.checked_mul(s.height) {
        Some(n) if n > 0 && s.width <= u32::MAX as usize && s.height <= u32::MAX as usize => n,
        _ => return bad(format!("cannot export a {} x {} sample", s.width, s.height)),
    };
    let checks: [(&str, usize, usize); 8] = [
        ("image1", s.image1.len(), n * 3),
        ("image2", s.image2.len(), n * 3),
        ("flow", s.flow.len(), n * 2),
        ("valid", s.valid.len(), n),
        ("occlusion", s.occlusion.len(), n),
        ("mask1", s.mask1.len(), n),
        ("mask2", s.mask2.len(), n),
        ("holes", s.holes.len(), n),
    ];
    for (name, got, want) in checks {
        if got != want {
            return bad(format!("{name} holds {got} values, a {} x {} sample needs {want}", s.width, s.height));
        }
    }
    if let Some(i) = s.flow.iter().position(|v| !v.is_finite()) {
        return bad(format!("flow value {i} is not finite ({})", s.flow[i]));
    }
    if s.clip.len() + 2 > crate::sample::config::MAX_FRAMES {
        return bad(format!("{} frames (at most {})", s.clip.len() + 2, crate::sample::config::MAX_FRAMES));
    }
    let links = std::iter::once(("backward", &s.backward))
        .chain(s.clip.iter().flat_map(|c| [("clip forward", &c.forward), ("clip backward", &c.backward)]));
    for (name, l) in links {
        if l.flow.is_empty() && l.valid.is_empty() && l.occlusion.is_empty() {
            continue;
        }
        if l.flow.len() != n * 2 || l.valid.len() != n || l.occlusion.len() != n {
            return bad(format!("the {name} flow or its masks have the wrong size"));
        }
        if l.flow.iter().any(|v| !v.is_finite()) {
            return bad(format!("the {name} flow is not finite"));
        }
    }
    if s.clip.iter().any(|c| c.image.len() != n * 3) {
        return bad("a clip frame has the wrong size".into());
    }
    Ok(())
}

/// Encodes interleaved 8- or 16-bit samples as PNG bytes.
pub fn encode_png(width: usize, height: usize, bytes: &[u8], color: ExtendedColorType) -> Result<Vec<u8>, ExportError> {
    let mut out = Vec::with_capacity(bytes.len() / 2 + 1024);
    PngEncoder::new(&mut out)
        .write_image(bytes, width as u32, height as u32, color)
        .map_err(|e| ExportError::Encode(format!("PNG of {width} x {height}: {e}")))?;
    Ok(out)
}

/// 0/1 (or any non-zero) mask as an 8-bit PNG with 0 and 255.
pub(crate) fn binary_png(width: usize, height: usize, mask: &[u8]) -> Result<Vec<u8>, ExportError> {
    let v: Vec<u8> = mask.iter().map(|&m| if m != 0 { 255 } else { 0 }).collect();
    encode_png(width, height, &v, ExtendedColorType::L8)
}

/// KITTI encoding of one component: round(64 x + 2^15), clamped to 0..=65535 (as
/// [`crate::io::flo::write_kitti_flow_png`] writes it).
#[inline]
fn kitti_component(x: f32) -> u16 {
    (x * 64.0 + 32768.0).round().clamp(0.0, 65535.0) as u16
}

/// A KITTI 16-bit flow PNG in memory: R = u, G = v (64 x + 2^15), B = 1 where `valid` is
/// non-zero.
pub fn encode_kitti_flow(width: usize, height: usize, flow: &[f32], valid: &[u8]) -> Result<Vec<u8>, ExportError> {
    let mut bytes = Vec::with_capacity(width * height * 6);
    for (p, &ok) in flow.chunks_exact(2).zip(valid) {
        let px = if p[0].is_finite() && p[1].is_finite() {
            [kitti_component(p[0]), kitti_component(p[1]), u16::from(ok != 0)]
        } else {
            [32768, 32768, 0]
        };
        for c in px {
            bytes.extend_from_slice(&c.to_ne_bytes());
        }
    }
    encode_png(width, height, &bytes, ExtendedColorType::Rgb16)
}

#[derive(Serialize)]
struct AddressJson {
    dataset: u64,
    /// The fingerprint as 16 hex digits (JSON readers that use doubles lose u64 precision).
    dataset_hex: String,
    seed: u64,
    index: u64,
}

#[derive(Serialize)]
struct StatsJson {
    valid_fraction: f64,
    occluded_fraction: f64,
    /// Largest flow magnitude in pixels.
    max_flow: f32,
}

#[derive(Serialize)]
struct SampleJson<'a> {
    mpiflow_export: u32,
    key: &'a str,
    index: u64,
    source_id: &'a str,
    address: AddressJson,
    width: usize,
    height: usize,
    /// The files/members written for this sample, without the key (e.g. `img1.png`).
    fields: Vec<String>,
    flow_encoding: &'static str,
    camera: &'a Motion,
    objects: &'a [ObjectRecord],
    inpainted_pixels: u64,
    stats: StatsJson,
    provenance: &'a [String],
    timings: &'a StageTimings,
}

fn fraction(mask: &[u8]) -> f64 {
    if mask.is_empty() {
        0.0
    } else {
        mask.iter().filter(|&&m| m != 0).count() as f64 / mask.len() as f64
    }
}

fn record<'a>(index: u64, key: &'a str, s: &'a Sample, flow: FlowEncoding, fields: &[String]) -> SampleJson<'a> {
    SampleJson {
        mpiflow_export: JSON_VERSION,
        key,
        index,
        source_id: &s.source_id,
        address: AddressJson {
            dataset: s.address.dataset,
            dataset_hex: format!("{:016x}", s.address.dataset),
            seed: s.address.seed,
            index: s.address.index,
        },
        width: s.width,
        height: s.height,
        fields: fields.to_vec(),
        flow_encoding: match flow {
            FlowEncoding::Flo => "flo",
            FlowEncoding::KittiPng => "kitti-png",
            FlowEncoding::Npy => "npy-float32-hw2",
            FlowEncoding::DisparityPfm => "pfm-disparity",
        },
        camera: &s.camera,
        objects: &s.objects,
        inpainted_pixels: s.inpainted_pixels,
        stats: StatsJson {
            valid_fraction: fraction(&s.valid),
            occluded_fraction: fraction(&s.occlusion),
            max_flow: colorwheel::max_magnitude(&s.flow),
        },
        provenance: &s.provenance,
        timings: &s.timings,
    }
}

/// Field names of a clip's frames 3..8 (`img3` ...) and of the pairs ending in them
/// (`flow23` = frame 2 -> 3 on frame 2's grid, `flow_bw32` = frame 3 -> 2 on frame 3's grid).
const CLIP_IMG: [&str; 6] = ["img3", "img4", "img5", "img6", "img7", "img8"];
const CLIP_FLOW: [&str; 6] = ["flow23", "flow34", "flow45", "flow56", "flow67", "flow78"];
const CLIP_VALID: [&str; 6] = ["valid23", "valid34", "valid45", "valid56", "valid67", "valid78"];
const CLIP_OCC: [&str; 6] = ["occ23", "occ34", "occ45", "occ56", "occ67", "occ78"];
const CLIP_FLOW_BW: [&str; 6] = ["flow_bw32", "flow_bw43", "flow_bw54", "flow_bw65", "flow_bw76", "flow_bw87"];
const CLIP_VALID_BW: [&str; 6] = ["valid_bw32", "valid_bw43", "valid_bw54", "valid_bw65", "valid_bw76", "valid_bw87"];
const CLIP_OCC_BW: [&str; 6] = ["occ_bw32", "occ_bw43", "occ_bw54", "occ_bw65", "occ_bw76", "occ_bw87"];

/// One flow field in `encoding` (`valid` is the KITTI PNG's third channel).
pub fn encode_flow(
    w: usize,
    h: usize,
    flow: &[f32],
    valid: &[u8],
    encoding: FlowEncoding,
) -> Result<Vec<u8>, ExportError> {
    Ok(match encoding {
        FlowEncoding::Flo => {
            let mut v = Vec::with_capacity(12 + flow.len() * 4);
            flo::write_flo_to(&mut v, w, h, flow).map_err(|e| ExportError::Encode(format!(".flo: {e}")))?;
            v
        }
        FlowEncoding::KittiPng => encode_kitti_flow(w, h, flow, valid)?,
        FlowEncoding::Npy => {
            let mut v = Vec::with_capacity(128 + flow.len() * 4);
            npy::write_f32_to(&mut v, &[h as u64, w as u64, 2], flow)
                .map_err(|e| ExportError::Encode(format!(".npy: {e}")))?;
            v
        }
        FlowEncoding::DisparityPfm => encode_pfm(w, h, 1, &disparity_of(flow), true),
    })
}

/// Sintel field names: `KIND/frame_000N` (the file `OUT/training/KIND/<key>/frame_000N.EXT`).
const SINTEL_CLEAN: [&str; 8] = [
    "clean/frame_0001",
    "clean/frame_0002",
    "clean/frame_0003",
    "clean/frame_0004",
    "clean/frame_0005",
    "clean/frame_0006",
    "clean/frame_0007",
    "clean/frame_0008",
];
const SINTEL_FLOW: [&str; 7] = [
    "flow/frame_0001",
    "flow/frame_0002",
    "flow/frame_0003",
    "flow/frame_0004",
    "flow/frame_0005",
    "flow/frame_0006",
    "flow/frame_0007",
];
const SINTEL_OCC: [&str; 7] = [
    "occlusions/frame_0001",
    "occlusions/frame_0002",
    "occlusions/frame_0003",
    "occlusions/frame_0004",
    "occlusions/frame_0005",
    "occlusions/frame_0006",
    "occlusions/frame_0007",
];
const SINTEL_INVALID: [&str; 7] = [
    "invalid/frame_0001",
    "invalid/frame_0002",
    "invalid/frame_0003",
    "invalid/frame_0004",
    "invalid/frame_0005",
    "invalid/frame_0006",
    "invalid/frame_0007",
];

/// Encodes a sample (pair or clip of K frames) in the MPI Sintel training layout: K frames
/// `clean/frame_000k.png`, K - 1 flows `flow/frame_000k.flo` (frame k -> k+1 on frame k's
/// grid), K - 1 occlusion masks and K - 1 invalid masks (8-bit, 255 = occluded / invalid, as
/// Sintel), and the JSON record (`OUT/training/<key>.json`, named by the empty field name).
pub fn encode_sintel(index: u64, s: &Sample) -> Result<EncodedSample, ExportError> {
    check_sample(index, s)?;
    let (w, h) = (s.width, s.height);
    let mut fields = Vec::with_capacity(4 * (s.clip.len() + 2));
    let images = [&s.image1, &s.image2].into_iter().chain(s.clip.iter().map(|c| &c.image));
    for (k, img) in images.enumerate() {
        fields.push(Field {
            name: SINTEL_CLEAN[k],
            ext: "png",
            bytes: encode_png(w, h, img, ExtendedColorType::Rgb8)?,
        });
    }
    let pairs = std::iter::once((&s.flow, &s.valid, &s.occlusion))
        .chain(s.clip.iter().map(|c| (&c.forward.flow, &c.forward.valid, &c.forward.occlusion)));
    for (k, (flow, valid, occ)) in pairs.enumerate() {
        if flow.len() != 2 * w * h || valid.len() != w * h || occ.len() != w * h {
            return Err(ExportError::InvalidSample {
                index,
                reason: format!("pair {} lacks its flow or masks", k + 1),
            });
        }
        fields.push(Field {
            name: SINTEL_FLOW[k],
            ext: "flo",
            bytes: encode_flow(w, h, flow, valid, FlowEncoding::Flo)?,
        });
        fields.push(Field { name: SINTEL_OCC[k], ext: "png", bytes: binary_png(w, h, occ)? });
        let invalid: Vec<u8> = valid.iter().map(|&v| u8::from(v == 0)).collect();
        fields.push(Field { name: SINTEL_INVALID[k], ext: "png", bytes: binary_png(w, h, &invalid)? });
    }
    let mut names: Vec<String> = fields.iter().map(|f| format!("{}.{}", f.name, f.ext)).collect();
    names.push("json".into());
    let key = sample_key(index);
    let json = record(index, &key, s, FlowEncoding::Flo, &names);
    let mut bytes = serde_json::to_vec_pretty(&json).map_err(|e| ExportError::Encode(format!("JSON: {e}")))?;
    bytes.push(b'\n');
    fields.push(Field { name: "", ext: "json", bytes });
    Ok(EncodedSample { index, key, fields })
}

/// Encodes a sample's fields in writing order: `img1.png`, `img2.png`, the flow, `valid.png`,
/// `occ.png`, `holes.png`, `mask.png` (only when objects moved) and the JSON record.
pub fn encode_sample(index: u64, s: &Sample, flow: FlowEncoding) -> Result<EncodedSample, ExportError> {
    check_sample(index, s)?;
    let (w, h) = (s.width, s.height);
    let mut fields = Vec::with_capacity(8);
    fields.push(Field { name: "img1", ext: "png", bytes: encode_png(w, h, &s.image1, ExtendedColorType::Rgb8)? });
    fields.push(Field { name: "img2", ext: "png", bytes: encode_png(w, h, &s.image2, ExtendedColorType::Rgb8)? });
    fields.push(Field { name: "flow", ext: flow.ext(), bytes: encode_flow(w, h, &s.flow, &s.valid, flow)? });
    fields.push(Field { name: "valid", ext: "png", bytes: binary_png(w, h, &s.valid)? });
    fields.push(Field { name: "occ", ext: "png", bytes: binary_png(w, h, &s.occlusion)? });
    fields.push(Field { name: "holes", ext: "png", bytes: binary_png(w, h, &s.holes)? });
    if !s.objects.is_empty() {
        fields.push(Field { name: "mask", ext: "png", bytes: encode_png(w, h, &s.mask1, ExtendedColorType::L8)? });
    }
    if !s.backward.flow.is_empty() {
        let b = &s.backward;
        fields.push(Field { name: "flow_bw", ext: flow.ext(), bytes: encode_flow(w, h, &b.flow, &b.valid, flow)? });
        fields.push(Field { name: "valid_bw", ext: "png", bytes: binary_png(w, h, &b.valid)? });
        fields.push(Field { name: "occ_bw", ext: "png", bytes: binary_png(w, h, &b.occlusion)? });
    }
    // a clip's later frames: image k (k >= 3) and the pair k-1 -> k (and back)
    for (j, c) in s.clip.iter().enumerate() {
        let k = j + 3;
        fields.push(Field {
            name: CLIP_IMG[k - 3],
            ext: "png",
            bytes: encode_png(w, h, &c.image, ExtendedColorType::Rgb8)?,
        });
        let f = &c.forward;
        fields.push(Field {
            name: CLIP_FLOW[k - 3],
            ext: flow.ext(),
            bytes: encode_flow(w, h, &f.flow, &f.valid, flow)?,
        });
        fields.push(Field { name: CLIP_VALID[k - 3], ext: "png", bytes: binary_png(w, h, &f.valid)? });
        fields.push(Field { name: CLIP_OCC[k - 3], ext: "png", bytes: binary_png(w, h, &f.occlusion)? });
        if !c.backward.flow.is_empty() {
            let b = &c.backward;
            let bytes = encode_flow(w, h, &b.flow, &b.valid, flow)?;
            fields.push(Field { name: CLIP_FLOW_BW[k - 3], ext: flow.ext(), bytes });
            fields.push(Field { name: CLIP_VALID_BW[k - 3], ext: "png", bytes: binary_png(w, h, &b.valid)? });
            fields.push(Field { name: CLIP_OCC_BW[k - 3], ext: "png", bytes: binary_png(w, h, &b.occlusion)? });
        }
    }
    finish_record(index, s, flow, fields)
}

/// Appends the JSON record (listing `fields` and itself) to a sample's encoded fields.
pub(crate) fn finish_record(
    index: u64,
    s: &Sample,
    flow: FlowEncoding,
    mut fields: Vec<Field>,
) -> Result<EncodedSample, ExportError> {
    let mut names: Vec<String> = fields.iter().map(|f| format!("{}.{}", f.name, f.ext)).collect();
    names.push("json".into());
    let key = sample_key(index);
    let json = record(index, &key, s, flow, &names);
    let mut bytes = serde_json::to_vec_pretty(&json).map_err(|e| ExportError::Encode(format!("JSON: {e}")))?;
    bytes.push(b'\n');
    fields.push(Field { name: "", ext: "json", bytes });
    Ok(EncodedSample { index, key, fields })
}
