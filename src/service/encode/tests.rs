//! The unit tests of the wire format: compression and f16, a sample's round trip, the crop.

use super::*;
use crate::geometry::Intrinsics;
use crate::sample::motion::{Motion, RotationKind};
use crate::sample::{ClipFrame, LinkFields, Sample, SampleAddress, StageTimings};
use crate::service::pb;
use crate::service::tensor::{float_tensor, u8_tensor};

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
        let p = to_proto(s.clone(), "d", (0, 0), &spec);
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
