//! Laws of the one renderer over windows: a windowed render is the same
//! window of the full-frame render, bit for bit (per-plane and broadcast channels, any window
//! alignment, with and without `flow_where`); render(1 - U) = coverage - render(U) for a
//! broadcast mask U; a broadcast channel is the same as per-plane extras holding the mask on
//! every plane, and the same inside a rectangle when it is needed only there, whatever the
//! colour kernel; no NaN or Inf leaves a window, whatever the pose; bad requests are errors.
//! Each law holds for true-depth MPIs too (texels at their own disparity, `Mpi::surface`).

use mpiflow::geometry::{Intrinsics, Pose};
use mpiflow::mpi::Mpi;
use mpiflow::render::{
    render, render_window, Channels, Fields, Mode, Rect, RenderError, RenderOutput, RenderParams, Resample, Skip, View,
    WindowRender,
};
use mpiflow::rng::SplitMix64 as Stream;
use mpiflow::sample::object::mpi_with_mask;
use proptest::prelude::*;

/// `planes` planes of `w` x `h` with random colours, two random extra channels, and densities
/// that are exactly 0 over random blocks (so tile skipping has work to skip); the farthest plane
/// is opaque. With `far_zero` the farthest plane sits at disparity 0.
fn random_mpi(w: usize, h: usize, planes: usize, seed: u64, far_zero: bool) -> Mpi {
    let mut r = Stream(seed);
    let mut disp: Vec<f64> = (0..planes).map(|i| 1.0 - 0.9 * i as f64 / (planes - 1) as f64).collect();
    if far_zero {
        disp[planes - 1] = 0.0;
    }
    let mut m = Mpi::new(w, h, disp, 2);
    for i in 0..planes {
        // a block of 8 x 8 pixels is empty on this plane with probability 1/2
        let empty: Vec<bool> = (0..w.div_ceil(8) * h.div_ceil(8)).map(|_| r.next_u64().is_multiple_of(2)).collect();
        for y in 0..h {
            for x in 0..w {
                let o = (i * h * w + y * w + x) * 4;
                for c in 0..3 {
                    m.rgba[o + c] = r.unit_f32();
                }
                m.rgba[o + 3] = if i + 1 == planes {
                    1e3
                } else if empty[(y / 8) * w.div_ceil(8) + x / 8] {
                    0.0
                } else {
                    5.0 * r.unit_f32()
                };
            }
        }
    }
    m.extras.iter_mut().for_each(|v| *v = r.unit_f32());
    m
}

/// Gives `mpi` a true-depth surface ([`Mpi::surface`]): a random slope in disparity with a
/// step (a depth edge), over the planes' range and beyond it on both sides (so the slabs clamp).
fn with_surface(mpi: &mut Mpi, seed: u64) {
    let mut r = Stream(seed ^ 0x5eed);
    let (a, b, c) = (r.unit_f32(), r.unit_f32(), r.unit_f32());
    let (w, h) = (mpi.width, mpi.height);
    let disparity = (0..w * h)
        .map(|p| {
            let (x, y) = ((p % w) as f32 / w as f32, (p / w) as f32 / h as f32);
            0.05 + 0.5 * (a * x + b * y) + if x > c { 0.3 } else { 0.0 }
        })
        .collect();
    mpi.surface = Some(std::sync::Arc::new(mpiflow::mpi::Surface { disparity }));
}

/// A soft disc of radius `rad` at (`cx`, `cy`), 0 outside: a mask with an exact-zero region.
fn disc(w: usize, h: usize, cx: f32, cy: f32, rad: f32) -> Vec<f32> {
    let mut m = vec![0.0f32; w * h];
    for y in 0..h {
        for x in 0..w {
            let d = ((x as f32 - cx).powi(2) + (y as f32 - cy).powi(2)).sqrt();
            m[y * w + x] = ((rad - d) / 2.0 + 0.5).clamp(0.0, 1.0);
        }
    }
    m
}

fn params(mpi: &Mpi, pose: Pose, skip: Skip) -> RenderParams {
    let mut p = RenderParams::new(Intrinsics::reference_default(mpi.width, mpi.height), pose);
    p.skip = skip;
    p.fields = Fields { target: true, flow: true, occlusion: false };
    p
}

/// Every field of the window render `wr` equals the full-frame render `full` (frame width `w`)
/// at the same pixel, bit for bit; with `flow_where` the source view equals it where the mask is
/// > 0 and is 0 elsewhere.
fn assert_is_window_of(full: &RenderOutput, wr: &WindowRender, w: usize, flow_where: Option<&[f32]>) {
    let (win, o) = (wr.win, &wr.out);
    assert_eq!((o.width, o.height), (win.width(), win.height()));
    assert_eq!(o.extra_channels, full.extra_channels);
    let c = o.extra_channels;
    for y in win.y0..win.y1 {
        for x in win.x0..win.x1 {
            let (f, i) = (y * w + x, wr.index(x, y).unwrap());
            let same = |a: &[f32], b: &[f32], what: &str| {
                let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(a), bits(b), "{what} at ({x}, {y}) in {win:?}: {a:?} vs {b:?}");
            };
            same(&o.image[3 * i..3 * i + 3], &full.image[3 * f..3 * f + 3], "image");
            same(&o.depth[i..=i], &full.depth[f..=f], "depth");
            same(&o.coverage[i..=i], &full.coverage[f..=f], "coverage");
            same(&o.extras[c * i..c * i + c], &full.extras[c * f..c * f + c], "extras");
            let computed = flow_where.is_none_or(|m| m[f] > 0.0);
            if computed {
                same(&o.flow[2 * i..2 * i + 2], &full.flow[2 * f..2 * f + 2], "flow");
                same(&o.source_depth_in_target[i..=i], &full.source_depth_in_target[f..=f], "source depth");
                if !o.source_depth.is_empty() {
                    same(&o.source_depth[i..=i], &full.source_depth[f..=f], "the source camera's depth");
                }
                assert_eq!(o.valid[i], full.valid[f], "valid at ({x}, {y}) in {win:?}");
            } else {
                assert_eq!(&o.flow[2 * i..2 * i + 2], &[0.0, 0.0]);
                assert_eq!(o.source_depth_in_target[i], 0.0);
                assert!(o.source_depth.get(i).is_none_or(|&d| d == 0.0));
                assert_eq!(o.valid[i], 0);
            }
        }
    }
}

fn assert_finite(o: &RenderOutput, what: &str) {
    for (name, buf) in [
        ("image", &o.image),
        ("depth", &o.depth),
        ("coverage", &o.coverage),
        ("extras", &o.extras),
        ("flow", &o.flow),
        ("source depth", &o.source_depth_in_target),
    ] {
        if let Some(i) = buf.iter().position(|v| !v.is_finite()) {
            panic!("{what}: {name}[{i}] = {}", buf[i]);
        }
    }
}

/// A window of a `w` x `h` frame from four unit numbers (never empty).
fn window(w: usize, h: usize, a: [f64; 4]) -> Rect {
    let x0 = (a[0] * w as f64) as usize % w;
    let y0 = (a[1] * h as f64) as usize % h;
    let x1 = x0 + 1 + (a[2] * (w - x0) as f64) as usize % (w - x0);
    let y1 = y0 + 1 + (a[3] * (h - y0) as f64) as usize % (h - y0);
    Rect { x0, y0, x1, y1 }
}

const W: usize = 37;
const H: usize = 29;

fn pose_strategy() -> impl Strategy<Value = Pose> {
    (prop::array::uniform3(-0.08f64..0.08), prop::array::uniform3(-0.3f64..0.3))
        .prop_map(|(r, t)| Pose::from_axis_angle(r, t))
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    /// Law (a): a windowed render equals the same window of the full-frame render, bit for bit,
    /// with the MPI's own (per-plane) channels and with a broadcast mask, for random windows
    /// (any alignment to the 16-pixel tiles and bands) and random poses, with tile skipping and
    /// early ray termination on or off; `flow_where` restricts the source view exactly.
    #[test]
    fn a_window_is_the_same_window_of_the_full_frame(
        seed in any::<u64>(),
        planes in 4usize..=6,
        pose in pose_strategy(),
        corners in prop::array::uniform4(0.0f64..1.0),
        skip_on in any::<bool>(),
        centre in prop::array::uniform2(0.0f32..1.0),
        true_depth in any::<bool>(),
    ) {
        let mut mpi = random_mpi(W, H, planes, seed, seed.is_multiple_of(3));
        if true_depth {
            with_surface(&mut mpi, seed);
        }
        let skip = if skip_on { Skip::DEFAULT } else { Skip::NONE };
        let p = params(&mpi, pose, skip);
        let win = window(W, H, corners);
        // per-plane channels
        let full = render::<f32>(&mpi, &p, None).unwrap();
        let wr = render_window::<f32>(&mpi, &p, None, &win, Channels::PerPlane, None).unwrap();
        assert_is_window_of(&full, &wr, W, None);
        prop_assert_eq!(wr.out.stats.repaired, 0);
        // a broadcast mask, against the full frame of the same broadcast
        let mask = disc(W, H, centre[0] * W as f32, centre[1] * H as f32, 6.0);
        let full_b = render_window::<f32>(&mpi, &p, None, &Rect::full(W, H), Channels::Broadcast(&mask), None).unwrap();
        let wr_b = render_window::<f32>(&mpi, &p, None, &win, Channels::Broadcast(&mask), None).unwrap();
        assert_is_window_of(&full_b.out, &wr_b, W, None);
        // the source view only where the mask is > 0
        let wr_m = render_window::<f32>(&mpi, &p, None, &win, Channels::Broadcast(&mask), Some(&mask)).unwrap();
        assert_is_window_of(&full_b.out, &wr_m, W, Some(&mask));
        // the broadcast needed only inside `win`, on a full frame with the other colour kernel:
        // the same coverage, and inside `win` the same channel (its weights are the density's);
        // outside, the same or 0
        let mut pk = p;
        pk.resample = if p.resample == Resample::Bilinear { Resample::Bspline3 } else { Resample::Bilinear };
        let within = Channels::BroadcastWithin(&mask, [win.x0, win.y0, win.x1, win.y1]);
        let fw = render_window::<f32>(&mpi, &pk, None, &Rect::full(W, H), within, None).unwrap().out;
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        prop_assert_eq!(bits(&fw.coverage), bits(&full_b.out.coverage));
        prop_assert_eq!(bits(&fw.depth), bits(&full_b.out.depth));
        for (i, (&got, &want)) in fw.extras.iter().zip(&full_b.out.extras).enumerate() {
            let (x, y) = (i % W, i / W);
            let inside = x >= win.x0 && x < win.x1 && y >= win.y0 && y < win.y1;
            prop_assert!(got.to_bits() == want.to_bits() || (!inside && got == 0.0), "({}, {}): {} vs {}", x, y, got, want);
        }
    }

    /// The source view takes four pixels at a time in f32 lanes (sixteen on AVX-512), with or
    /// without a `flow_where` mask; a window one pixel wide runs the scalar loop, which stays
    /// the reference. Over random MPIs, poses (also ones that carry the camera through and
    /// behind the planes), both skipping settings and with a link (which asks for the source
    /// camera's own depth), every column equals the full frame's lanes in every field, and the
    /// masked render equals it where the mask is > 0 and is 0 elsewhere. The frame (37 px) is
    /// not a multiple of 4, so rows end in scalar pixels.
    #[test]
    fn the_source_views_lanes_give_the_scalar_loops_bits(
        seed in any::<u64>(),
        planes in 4usize..=8,
        r in prop::array::uniform3(-0.5f64..0.5),
        t in prop::array::uniform3(-3.0f64..3.0),
        skip_on in any::<bool>(),
        link in any::<bool>(),
        centre in prop::array::uniform2(0.0f32..1.0),
        true_depth in any::<bool>(),
    ) {
        let mut mpi = random_mpi(W, H, planes, seed, seed.is_multiple_of(3));
        if true_depth {
            with_surface(&mut mpi, seed);
        }
        let skip = if skip_on { Skip::DEFAULT } else { Skip::NONE };
        let mut p = params(&mpi, Pose::from_axis_angle(r, t), skip);
        if link {
            p.links = [Some(View::Source), None];
        }
        let full = Rect::full(W, H);
        let lanes = render_window::<f32>(&mpi, &p, None, &full, Channels::PerPlane, None).unwrap().out;
        prop_assert!(lanes.flow.iter().any(|v| *v != 0.0), "the pose moves something");
        prop_assert_eq!(lanes.source_depth.is_empty(), !link);
        for x in 0..W {
            let column = Rect { x0: x, y0: 0, x1: x + 1, y1: H };
            let column = render_window::<f32>(&mpi, &p, None, &column, Channels::PerPlane, None).unwrap();
            assert_is_window_of(&lanes, &column, W, None);
        }
        let mask = disc(W, H, centre[0] * W as f32, centre[1] * H as f32, 9.0);
        let masked = render_window::<f32>(&mpi, &p, None, &full, Channels::PerPlane, Some(&mask)).unwrap();
        assert_is_window_of(&lanes, &masked, W, Some(&mask));
    }

    /// Both passes take four adjacent pixels at a time in f32 lanes where they can (the target
    /// view sixteen, reading packed planes in registers, on AVX-512); a window one pixel wide
    /// leaves no four pixels in a row, so it runs the scalar loops, which stay the reference.
    /// Over random MPIs, dense or packed as a prepared scene is, poses (also ones that carry the
    /// camera through and behind the planes), both skipping settings, three colour kernels and
    /// with no extra channel or a broadcast mask (the cases the target view's lanes take), every
    /// pixel of the full frame equals its one-pixel-wide column's, bit for bit, in every field.
    #[test]
    fn the_lanes_give_the_scalar_loops_bits(
        seed in any::<u64>(),
        planes in 4usize..=8,
        r in prop::array::uniform3(-0.5f64..0.5),
        t in prop::array::uniform3(-3.0f64..3.0),
        skip_on in any::<bool>(),
        kernel in 0usize..3,
        broadcast in any::<bool>(),
        centre in prop::array::uniform2(0.0f32..1.0),
        packed in any::<bool>(),
        true_depth in any::<bool>(),
    ) {
        let mut mpi = random_mpi(W, H, planes, seed, seed.is_multiple_of(3));
        if true_depth {
            with_surface(&mut mpi, seed);
        }
        mpi.extras.clear();
        mpi.extra_channels = 0;
        let skip = if skip_on { Skip::DEFAULT } else { Skip::NONE };
        let mut p = params(&mpi, Pose::from_axis_angle(r, t), skip);
        p.resample = [Resample::Bilinear, Resample::Bspline3, Resample::Bicubic][kernel];
        if packed {
            mpiflow::render::resample::prefilter(&mut mpi, p.resample);
            if mpiflow::render::store::packs(p.mode, p.resample, false) {
                mpiflow::render::store::pack(&mut mpi);
            }
        }
        let mask = disc(W, H, centre[0] * W as f32, centre[1] * H as f32, 9.0);
        let ch = if broadcast { Channels::Broadcast(&mask) } else { Channels::PerPlane };
        let full = render_window::<f32>(&mpi, &p, None, &Rect::full(W, H), ch, None).unwrap();
        prop_assert!(full.out.coverage.iter().any(|&c| c > 0.0), "something is seen");
        for x in 0..W {
            let column = render_window::<f32>(&mpi, &p, None, &Rect { x0: x, y0: 0, x1: x + 1, y1: H }, ch, None).unwrap();
            assert_is_window_of(&full.out, &column, W, None);
        }
    }

    /// Law (b): for a broadcast mask U, render(1 - U) = coverage - render(U). Stated tolerance:
    /// 1e-5 absolute (both sides are sums of at most 6 weighted bilinear samples in f32, coverage
    /// <= 1), in every window.
    #[test]
    fn the_complement_mask_renders_as_coverage_minus_the_mask(
        seed in any::<u64>(),
        pose in pose_strategy(),
        corners in prop::array::uniform4(0.0f64..1.0),
        centre in prop::array::uniform2(0.0f32..1.0),
    ) {
        let mpi = random_mpi(W, H, 5, seed, false);
        let mut p = params(&mpi, pose, Skip::DEFAULT);
        p.fields.flow = false;
        let u = disc(W, H, centre[0] * W as f32, centre[1] * H as f32, 8.0);
        let inv: Vec<f32> = u.iter().map(|v| 1.0 - v).collect();
        for win in [Rect::full(W, H), window(W, H, corners)] {
            let ru = render_window::<f32>(&mpi, &p, None, &win, Channels::Broadcast(&u), None).unwrap().out;
            let ri = render_window::<f32>(&mpi, &p, None, &win, Channels::Broadcast(&inv), None).unwrap().out;
            for i in 0..ru.coverage.len() {
                let d = (ri.extras[i] - (ru.coverage[i] - ru.extras[i])).abs();
                prop_assert!(d <= 1e-5, "pixel {} of {:?}: render(1-U) {} vs coverage - render(U) {}",
                    i, win, ri.extras[i], ru.coverage[i] - ru.extras[i]);
            }
        }
    }

    /// Law (c): a broadcast channel is the same, bit for bit, as per-plane extras holding the
    /// mask on every plane (the reference's MPI copy), full frame and windows, every field.
    #[test]
    fn a_broadcast_channel_is_a_per_plane_copy_of_the_mask(
        seed in any::<u64>(),
        pose in pose_strategy(),
        corners in prop::array::uniform4(0.0f64..1.0),
        centre in prop::array::uniform2(0.0f32..1.0),
    ) {
        let mpi = random_mpi(W, H, 6, seed, seed.is_multiple_of(2));
        let p = params(&mpi, pose, Skip::DEFAULT);
        let mask = disc(W, H, centre[0] * W as f32, centre[1] * H as f32, 7.0);
        let copy = mpi_with_mask(&mpi, &mask);
        for win in [Rect::full(W, H), window(W, H, corners)] {
            let b = render_window::<f32>(&mpi, &p, None, &win, Channels::Broadcast(&mask), None).unwrap().out;
            let c = render_window::<f32>(&copy, &p, None, &win, Channels::PerPlane, None).unwrap().out;
            prop_assert_eq!(b.extra_channels, 1);
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            for (name, x, y) in [
                ("image", &b.image, &c.image),
                ("depth", &b.depth, &c.depth),
                ("coverage", &b.coverage, &c.coverage),
                ("extras", &b.extras, &c.extras),
                ("flow", &b.flow, &c.flow),
                ("source depth", &b.source_depth_in_target, &c.source_depth_in_target),
            ] {
                prop_assert_eq!(bits(x), bits(y), "{} in {:?}", name, win);
            }
            prop_assert_eq!(&b.valid, &c.valid);
        }
    }

    /// Law (d): no NaN or Inf in any window output, for extreme poses (large and tiny
    /// translations, rotations up to pi, cameras that pass the planes or look along them), and a
    /// plane at disparity 0.
    #[test]
    fn no_nonfinite_values_leave_a_window(
        seed in any::<u64>(),
        axis in prop::array::uniform3(-1.0f64..1.0),
        angle in 0.0f64..std::f64::consts::PI,
        dir in prop::array::uniform3(-1.0f64..1.0),
        scale_exp in -12i32..7,
        corners in prop::array::uniform4(0.0f64..1.0),
        centre in prop::array::uniform2(0.0f32..1.0),
    ) {
        let mpi = random_mpi(W, H, 5, seed, true);
        let n = (axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2]).sqrt().max(1e-9);
        let aa = [axis[0] / n * angle, axis[1] / n * angle, axis[2] / n * angle];
        let s = 10f64.powi(scale_exp);
        let pose = Pose::from_axis_angle(aa, [dir[0] * s, dir[1] * s, dir[2] * s]);
        let mask = disc(W, H, centre[0] * W as f32, centre[1] * H as f32, 9.0);
        for skip in [Skip::DEFAULT, Skip::NONE] {
            let p = params(&mpi, pose, skip);
            for win in [Rect::full(W, H), window(W, H, corners)] {
                for (ch, fw) in [(Channels::PerPlane, None), (Channels::Broadcast(&mask), Some(mask.as_slice()))] {
                    let r = render_window::<f32>(&mpi, &p, None, &win, ch, fw).unwrap();
                    assert_finite(&r.out, &format!("{pose:?} {win:?}"));
                }
            }
        }
    }
}

#[test]
fn occlusion_is_computed_for_the_full_frame_only() {
    let mpi = random_mpi(W, H, 5, 7, false);
    let mut p = params(&mpi, Pose::from_axis_angle([0.02, -0.03, 0.01], [0.2, -0.1, -0.2]), Skip::DEFAULT);
    p.fields = Fields::default();
    let full = render::<f32>(&mpi, &p, None).unwrap();
    assert_eq!(full.occlusion.len(), W * H);
    let same = render_window::<f32>(&mpi, &p, None, &Rect::full(W, H), Channels::PerPlane, None).unwrap();
    assert_eq!(same.out.occlusion, full.occlusion);
    let part = Rect { x0: 3, y0: 2, x1: 30, y1: 20 };
    let wr = render_window::<f32>(&mpi, &p, None, &part, Channels::PerPlane, None).unwrap();
    assert!(wr.out.occlusion.is_empty());
    assert_is_window_of(&full, &wr, W, None);
}

#[test]
fn an_empty_window_renders_nothing() {
    let mpi = random_mpi(W, H, 4, 1, false);
    let p = params(&mpi, Pose::from_axis_angle([0.0; 3], [0.1, 0.0, 0.0]), Skip::DEFAULT);
    let r =
        render_window::<f32>(&mpi, &p, None, &Rect { x0: 5, y0: 5, x1: 5, y1: 9 }, Channels::PerPlane, None).unwrap();
    assert_eq!((r.out.width, r.out.height), (0, 4));
    assert!(r.out.image.is_empty() && r.out.flow.is_empty() && r.out.valid.is_empty());
}

#[test]
fn bad_requests_are_errors() {
    let mpi = random_mpi(W, H, 4, 2, false);
    let p = params(&mpi, Pose::from_axis_angle([0.0; 3], [0.1, 0.0, 0.0]), Skip::DEFAULT);
    let request = |r: Result<WindowRender, RenderError>| matches!(r, Err(RenderError::Request(_)));
    let outside = Rect { x0: 10, y0: 0, x1: W + 1, y1: H };
    assert!(request(render_window::<f32>(&mpi, &p, None, &outside, Channels::PerPlane, None)));
    let short = vec![1.0f32; W * H - 1];
    let full = Rect::full(W, H);
    assert!(request(render_window::<f32>(&mpi, &p, None, &full, Channels::Broadcast(&short), None)));
    assert!(request(render_window::<f32>(&mpi, &p, None, &full, Channels::PerPlane, Some(&short))));
    let mut r = p;
    r.mode = Mode::Reference;
    let part = Rect { x0: 0, y0: 0, x1: 10, y1: 10 };
    assert!(request(render_window::<f32>(&mpi, &r, None, &part, Channels::PerPlane, None)));
    let ones = vec![1.0f32; W * H];
    assert!(request(render_window::<f32>(&mpi, &r, None, &full, Channels::Broadcast(&ones), None)));
    // the reference mode's full frame with its own channels is render()
    let a = render_window::<f32>(&mpi, &r, None, &full, Channels::PerPlane, None).unwrap().out;
    let b = render::<f32>(&mpi, &r, None).unwrap();
    assert_eq!(a.image, b.image);
    assert_eq!(a.flow, b.flow);
}
