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
use crate::sample::{ObjectRecord, Sample, StageTimings};

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
    /// The stereo layout: no flow file, the disparity `d = -u` as a one-channel PFM
    /// ([`super::stereo`]).
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

/// The JSON record of a sample (what `I.json` holds, there with its keys in this order:
/// `mpiflow_export`, `key`, `index`, `source_id`, `address`, `width`, `height`, `fields`,
/// `flow_encoding`, `camera`, `objects`, `inpainted_pixels`, `stats`, `provenance`, `timings`).
pub fn sample_json(index: u64, s: &Sample, flow: FlowEncoding, fields: &[String]) -> serde_json::Value {
    let key = sample_key(index);
    // serialising plain structs of numbers and strings cannot fail; non-finite floats become null
    serde_json::to_value(record(index, &key, s, flow, fields)).unwrap_or(serde_json::Value::Null)
}

/// Encodes a sample's fields in writing order: `img1.png`, `img2.png`, the flow, `valid.png`,
/// `occ.png`, `holes.png`, `mask.png` (only when objects moved) and the JSON record.
pub fn encode_sample(index: u64, s: &Sample, flow: FlowEncoding) -> Result<EncodedSample, ExportError> {
    if flow == FlowEncoding::DisparityPfm {
        return super::stereo::encode_stereo(index, s);
    }
    check_sample(index, s)?;
    let (w, h) = (s.width, s.height);
    let mut fields = Vec::with_capacity(8);
    fields.push(Field { name: "img1", ext: "png", bytes: encode_png(w, h, &s.image1, ExtendedColorType::Rgb8)? });
    fields.push(Field { name: "img2", ext: "png", bytes: encode_png(w, h, &s.image2, ExtendedColorType::Rgb8)? });
    let flow_bytes = match flow {
        FlowEncoding::Flo => {
            let mut v = Vec::with_capacity(12 + s.flow.len() * 4);
            flo::write_flo_to(&mut v, w, h, &s.flow).map_err(|e| ExportError::Encode(format!(".flo: {e}")))?;
            v
        }
        FlowEncoding::KittiPng => encode_kitti_flow(w, h, &s.flow, &s.valid)?,
        FlowEncoding::Npy => {
            let mut v = Vec::with_capacity(128 + s.flow.len() * 4);
            npy::write_f32_to(&mut v, &[h as u64, w as u64, 2], &s.flow)
                .map_err(|e| ExportError::Encode(format!(".npy: {e}")))?;
            v
        }
        FlowEncoding::DisparityPfm => unreachable!("encoded by the stereo layout above"),
    };
    fields.push(Field { name: "flow", ext: flow.ext(), bytes: flow_bytes });
    fields.push(Field { name: "valid", ext: "png", bytes: binary_png(w, h, &s.valid)? });
    fields.push(Field { name: "occ", ext: "png", bytes: binary_png(w, h, &s.occlusion)? });
    fields.push(Field { name: "holes", ext: "png", bytes: binary_png(w, h, &s.holes)? });
    if !s.objects.is_empty() {
        fields.push(Field { name: "mask", ext: "png", bytes: encode_png(w, h, &s.mask1, ExtendedColorType::L8)? });
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
