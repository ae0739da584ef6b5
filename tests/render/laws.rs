//! Laws that hold for every input, checked with proptest on the pure functions: a pose composed
//! with its inverse is the identity (and composition is application in turn), COCO RLE encodes and
//! decodes back to the same mask and counts, crop windows always lie inside the image, and the
//! ranks of a world partition the indices (rank `r` of `W` gets exactly `start + r + kW`, every
//! index once).

use std::collections::BTreeMap;

use glam::DVec3;
use mpiflow::geometry::Pose;
use mpiflow::raster::{rle_decode_counts, rle_encode, rle_from_string, rle_to_string};
use mpiflow::sample::SampleAddress;
use mpiflow::service::encode::{crop_window, CropSpec};
use mpiflow::service::pool::StreamSpec;
use proptest::prelude::*;

fn pose() -> impl Strategy<Value = Pose> {
    let angle = -3.1f64..3.1;
    let shift = -50.0f64..50.0;
    (angle.clone(), angle.clone(), angle, shift.clone(), shift.clone(), shift)
        .prop_map(|(a, b, c, x, y, z)| Pose::from_axis_angle([a, b, c], [x, y, z]))
}

fn near(a: DVec3, b: DVec3, tol: f64) -> bool {
    (a - b).abs().max_element() <= tol * (1.0 + b.abs().max_element())
}

fn is_identity(p: &Pose, tol: f64) -> bool {
    p.rotation.abs_diff_eq(glam::DMat3::IDENTITY, tol) && p.translation.abs().max_element() <= tol
}

proptest! {
    #[test]
    fn a_pose_after_its_inverse_is_the_identity(p in pose()) {
        prop_assert!(is_identity(&p.compose(&p.inverse()), 1e-9), "{:?}", p.compose(&p.inverse()));
        prop_assert!(is_identity(&p.inverse().compose(&p), 1e-9), "{:?}", p.inverse().compose(&p));
    }

    #[test]
    fn composing_is_applying_in_turn(a in pose(), b in pose(), x in -20.0f64..20.0, y in -20.0f64..20.0, z in 0.1f64..40.0) {
        let v = DVec3::new(x, y, z);
        let ab = a.compose(&b);
        prop_assert!(near(ab.apply(v), a.apply(b.apply(v)), 1e-9));
        // exactly the recipe's formula: rotation a.r b.r, translation a.r b.t + a.t
        prop_assert_eq!(ab.rotation, a.rotation * b.rotation);
        prop_assert_eq!(ab.translation, a.rotation * b.translation + a.translation);
        prop_assert!(is_identity(&Pose::identity().compose(&a).compose(&a.inverse()), 1e-9));
    }

    #[test]
    fn rle_decodes_to_the_mask_it_encodes(h in 1usize..24, w in 1usize..24, seed in any::<u64>(), density in 0u64..=8) {
        // a mask of runs and speckles: pixel i set when a hash of (seed, i) falls under the density
        let mask: Vec<u8> = (0..h * w)
            .map(|i| {
                let v = (seed ^ (i as u64 / 3)).wrapping_mul(0x9e37_79b9_7f4a_7c15) >> 61;
                u8::from(v < density)
            })
            .collect();
        let counts = rle_encode(&mask, h, w);
        prop_assert_eq!(counts.iter().map(|&c| u64::from(c)).sum::<u64>(), (h * w) as u64);
        prop_assert_eq!(rle_decode_counts(&counts, h, w).unwrap(), mask.clone());
        // and through COCO's compressed string
        let text = rle_to_string(&counts);
        prop_assert_eq!(rle_from_string(&text).unwrap(), counts.clone());
        prop_assert_eq!(rle_decode_counts(&rle_from_string(&text).unwrap(), h, w).unwrap(), mask);
    }

    #[test]
    fn rle_strings_round_trip_any_counts(counts in proptest::collection::vec(any::<u32>(), 0..40)) {
        prop_assert_eq!(rle_from_string(&rle_to_string(&counts)).unwrap(), counts);
    }

    #[test]
    fn crop_windows_lie_inside_the_image(
        w in 1usize..4000,
        h in 1usize..4000,
        cw in 0u32..5000,
        ch in 0u32..5000,
        random in any::<bool>(),
        dataset in any::<u64>(),
        seed in any::<u64>(),
        index in any::<u64>(),
    ) {
        let spec = CropSpec { width: cw, height: ch, random };
        let address = SampleAddress { dataset, seed, index };
        let side = |asked: u32, side: usize| if asked == 0 { side } else { asked as usize };
        let (want_w, want_h) = (side(cw, w), side(ch, h));
        if want_w > w || want_h > h {
            // larger than the image: refused with both sizes, never shrunk
            let e = crop_window(&spec, w, h, address).unwrap_err();
            prop_assert_eq!((e.want_w, e.want_h, e.w, e.h), (want_w, want_h, w, h));
            return Ok(());
        }
        let (x0, y0, ww, hh) = crop_window(&spec, w, h, address).unwrap();
        prop_assert!(ww >= 1 && hh >= 1);
        prop_assert!(x0 + ww <= w && y0 + hh <= h, "({x0}, {y0}, {ww}, {hh}) in {w} x {h}");
        // the asked size (0 = the image's)
        prop_assert_eq!((ww, hh), (want_w, want_h));
        if !random {
            prop_assert_eq!((x0, y0), ((w - ww) / 2, (h - hh) / 2));
        }
        // the same address, the same window
        prop_assert_eq!(crop_window(&spec, w, h, address), Ok((x0, y0, ww, hh)));
    }

    #[test]
    fn ranks_partition_the_indices(start in 0u64..1_000_000, world in 1u64..9, per_rank in 1u64..50) {
        // (count 0 would be an endless stream)
        let spec = |rank: u64| StreamSpec {
            start_index: start,
            rank,
            world_size: world,
            count: per_rank,
            batch_size: 1,
            prefetch: 1,
            max_message_bytes: 1 << 20,
        };
        let mut owner: BTreeMap<u64, u64> = BTreeMap::new();
        for r in 0..world {
            let s = spec(r);
            prop_assert_eq!(s.len(), per_rank);
            for k in 0..s.len() {
                let i = s.index(k).unwrap();
                prop_assert_eq!(i, start + r + k * world);
                prop_assert!(owner.insert(i, r).is_none(), "index {} given to ranks {:?} and {}", i, owner.get(&i), r);
            }
        }
        // together the ranks cover start .. start + W * n, each index once
        let all: Vec<u64> = owner.keys().copied().collect();
        prop_assert_eq!(all, (start..start + world * per_rank).collect::<Vec<_>>());
    }

    #[test]
    fn an_endless_rank_stops_at_the_end_of_the_index_space(start in (u64::MAX - 1000)..=u64::MAX, world in 1u64..9, rank in 0u64..9) {
        let rank = rank % world;
        let s = StreamSpec { start_index: start, rank, world_size: world, count: 0, batch_size: 1, prefetch: 1, max_message_bytes: 1 };
        let n = s.len();
        for k in 0..n {
            prop_assert_eq!(s.index(k), Some(start + rank + k * world));
        }
        prop_assert_eq!(s.index(n), None, "position {} of {} is past the end", n, n);
        // every index is below 2^64 - 1, and the cursor after the last one is the end: a
        // request resuming from it gets nothing (no repeat, no skip)
        if n > 0 {
            prop_assert!(s.index(n - 1).unwrap() < u64::MAX);
        }
        let (next, resume) = s.cursor(n);
        prop_assert_eq!(next, u64::MAX);
        let again = StreamSpec { start_index: resume, ..s };
        prop_assert_eq!(again.len(), 0);
        // the cursor inside the stream is the next index, never one already sent
        for k in 0..n {
            prop_assert_eq!(s.cursor(k).0, s.index(k).unwrap());
        }
    }
}
