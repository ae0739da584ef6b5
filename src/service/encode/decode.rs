//! The way back: a received tensor's bytes (read in place when uncompressed) and a received
//! sample as the library's `Sample`, a clip's stacked tensors unstacked.

use std::borrow::Cow;

use half::f16;

use crate::geometry::Intrinsics;
use crate::sample::motion::{Motion, RotationKind};
use crate::sample::{ClipFrame, LinkFields, ObjectRecord, Sample, SampleAddress, StageTimings};
use crate::service::pb;

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
    let mut out = zero_filled(s);
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
        from_tensor(t, s, &mut out)?;
    }
    Ok(out)
}

/// The sample of a received message's metadata, every field zero-filled (the pair's only).
fn zero_filled(s: &pb::Sample) -> Sample {
    let (w, h) = (s.width as usize, s.height as usize);
    let n = w * h;
    Sample {
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
    }
}

/// One tensor of a pair's field (not stacked) into `out`; a tensor of no field is skipped.
fn from_tensor(t: &pb::Tensor, s: &pb::Sample, out: &mut Sample) -> Result<(), DecodeError> {
    let (w, h) = (s.width as usize, s.height as usize);
    let n = w * h;
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
                _ => return Ok(()),
            };
            let v = decode_tensor(t)?;
            check(v.len(), slot.len())?;
            *slot = v;
        }
    }
    Ok(())
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
