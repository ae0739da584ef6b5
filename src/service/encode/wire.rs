//! A sample on the wire: its tensors (pairs, and a clip's stacked tensors) and its message,
//! moving the sample's buffers.

use super::fields::{clip_field_name, field_name, OutputSpec};
use crate::sample::motion::{Motion, RotationKind};
use crate::sample::Sample;
use crate::service::pb;
use crate::service::tensor::{float_tensor, u8_tensor};

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
/// the rendered frame (the sample's intrinsics are already the window's).
pub fn to_proto(mut s: Sample, dataset: &str, crop: (usize, usize), out: &OutputSpec) -> pb::Sample {
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
    let k = s.intrinsics;
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
