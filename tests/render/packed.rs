//! A packed MPI (`render::store::pack`: the planes in 16 x 16 blocks, only those a render can
//! read, as a prepared scene keeps them) renders the same bits as its dense planes, on every
//! path: both passes, the lanes and the scalar loops (odd windows, `flow_where`), links
//! (backward flow), the three kernels a prepared scene packs for, f32 and f64, the reference
//! mode, the density cut of the object and background renders, the tile occupancy. (What it
//! saves on real scenes: `tests/samples/scene_cache.rs`, docs/performance.md.)

use mpiflow::geometry::{Intrinsics, Pose};
use mpiflow::mpi::Mpi;
use mpiflow::render::cut::render_cut;
use mpiflow::render::resample::prefilter;
use mpiflow::render::store::{pack, packs};
use mpiflow::render::{
    render, render_window, Channels, DensityCut, Fields, Mode, Occupancy, Rect, RenderOutput, RenderParams, Resample,
    Skip, View,
};
use mpiflow::rng::SplitMix64 as Stream;
use proptest::prelude::*;

/// Planes with density in a few discs each (and on single pixels on block borders), colour
/// everywhere (as a layered MPI has), one extra channel; the last plane opaque where `opaque`.
fn sparse_mpi(w: usize, h: usize, planes: usize, seed: u64, opaque: bool) -> Mpi {
    let mut r = Stream(seed);
    let disp: Vec<f64> = (0..planes).map(|i| 1.0 - 0.9 * i as f64 / (planes - 1) as f64).collect();
    let mut m = Mpi::new(w, h, disp, 1);
    for i in 0..planes {
        let discs: Vec<(f32, f32, f32)> =
            (0..3).map(|_| (r.unit_f32() * w as f32, r.unit_f32() * h as f32, 2.0 + 9.0 * r.unit_f32())).collect();
        let edge = (16 * (1 + r.next_u64() as usize % 2), 16 * (1 + r.next_u64() as usize % 2));
        for y in 0..h {
            for x in 0..w {
                let o = (i * h * w + y * w + x) * 4;
                for c in 0..3 {
                    m.rgba[o + c] = r.unit_f32();
                }
                let inside = discs.iter().any(|&(cx, cy, rad)| (x as f32 - cx).hypot(y as f32 - cy) < rad);
                m.rgba[o + 3] = if i + 1 == planes && opaque {
                    1e3
                } else if inside || (x, y) == edge || (x == edge.0 && y < 5) {
                    0.5 + 4.0 * r.unit_f32()
                } else {
                    0.0
                };
            }
        }
    }
    m.extras.iter_mut().for_each(|v| *v = r.unit_f32());
    m
}

fn params(mpi: &Mpi, pose: Pose, resample: Resample) -> RenderParams {
    let mut p = RenderParams::new(Intrinsics::reference_default(mpi.width, mpi.height), pose);
    p.resample = resample;
    p.fields = Fields { target: true, flow: true, occlusion: true };
    p
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

fn assert_same(a: &RenderOutput, b: &RenderOutput, what: &str) {
    assert_eq!(bits(&a.image), bits(&b.image), "{what}: image");
    assert_eq!(bits(&a.depth), bits(&b.depth), "{what}: depth");
    assert_eq!(bits(&a.coverage), bits(&b.coverage), "{what}: coverage");
    assert_eq!(bits(&a.extras), bits(&b.extras), "{what}: extras");
    assert_eq!(bits(&a.flow), bits(&b.flow), "{what}: flow");
    assert_eq!(bits(&a.source_depth_in_target), bits(&b.source_depth_in_target), "{what}: source depth in target");
    assert_eq!(bits(&a.source_depth), bits(&b.source_depth), "{what}: source depth");
    assert_eq!(a.valid, b.valid, "{what}: valid");
    assert_eq!(a.occlusion, b.occlusion, "{what}: occlusion");
    for (la, lb) in a.links.iter().zip(&b.links) {
        assert_eq!(bits(&la.flow), bits(&lb.flow), "{what}: link flow");
        assert_eq!(bits(&la.depth), bits(&lb.depth), "{what}: link depth");
    }
    assert!(a.image.iter().all(|v| v.is_finite()) && a.flow.iter().all(|v| v.is_finite()), "{what}: finite");
}

const W: usize = 75;
const H: usize = 53;

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    #[test]
    fn a_packed_mpi_renders_the_bits_of_its_dense_planes(
        seed in any::<u64>(),
        planes in 3usize..=6,
        opaque in any::<bool>(),
        r in prop::array::uniform3(-0.3f64..0.3),
        t in prop::array::uniform3(-0.6f64..0.6),
        kernel in 0usize..3,
        skip_on in any::<bool>(),
    ) {
        let resample = [Resample::Bilinear, Resample::Bspline3, Resample::Bspline5][kernel];
        prop_assert!(packs(Mode::Exact, resample, false));
        let mut dense = sparse_mpi(W, H, planes, seed, opaque);
        prefilter(&mut dense, resample);
        let mut packed = dense.clone();
        pack(&mut packed);
        prop_assert!(packed.is_packed() && packed.rgba.is_empty());
        packed.validate().unwrap();
        let pose = Pose::from_axis_angle(r, t);
        let mut p = params(&dense, pose, resample);
        p.skip = if skip_on { Skip::DEFAULT } else { Skip::NONE };

        // full frames (the lanes), f32 and f64, with and without the tile occupancy
        let a = render::<f32>(&dense, &p, None).unwrap();
        prop_assert!(a.coverage.iter().any(|&c| c > 0.0));
        assert_same(&a, &render::<f32>(&packed, &p, None).unwrap(), "f32");
        let (od, op) = (Occupancy::build(&dense, 0.0), Occupancy::build(&packed, 0.0));
        prop_assert_eq!(&od.plane_any, &op.plane_any);
        assert_same(&render::<f32>(&dense, &p, Some(&od)).unwrap(), &render::<f32>(&packed, &p, Some(&op)).unwrap(), "occupancy");
        assert_same(&render::<f64>(&dense, &p, None).unwrap(), &render::<f64>(&packed, &p, None).unwrap(), "f64");

        // odd windows (scalar pixels), a flow_where mask (the scalar source loop), links
        let win = Rect { x0: 3, y0: 7, x1: 3 + 37, y1: 7 + 29 };
        let mut lp = p;
        lp.fields.occlusion = false;
        lp.links = [Some(View::Source), Some(View::Pose(Pose::from_axis_angle([0.0, 0.05, 0.0], [0.1, 0.0, 0.2])))];
        let some: Vec<f32> = (0..W * H).map(|k| (k % 3) as f32).collect();
        for (ch, fw) in [(Channels::PerPlane, None), (Channels::PerPlane, Some(&some[..]))] {
            let wa = render_window::<f32>(&dense, &lp, None, &win, ch, fw).unwrap();
            let wb = render_window::<f32>(&packed, &lp, None, &win, ch, fw).unwrap();
            assert_same(&wa.out, &wb.out, "window with links");
        }

        // the density cut (moved objects' and the background's renders)
        let mask: Vec<f32> = (0..W * H).map(|k| if k % 7 < 3 { 1.0 } else { 0.25 }).collect();
        let last: Vec<u8> = (0..W * H).map(|k| (k % planes) as u8).collect();
        let cut = DensityCut { mask: &mask, last: &last };
        let ca = render_cut::<f32>(&dense, &p, None, &win, &cut).unwrap();
        let cb = render_cut::<f32>(&packed, &p, None, &win, &cut).unwrap();
        assert_same(&ca.out, &cb.out, "cut");

        // the reference mode and the unpacked copy
        if kernel == 0 {
            let mut rp = p;
            rp.mode = Mode::Reference;
            assert_same(&render::<f32>(&dense, &rp, None).unwrap(), &render::<f32>(&packed, &rp, None).unwrap(), "reference");
        }
        let unpacked = packed.unpacked();
        assert_same(&a, &render::<f32>(&unpacked, &p, None).unwrap(), "unpacked");
    }
}

/// What the prepared scene packs for: the exact mode with bilinear or B-spline colour and no
/// minification; not the reference mode, the kernels that read colour around the density
/// (bicubic, Lanczos), or minification.
#[test]
fn what_is_packed() {
    assert!(packs(Mode::Exact, Resample::Bspline3, false));
    assert!(!packs(Mode::Exact, Resample::Bspline3, true));
    assert!(!packs(Mode::Reference, Resample::Bilinear, false));
    assert!(!packs(Mode::Exact, Resample::Bicubic, false));
    assert!(!packs(Mode::Exact, Resample::Lanczos3, false));
}
