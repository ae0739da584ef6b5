//! Samples on the wire: cropping (centre, or a position from the sample's own random stream),
//! a sample's tensors (their bytes: [`super::tensor`]) and the way back (decoding a received
//! sample, for `mpiflow pull` and tests, reading the received bytes in place).

use std::borrow::Cow;

use half::f16;

use super::pb;
use super::tensor::{float_tensor, u8_tensor};
use crate::geometry::Intrinsics;
use crate::rng::{Purpose, SampleRng};
use crate::sample::augment::{clear_valid_outside, Augment};
use crate::sample::motion::{Motion, RotationKind};
use crate::sample::{ClipFrame, LinkFields, ObjectRecord, Sample, SampleAddress, StageTimings};

/// The random stream of a sample's crop position: `Purpose::Other(CROP_PURPOSE)` of its address.
pub const CROP_PURPOSE: u32 = 0x6372_6f70; // "crop"

/// The default fields of a request that names none.
pub const DEFAULT_FIELDS: [pb::Field; 4] = [pb::Field::Image1, pb::Field::Image2, pb::Field::Flow, pb::Field::Valid];

/// How to cut samples.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CropSpec {
    /// 0 = the rendered width.
    pub width: u32,
    /// 0 = the rendered height.
    pub height: u32,
    pub random: bool,
}

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

/// The crop window `(x0, y0, width, height)` of a `w` x `h` sample at `address`. A requested side
/// larger than the sample is clamped to the sample's side. Centre: `(w - cw) / 2`; random:
/// `x0 = below(w - cw + 1)`, then `y0 = below(h - ch + 1)`, from the address's crop stream.
/// A crop that does not fit the rendered frame (never shrunk to fit).
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{want_w}x{want_h} is larger than the rendered frame {w}x{h}")]
pub struct CropTooLarge {
    pub want_w: usize,
    pub want_h: usize,
    pub w: usize,
    pub h: usize,
}

/// The crop window `(x0, y0, width, height)` of a `w` x `h` frame; a crop larger than the frame
/// in either side is an error (0 = the rendered side).
pub fn crop_window(
    spec: &CropSpec,
    w: usize,
    h: usize,
    address: SampleAddress,
) -> Result<(usize, usize, usize, usize), CropTooLarge> {
    let cw = if spec.width == 0 { w } else { spec.width as usize };
    let ch = if spec.height == 0 { h } else { spec.height as usize };
    if cw > w || ch > h {
        return Err(CropTooLarge { want_w: cw, want_h: ch, w, h });
    }
    if spec.random {
        let mut rng = SampleRng::new(address.dataset, address.seed, address.index, Purpose::Other(CROP_PURPOSE));
        let x0 = rng.below((w - cw + 1) as u64) as usize;
        let y0 = rng.below((h - ch + 1) as u64) as usize;
        Ok((x0, y0, cw, ch))
    } else {
        Ok(((w - cw) / 2, (h - ch) / 2, cw, ch))
    }
}

fn crop_plane<T: Copy>(data: &[T], w: usize, channels: usize, x0: usize, y0: usize, cw: usize, ch: usize) -> Vec<T> {
    if data.is_empty() {
        return Vec::new();
    }
    let mut out = Vec::with_capacity(cw * ch * channels);
    for y in y0..y0 + ch {
        out.extend_from_slice(&data[(y * w + x0) * channels..(y * w + x0 + cw) * channels]);
    }
    out
}

/// A flow with its masks cut to the window (`valid` cleared where the target leaves it).
fn crop_link(l: &LinkFields, w: usize, x0: usize, y0: usize, cw: usize, ch: usize) -> LinkFields {
    let flow = crop_plane(&l.flow, w, 2, x0, y0, cw, ch);
    let mut valid = crop_plane(&l.valid, w, 1, x0, y0, cw, ch);
    if !valid.is_empty() {
        clear_valid_outside(&flow, &mut valid, cw, ch);
    }
    LinkFields { flow, valid, occlusion: crop_plane(&l.occlusion, w, 1, x0, y0, cw, ch) }
}

/// Cuts every field of `s` to the window; the flow values stay (a displacement does not change
/// when both images are cut alike), and `valid` is cleared where the flow target leaves the crop
/// (the renderer's rule: target inside `[0, cw - 1] x [0, ch - 1]`).
pub fn crop_sample(s: &Sample, x0: usize, y0: usize, cw: usize, ch: usize) -> Sample {
    let w = s.width;
    let flow = crop_plane(&s.flow, w, 2, x0, y0, cw, ch);
    let mut valid = crop_plane(&s.valid, w, 1, x0, y0, cw, ch);
    clear_valid_outside(&flow, &mut valid, cw, ch);
    Sample {
        address: s.address,
        source_id: s.source_id.clone(),
        width: cw,
        height: ch,
        image1: crop_plane(&s.image1, w, 3, x0, y0, cw, ch),
        image2: crop_plane(&s.image2, w, 3, x0, y0, cw, ch),
        flow,
        valid,
        occlusion: crop_plane(&s.occlusion, w, 1, x0, y0, cw, ch),
        mask1: crop_plane(&s.mask1, w, 1, x0, y0, cw, ch),
        mask2: crop_plane(&s.mask2, w, 1, x0, y0, cw, ch),
        camera: s.camera.clone(),
        objects: s.objects.clone(),
        depth1: crop_plane(&s.depth1, w, 1, x0, y0, cw, ch),
        depth2: crop_plane(&s.depth2, w, 1, x0, y0, cw, ch),
        holes: crop_plane(&s.holes, w, 1, x0, y0, cw, ch),
        inpainted_pixels: s.inpainted_pixels,
        backward: crop_link(&s.backward, w, x0, y0, cw, ch),
        clip: s
            .clip
            .iter()
            .map(|f| ClipFrame {
                image: crop_plane(&f.image, w, 3, x0, y0, cw, ch),
                forward: crop_link(&f.forward, w, x0, y0, cw, ch),
                backward: crop_link(&f.backward, w, x0, y0, cw, ch),
                mask: crop_plane(&f.mask, w, 1, x0, y0, cw, ch),
                depth: crop_plane(&f.depth, w, 1, x0, y0, cw, ch),
                holes: crop_plane(&f.holes, w, 1, x0, y0, cw, ch),
            })
            .collect(),
        skipped_sources: s.skipped_sources,
        provenance: s.provenance.clone(),
        intrinsics: crate::geometry::Intrinsics::new(
            s.intrinsics.fx,
            s.intrinsics.fy,
            s.intrinsics.cx - x0 as f64,
            s.intrinsics.cy - y0 as f64,
        ),
        timings: s.timings,
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

/// The stacked tensors of a clip (see [`clip_field_name`]).
fn clip_tensors(s: &mut Sample, out: &OutputSpec, tensors: &mut Vec<pb::Tensor>) -> Vec<pb::Field> {
    let (w, h) = (s.width, s.height);
    let k = s.clip.len() + 2;
    let mut pair_fields = Vec::new();
    let mut images_done = false;
    for &f in &out.fields {
        let Some(name) = clip_field_name(f) else {
            pair_fields.push(f);
            continue;
        };
        let cat_u8 = |first: &[u8], rest: &mut dyn Iterator<Item = &[u8]>| -> Vec<u8> {
            let mut v = first.to_vec();
            for r in rest {
                v.extend_from_slice(r);
            }
            v
        };
        let cat_f32 = |first: &[f32], rest: &mut dyn Iterator<Item = &[f32]>| -> Vec<f32> {
            let mut v = first.to_vec();
            for r in rest {
                v.extend_from_slice(r);
            }
            v
        };
        let t = match f {
            pb::Field::Image1 | pb::Field::Image2 => {
                if images_done {
                    continue;
                }
                images_done = true;
                let mut v = cat_u8(&s.image1, &mut std::iter::once(s.image2.as_slice()));
                for c in &s.clip {
                    v.extend_from_slice(&c.image);
                }
                u8_tensor(name, &[k, h, w, 3], v, out.lz4)
            }
            pb::Field::Flow => {
                let v = cat_f32(&s.flow, &mut s.clip.iter().map(|c| c.forward.flow.as_slice()));
                float_tensor(name, &[k - 1, h, w, 2], v, out.flow_f16, out.lz4)
            }
            pb::Field::FlowBackward => {
                let v = cat_f32(&s.backward.flow, &mut s.clip.iter().map(|c| c.backward.flow.as_slice()));
                float_tensor(name, &[k - 1, h, w, 2], v, out.flow_f16, out.lz4)
            }
            pb::Field::Valid => {
                let v = cat_u8(&s.valid, &mut s.clip.iter().map(|c| c.forward.valid.as_slice()));
                u8_tensor(name, &[k - 1, h, w], v, out.lz4)
            }
            pb::Field::Occlusion => {
                let v = cat_u8(&s.occlusion, &mut s.clip.iter().map(|c| c.forward.occlusion.as_slice()));
                u8_tensor(name, &[k - 1, h, w], v, out.lz4)
            }
            pb::Field::ValidBackward => {
                let v = cat_u8(&s.backward.valid, &mut s.clip.iter().map(|c| c.backward.valid.as_slice()));
                u8_tensor(name, &[k - 1, h, w], v, out.lz4)
            }
            pb::Field::OcclusionBackward => {
                let v = cat_u8(&s.backward.occlusion, &mut s.clip.iter().map(|c| c.backward.occlusion.as_slice()));
                u8_tensor(name, &[k - 1, h, w], v, out.lz4)
            }
            _ => continue,
        };
        tensors.push(t);
    }
    pair_fields
}

fn motion_pb(m: &Motion) -> pb::Motion {
    pb::Motion {
        law: m.law.clone(),
        translation: m.translation.to_vec(),
        axis_angle: m.axis_angle.to_vec(),
        rotation: m.rotation.iter().flatten().copied().collect(),
        rotation_kind: match m.rotation_kind {
            RotationKind::AxisAngle => "axis-angle".into(),
            RotationKind::EulerZyx => "euler-zyx".into(),
        },
        angles: m.angles.to_vec(),
    }
}

/// Encodes a (cropped) sample for the wire, moving its buffers. `crop` is the window's corner in
/// the rendered frame; `intrinsics` are the rendered frame's (shifted here).
pub fn to_proto(
    mut s: Sample,
    dataset: &str,
    intrinsics: Intrinsics,
    crop: (usize, usize),
    out: &OutputSpec,
) -> pb::Sample {
    let t = std::time::Instant::now();
    let (w, h) = (s.width, s.height);
    let frames = s.clip.len() + 2;
    let mut tensors = Vec::with_capacity(out.fields.len());
    let pair_fields = if s.clip.is_empty() { out.fields.clone() } else { clip_tensors(&mut s, out, &mut tensors) };
    // the disparity is the flow's; computed before the flow's buffer moves into its tensor
    let mut disparity = pair_fields.contains(&pb::Field::Disparity).then(|| s.disparity());
    for &f in &pair_fields {
        let name = field_name(f);
        let (f16, lz4) = (out.flow_f16, out.lz4);
        let mask = |v: &mut Vec<u8>| u8_tensor(name, &[h, w], std::mem::take(v), lz4);
        let t = match f {
            pb::Field::Image1 => u8_tensor(name, &[h, w, 3], std::mem::take(&mut s.image1), lz4),
            pb::Field::Image2 => u8_tensor(name, &[h, w, 3], std::mem::take(&mut s.image2), lz4),
            pb::Field::Flow => float_tensor(name, &[h, w, 2], std::mem::take(&mut s.flow), f16, lz4),
            pb::Field::Valid => mask(&mut s.valid),
            pb::Field::Occlusion => mask(&mut s.occlusion),
            pb::Field::Mask1 => mask(&mut s.mask1),
            pb::Field::Mask2 => mask(&mut s.mask2),
            pb::Field::Depth1 => float_tensor(name, &[h, w], std::mem::take(&mut s.depth1), false, lz4),
            pb::Field::Depth2 => float_tensor(name, &[h, w], std::mem::take(&mut s.depth2), false, lz4),
            pb::Field::Holes => mask(&mut s.holes),
            pb::Field::FlowBackward => float_tensor(name, &[h, w, 2], std::mem::take(&mut s.backward.flow), f16, lz4),
            pb::Field::ValidBackward => mask(&mut s.backward.valid),
            pb::Field::OcclusionBackward => mask(&mut s.backward.occlusion),
            pb::Field::Disparity => float_tensor(name, &[h, w], disparity.take().unwrap_or_default(), false, lz4),
            pb::Field::Unspecified => continue,
        };
        tensors.push(t);
    }
    let k = Intrinsics::new(intrinsics.fx, intrinsics.fy, intrinsics.cx - crop.0 as f64, intrinsics.cy - crop.1 as f64);
    let tm = &s.timings;
    pb::Sample {
        index: s.address.index,
        dataset: dataset.into(),
        fingerprint: s.address.dataset,
        seed: s.address.seed,
        source_id: std::mem::take(&mut s.source_id),
        width: w as u32,
        height: h as u32,
        tensors,
        camera: Some(motion_pb(&s.camera)),
        objects: s
            .objects
            .iter()
            .map(|o| pb::ObjectMotion {
                label: u32::from(o.label),
                instance: o.instance,
                score: o.score,
                area: o.area,
                motion: Some(motion_pb(&o.motion)),
            })
            .collect(),
        intrinsics: Some(pb::Intrinsics { fx: k.fx, fy: k.fy, cx: k.cx, cy: k.cy }),
        timings: Some(pb::Timings {
            scene_ms: tm.scene_ms,
            render_ms: tm.render_ms,
            objects_ms: tm.objects_ms,
            merge_ms: tm.merge_ms,
            inpaint_ms: tm.inpaint_ms,
            total_ms: tm.total_ms,
            encode_ms: t.elapsed().as_secs_f64() * 1e3,
        }),
        skipped_sources: s.skipped_sources,
        crop_x: crop.0 as u32,
        crop_y: crop.1 as u32,
        inpainted_pixels: s.inpainted_pixels,
        provenance: std::mem::take(&mut s.provenance),
        augment: String::new(),
        frames: frames as u32,
    }
}

/// Errors of decoding a received tensor or sample.
#[derive(Debug, thiserror::Error)]
#[error("tensor {name}: {message}")]
pub struct DecodeError {
    pub name: String,
    pub message: String,
}

fn dtype_size(d: pb::DType) -> Option<usize> {
    match d {
        pb::DType::DtypeU8 => Some(1),
        pb::DType::DtypeF16 => Some(2),
        pb::DType::DtypeF32 => Some(4),
        pb::DType::DtypeUnspecified => None,
    }
}

/// The raw bytes of a tensor (decompressed), checked against its shape, dtype and `raw_size`.
pub fn decode_tensor(t: &pb::Tensor) -> Result<Vec<u8>, DecodeError> {
    raw_view(t).map(Cow::into_owned)
}

/// The raw bytes of a tensor, checked as [`decode_tensor`] does: the received bytes themselves
/// when uncompressed, else the decompressed block.
pub fn raw_view(t: &pb::Tensor) -> Result<Cow<'_, [u8]>, DecodeError> {
    let bad = |message: String| DecodeError { name: t.name.clone(), message };
    let dtype = pb::DType::try_from(t.dtype).map_err(|_| bad(format!("unknown dtype {}", t.dtype)))?;
    let size = dtype_size(dtype).ok_or_else(|| bad("unspecified dtype".into()))?;
    let want = t
        .shape
        .iter()
        .try_fold(size as u64, |a, &d| a.checked_mul(u64::from(d)))
        .ok_or_else(|| bad("shape overflows".into()))?;
    if want != t.raw_size {
        return Err(bad(format!("raw_size {} but shape {:?} x {size} bytes = {want}", t.raw_size, t.shape)));
    }
    let raw = match pb::Compression::try_from(t.compression) {
        Ok(pb::Compression::Lz4) => {
            Cow::Owned(lz4_flex::block::decompress_size_prepended(&t.data).map_err(|e| bad(format!("lz4: {e}")))?)
        }
        Ok(pb::Compression::None | pb::Compression::Unspecified) => Cow::Borrowed(&t.data[..]),
        Err(_) => return Err(bad(format!("unknown compression {}", t.compression))),
    };
    if raw.len() as u64 != want {
        return Err(bad(format!("{} bytes, expected {want}", raw.len())));
    }
    Ok(raw)
}

/// A decoded f32 or f16 tensor as f32 values.
pub fn decode_f32(t: &pb::Tensor) -> Result<Vec<f32>, DecodeError> {
    let raw = raw_view(t)?;
    match pb::DType::try_from(t.dtype) {
        Ok(pb::DType::DtypeF32) => {
            Ok(raw.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect())
        }
        Ok(pb::DType::DtypeF16) => Ok(raw.chunks_exact(2).map(|b| f16::from_le_bytes([b[0], b[1]]).to_f32()).collect()),
        _ => Err(DecodeError { name: t.name.clone(), message: "expected an f32 or f16 tensor".into() }),
    }
}

fn motion_from_pb(m: Option<&pb::Motion>) -> Motion {
    let arr = |v: &[f64]| -> [f64; 3] { [0, 1, 2].map(|i| v.get(i).copied().unwrap_or(0.0)) };
    match m {
        Some(m) => {
            let kind = if m.rotation_kind == "euler-zyx" { RotationKind::EulerZyx } else { RotationKind::AxisAngle };
            let angles = if m.angles.len() == 3 { arr(&m.angles) } else { arr(&m.axis_angle) };
            Motion::new(&m.law, arr(&m.translation), kind, angles)
        }
        None => Motion::new("unknown", [0.0; 3], RotationKind::AxisAngle, [0.0; 3]),
    }
}

/// A received sample as the library's [`Sample`] (for the exporter); fields it does not carry are
/// zero-filled.
pub fn from_proto(s: &pb::Sample) -> Result<Sample, DecodeError> {
    let (w, h) = (s.width as usize, s.height as usize);
    let n = w * h;
    let mut out = Sample {
        address: SampleAddress { dataset: s.fingerprint, seed: s.seed, index: s.index },
        source_id: s.source_id.clone(),
        width: w,
        height: h,
        image1: vec![0; n * 3],
        image2: vec![0; n * 3],
        flow: vec![0.0; n * 2],
        valid: vec![0; n],
        occlusion: vec![0; n],
        mask1: vec![0; n],
        mask2: vec![0; n],
        camera: motion_from_pb(s.camera.as_ref()),
        objects: s
            .objects
            .iter()
            .map(|o| ObjectRecord {
                label: o.label.min(255) as u8,
                instance: o.instance,
                score: o.score,
                area: o.area,
                motion: motion_from_pb(o.motion.as_ref()),
            })
            .collect(),
        depth1: vec![0.0; n],
        depth2: vec![0.0; n],
        holes: vec![0; n],
        inpainted_pixels: s.inpainted_pixels,
        backward: Default::default(),
        clip: Vec::new(),
        skipped_sources: s.skipped_sources,
        provenance: s.provenance.clone(),
        intrinsics: s
            .intrinsics
            .as_ref()
            .map(|k| Intrinsics::new(k.fx, k.fy, k.cx, k.cy))
            .unwrap_or_else(|| Intrinsics::reference_default(w, h)),
        timings: s
            .timings
            .as_ref()
            .map(|t| StageTimings {
                scene_ms: t.scene_ms,
                render_ms: t.render_ms,
                objects_ms: t.objects_ms,
                merge_ms: t.merge_ms,
                inpaint_ms: t.inpaint_ms,
                total_ms: t.total_ms,
            })
            .unwrap_or_default(),
    };
    let frames = (s.frames as usize).max(2);
    if frames > crate::sample::config::MAX_FRAMES {
        return Err(DecodeError { name: "frames".into(), message: format!("{frames} frames (at most 8)") });
    }
    if frames > 2 {
        out.clip = (2..frames)
            .map(|_| ClipFrame {
                image: vec![0; n * 3],
                forward: LinkFields { flow: vec![0.0; n * 2], valid: vec![0; n], occlusion: vec![0; n] },
                mask: vec![0; n],
                depth: vec![0.0; n],
                holes: vec![0; n],
                ..ClipFrame::default()
            })
            .collect();
    }
    for t in &s.tensors {
        if let Some(stack) = stacked(t.name.as_str()) {
            from_stack(t, stack, &mut out, frames)?;
            continue;
        }
        let check = |len: usize, want: usize| {
            if len == want {
                Ok(())
            } else {
                Err(DecodeError { name: t.name.clone(), message: format!("{len} values for a {w} x {h} sample") })
            }
        };
        match t.name.as_str() {
            "flow" => {
                let v = decode_f32(t)?;
                check(v.len(), n * 2)?;
                out.flow = v;
            }
            "flow_backward" => {
                let v = decode_f32(t)?;
                check(v.len(), n * 2)?;
                out.backward.flow = v;
            }
            "valid_backward" | "occlusion_backward" => {
                let v = decode_tensor(t)?;
                check(v.len(), n)?;
                if t.name == "valid_backward" {
                    out.backward.valid = v;
                } else {
                    out.backward.occlusion = v;
                }
            }
            // a disparity without a flow tensor gives the flow (u, v) = (-d, 0)
            "disparity" if !s.tensors.iter().any(|t| t.name == "flow") => {
                let v = decode_f32(t)?;
                check(v.len(), n)?;
                out.flow = v.iter().flat_map(|&d| [0.0 - d, 0.0]).collect();
            }
            "depth1" | "depth2" => {
                let v = decode_f32(t)?;
                check(v.len(), n)?;
                if t.name == "depth1" {
                    out.depth1 = v;
                } else {
                    out.depth2 = v;
                }
            }
            name => {
                let slot = match name {
                    "image1" => &mut out.image1,
                    "image2" => &mut out.image2,
                    "valid" => &mut out.valid,
                    "occlusion" => &mut out.occlusion,
                    "mask1" => &mut out.mask1,
                    "mask2" => &mut out.mask2,
                    "holes" => &mut out.holes,
                    _ => continue,
                };
                let v = decode_tensor(t)?;
                check(v.len(), slot.len())?;
                *slot = v;
            }
        }
    }
    Ok(out)
}

/// What a stacked clip tensor holds.
#[derive(Clone, Copy)]
enum Stack {
    Images,
    Flow { backward: bool },
    Mask { backward: bool, occlusion: bool },
}

fn stacked(name: &str) -> Option<Stack> {
    Some(match name {
        "images" => Stack::Images,
        "flows" => Stack::Flow { backward: false },
        "flows_backward" => Stack::Flow { backward: true },
        "valids" => Stack::Mask { backward: false, occlusion: false },
        "occlusions" => Stack::Mask { backward: false, occlusion: true },
        "valids_backward" => Stack::Mask { backward: true, occlusion: false },
        "occlusions_backward" => Stack::Mask { backward: true, occlusion: true },
        _ => return None,
    })
}

/// Unstacks a clip tensor into the sample's frames and pairs.
fn from_stack(t: &pb::Tensor, stack: Stack, out: &mut Sample, frames: usize) -> Result<(), DecodeError> {
    let n = out.width * out.height;
    let bad = |message: String| DecodeError { name: t.name.clone(), message };
    match stack {
        Stack::Images => {
            let v = raw_view(t)?;
            if v.len() != frames * n * 3 {
                return Err(bad(format!("{} values for {frames} frames of {n} pixels", v.len())));
            }
            let mut parts = v.chunks_exact(n * 3);
            out.image1 = parts.next().unwrap_or_default().to_vec();
            out.image2 = parts.next().unwrap_or_default().to_vec();
            for (c, p) in out.clip.iter_mut().zip(parts) {
                c.image = p.to_vec();
            }
        }
        Stack::Flow { backward } => {
            let v = decode_f32(t)?;
            if v.len() != (frames - 1) * n * 2 {
                return Err(bad(format!("{} values for {} pairs of {n} pixels", v.len(), frames - 1)));
            }
            for (pair, p) in v.chunks_exact(n * 2).enumerate() {
                let slot = match (pair, backward) {
                    (0, false) => &mut out.flow,
                    (0, true) => &mut out.backward.flow,
                    (q, false) => &mut out.clip[q - 1].forward.flow,
                    (q, true) => &mut out.clip[q - 1].backward.flow,
                };
                *slot = p.to_vec();
            }
        }
        Stack::Mask { backward, occlusion } => {
            let v = raw_view(t)?;
            if v.len() != (frames - 1) * n {
                return Err(bad(format!("{} values for {} pairs of {n} pixels", v.len(), frames - 1)));
            }
            for (pair, p) in v.chunks_exact(n).enumerate() {
                let l = match (pair, backward) {
                    (0, false) => None,
                    (0, true) => Some(&mut out.backward),
                    (q, false) => Some(&mut out.clip[q - 1].forward),
                    (q, true) => Some(&mut out.clip[q - 1].backward),
                };
                let slot = match (l, occlusion) {
                    (None, false) => &mut out.valid,
                    (None, true) => &mut out.occlusion,
                    (Some(l), false) => &mut l.valid,
                    (Some(l), true) => &mut l.occlusion,
                };
                *slot = p.to_vec();
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lz4_and_f16_round_trip() {
        let raw: Vec<u8> = (0..1000u32).map(|i| (i % 7) as u8).collect();
        let t = u8_tensor("valid", &[10, 100], raw.clone(), true);
        assert!(t.data.len() < raw.len());
        assert_eq!(u32::from_le_bytes(t.data[..4].try_into().unwrap()), 1000);
        assert_eq!(decode_tensor(&t).unwrap(), raw);
        let flow = [0.5f32, -3.25, 100.0, 0.1];
        let t = float_tensor("flow", &[1, 2, 2], flow.to_vec(), true, false);
        let back = decode_f32(&t).unwrap();
        for (a, b) in flow.iter().zip(&back) {
            assert!((a - b).abs() <= a.abs() * 1e-3, "{a} {b}");
        }
        let mut broken = float_tensor("flow", &[1, 2, 2], flow.to_vec(), false, true);
        broken.data.truncate(6);
        assert!(decode_tensor(&broken).is_err());
    }

    /// A `w` x `h` sample of `frames` frames with every buffer filled from `seed` (floats of any
    /// bit pattern), backward links included.
    fn random_sample(w: usize, h: usize, frames: usize, seed: u64) -> Sample {
        let n = w * h;
        let mut state = seed | 1;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        let mut u8s = |len: usize| (0..len).map(|_| next() as u8).collect::<Vec<u8>>();
        let link = |u8s: &mut dyn FnMut(usize) -> Vec<u8>| LinkFields {
            flow: u8s(n * 8).chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect(),
            valid: u8s(n),
            occlusion: u8s(n),
        };
        let floats = |u8s: &mut dyn FnMut(usize) -> Vec<u8>, k: usize| -> Vec<f32> {
            u8s(k * 4).chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect()
        };
        let first = link(&mut u8s);
        let backward = link(&mut u8s);
        let clip = (2..frames)
            .map(|_| ClipFrame {
                image: u8s(n * 3),
                forward: link(&mut u8s),
                backward: link(&mut u8s),
                ..ClipFrame::default()
            })
            .collect();
        Sample {
            address: SampleAddress { dataset: 1, seed: 2, index: 3 },
            source_id: "t".into(),
            width: w,
            height: h,
            image1: u8s(n * 3),
            image2: u8s(n * 3),
            flow: first.flow,
            valid: first.valid,
            occlusion: first.occlusion,
            mask1: u8s(n),
            mask2: u8s(n),
            camera: Motion::new("x", [0.0; 3], RotationKind::AxisAngle, [0.0; 3]),
            objects: vec![],
            depth1: floats(&mut u8s, n),
            depth2: floats(&mut u8s, n),
            holes: u8s(n),
            inpainted_pixels: 0,
            backward,
            clip,
            skipped_sources: 0,
            provenance: vec![],
            intrinsics: Intrinsics::reference_default(w, h),
            timings: StageTimings::default(),
        }
    }

    fn bits(v: &[f32], f16: bool) -> Vec<u32> {
        v.iter().map(|&x| if f16 { half::f16::from_f32(x).to_f32() } else { x }.to_bits()).collect()
    }

    proptest::proptest! {
        /// Every field through the encoder, prost's bytes and back through the decoding path: the
        /// same values (f16 flow: the value rounded to f16), and a flow tensor's bytes are the
        /// plain per-value little-endian encoding.
        #[test]
        fn samples_round_trip_through_the_wire(
            w in 1usize..7, h in 1usize..6, frames in 2usize..4, seed: u64, flow_f16: bool, lz4: bool,
        ) {
            use prost::Message;
            let s = random_sample(w, h, frames, seed);
            let fields: Vec<pb::Field> = ALL_FIELDS.iter().copied().filter(|&f| f != pb::Field::Disparity).collect();
            let spec = OutputSpec { fields, flow_f16, lz4, crop: None, augment: None };
            let p = to_proto(s.clone(), "d", s.intrinsics, (0, 0), &spec);
            if !flow_f16 && frames == 2 {
                let flow = p.tensors.iter().find(|t| t.name == "flow").unwrap();
                let plain: Vec<u8> = s.flow.iter().flat_map(|x| x.to_le_bytes()).collect();
                proptest::prop_assert_eq!(raw_view(flow).unwrap().into_owned(), plain);
            }
            let back = pb::Sample::decode(p.encode_to_vec().as_slice()).unwrap();
            proptest::prop_assert_eq!(&back, &p);
            let d = from_proto(&back).unwrap();
            proptest::prop_assert_eq!(&d.image1, &s.image1);
            proptest::prop_assert_eq!(&d.image2, &s.image2);
            proptest::prop_assert_eq!(bits(&d.flow, false), bits(&s.flow, flow_f16));
            proptest::prop_assert_eq!(bits(&d.backward.flow, false), bits(&s.backward.flow, flow_f16));
            proptest::prop_assert_eq!((&d.valid, &d.occlusion), (&s.valid, &s.occlusion));
            proptest::prop_assert_eq!((&d.backward.valid, &d.backward.occlusion), (&s.backward.valid, &s.backward.occlusion));
            proptest::prop_assert_eq!((&d.mask1, &d.mask2, &d.holes), (&s.mask1, &s.mask2, &s.holes));
            proptest::prop_assert_eq!(bits(&d.depth1, false), bits(&s.depth1, false));
            proptest::prop_assert_eq!(bits(&d.depth2, false), bits(&s.depth2, false));
            proptest::prop_assert_eq!(d.clip.len(), s.clip.len());
            for (a, b) in d.clip.iter().zip(&s.clip) {
                proptest::prop_assert_eq!(&a.image, &b.image);
                proptest::prop_assert_eq!(bits(&a.forward.flow, false), bits(&b.forward.flow, flow_f16));
                proptest::prop_assert_eq!(bits(&a.backward.flow, false), bits(&b.backward.flow, flow_f16));
                proptest::prop_assert_eq!((&a.forward.valid, &a.forward.occlusion), (&b.forward.valid, &b.forward.occlusion));
                proptest::prop_assert_eq!((&a.backward.valid, &a.backward.occlusion), (&b.backward.valid, &b.backward.occlusion));
            }
        }
    }

    #[test]
    fn crop_clears_valid_where_the_target_leaves() {
        let (w, h) = (6, 4);
        let n = w * h;
        let mut s = Sample {
            address: SampleAddress { dataset: 1, seed: 2, index: 3 },
            source_id: "t".into(),
            width: w,
            height: h,
            image1: (0..n * 3).map(|i| i as u8).collect(),
            image2: vec![0; n * 3],
            flow: vec![0.0; n * 2],
            valid: vec![1; n],
            occlusion: vec![0; n],
            mask1: vec![0; n],
            mask2: vec![0; n],
            camera: Motion::new("x", [0.0; 3], RotationKind::AxisAngle, [0.0; 3]),
            objects: vec![],
            depth1: vec![1.0; n],
            depth2: vec![1.0; n],
            holes: vec![0; n],
            inpainted_pixels: 0,
            backward: Default::default(),
            clip: Vec::new(),
            skipped_sources: 0,
            provenance: vec![],
            intrinsics: Intrinsics::reference_default(w, h),
            timings: StageTimings::default(),
        };
        // every pixel moves 1.5 px right: inside the full frame except the last column
        for i in 0..n {
            s.flow[2 * i] = 1.5;
            s.valid[i] = u8::from(i % w + 2 < w);
        }
        let c = crop_sample(&s, 1, 1, 3, 2);
        assert_eq!((c.width, c.height), (3, 2));
        assert_eq!(&c.image1[..3], &s.image1[3 * (w + 1)..3 * (w + 1) + 3]);
        // crop columns 0..3 are frame columns 1..4; target x + 1.5 <= 2 only for x = 0
        assert_eq!(c.valid, vec![1, 0, 0, 1, 0, 0]);
        let spec = CropSpec { width: 3, height: 2, random: true };
        let a = crop_window(&spec, w, h, s.address).unwrap();
        assert_eq!(Ok(a), crop_window(&spec, w, h, s.address));
        assert!(a.0 + 3 <= w && a.1 + 2 <= h);
        assert_eq!(crop_window(&CropSpec { width: 4, height: 0, random: false }, w, h, s.address), Ok((1, 0, 4, 4)));
        // larger than the frame in one side: refused with both sizes, never shrunk
        let big = crop_window(&CropSpec { width: w as u32 + 1, height: 2, random: false }, w, h, s.address);
        let e = big.unwrap_err();
        assert_eq!(e, CropTooLarge { want_w: w + 1, want_h: 2, w, h });
        assert_eq!(e.to_string(), format!("{}x2 is larger than the rendered frame {w}x{h}", w + 1));
    }
}
