//! The colour kernels of the target render: no ringing leaves a sample
//! (colour within [0, coverage], density, coverage and masks bit-identical to the bilinear
//! render's), every kernel reproduces constants and linear ramps (partition of unity), windows
//! equal the full frame, the reference mode stays bilinear, the prefilter kept with the MPI is
//! the one the renderer would compute, and the higher-order kernels keep a photo's detail under a
//! sub-pixel lateral translation where bilinear loses most of it.

use mpiflow::bench::measure::laplacian_variance;
use mpiflow::geometry::{Intrinsics, Pose};
use mpiflow::io::image::{load_rgb, ImageLimits};
use mpiflow::mpi::{BsplineRgb, Mpi};
use mpiflow::render::resample::bspline_bricks;
use mpiflow::render::resample::prefilter;
use mpiflow::render::{render, render_window, Channels, Fields, Mode, Rect, RenderOutput, RenderParams, Resample};
use std::path::Path;
use std::sync::Arc;

fn params(mpi: &Mpi, pose: Pose, resample: Resample) -> RenderParams {
    let mut p = RenderParams::new(Intrinsics::reference_default(mpi.width, mpi.height), pose);
    p.resample = resample;
    p.fields = Fields { target: true, flow: true, occlusion: true };
    p
}

/// A hard case for ringing: 1-pixel checkerboards of 0 and 1 on a front plane with blocky
/// density (exact zeros next to dense pixels) and on an opaque back plane, one mask channel of
/// 0 / 1 blocks.
fn checker_mpi(w: usize, h: usize) -> Mpi {
    let mut m = Mpi::new(w, h, vec![0.9, 0.3], 1);
    for i in 0..2 {
        for y in 0..h {
            for x in 0..w {
                let o = (i * h * w + y * w + x) * 4;
                let v = ((x + y + i) % 2) as f32;
                m.rgba[o..o + 3].copy_from_slice(&[v, 1.0 - v, v]);
                m.rgba[o + 3] = if i == 1 {
                    1e3
                } else if (x / 5 + y / 3) % 2 == 0 {
                    40.0
                } else {
                    0.0
                };
                m.extras[i * h * w + y * w + x] = ((x / 4 + y / 4) % 2) as f32;
            }
        }
    }
    m
}

fn poses() -> Vec<Pose> {
    vec![
        Pose::from_axis_angle([0.0, 0.0, 0.0], [0.0131, -0.0077, 0.0]),
        Pose::from_axis_angle([0.01, -0.02, 0.005], [0.05, 0.03, -0.1]),
        Pose::from_axis_angle([0.0, 0.0, 0.0], [0.0, 0.0, 0.3]),
    ]
}

#[test]
fn no_kernel_rings_out_of_bounds_and_density_masks_and_flow_stay_bilinear() {
    let mpi = checker_mpi(48, 40);
    for pose in poses() {
        let base = render::<f32>(&mpi, &params(&mpi, pose, Resample::Bilinear), None).unwrap();
        for r in Resample::ALL {
            let mut m = mpi.clone();
            prefilter(&mut m, r);
            let out = render::<f32>(&m, &params(&m, pose, r), None).unwrap();
            assert_eq!(out.stats.repaired, 0);
            for (i, &c) in out.coverage.iter().enumerate() {
                assert!((0.0..=1.0).contains(&c), "{r}: coverage {c}");
                for k in 0..3 {
                    let v = out.image[3 * i + k];
                    assert!(v >= 0.0 && v <= c + 1e-6, "{r}: colour {v} with coverage {c} at {i}");
                }
                let e = out.extras[i];
                assert!((0.0..=1.0 + 1e-6).contains(&e), "{r}: mask {e}");
            }
            // the kernel changes colour only
            assert_eq!(out.coverage, base.coverage, "{r}");
            assert_eq!(out.depth, base.depth, "{r}");
            assert_eq!(out.extras, base.extras, "{r}");
            assert_eq!(out.flow, base.flow, "{r}");
            assert_eq!(out.valid, base.valid, "{r}");
            assert_eq!(out.occlusion, base.occlusion, "{r}");
            if r != Resample::Bilinear && pose.translation.z == 0.0 {
                assert_ne!(out.image, base.image, "{r} renders like bilinear");
            }
        }
    }
}

/// One opaque plane at depth 2 holding `colour(x, y)`.
fn opaque_plane(w: usize, h: usize, colour: impl Fn(usize, usize) -> [f32; 3]) -> Mpi {
    let mut m = Mpi::new(w, h, vec![0.5], 0);
    for y in 0..h {
        for x in 0..w {
            let o = (y * w + x) * 4;
            m.rgba[o..o + 3].copy_from_slice(&colour(x, y));
            m.rgba[o + 3] = 1e4;
        }
    }
    m
}

fn render_with(mpi: &Mpi, pose: Pose, r: Resample) -> RenderOutput {
    let mut m = mpi.clone();
    prefilter(&mut m, r);
    render::<f32>(&m, &params(&m, pose, r), None).unwrap()
}

#[test]
fn every_kernel_reproduces_constants_and_linear_ramps() {
    let (w, h) = (56, 44);
    let constant = opaque_plane(w, h, |_, _| [0.3, 0.6, 0.9]);
    let ramp = opaque_plane(w, h, |x, y| {
        let (x, y) = (x as f32, y as f32);
        [0.1 + 0.012 * x + 0.004 * y, 0.8 - 0.01 * x + 0.002 * y, 0.05 + 0.015 * y]
    });
    let pose = Pose::from_axis_angle([0.0, 0.0, 0.004], [0.0213, -0.0147, 0.0]);
    let lin = render_with(&ramp, pose, Resample::Bilinear);
    for r in Resample::ALL {
        let out = render_with(&constant, pose, r);
        for (i, &c) in out.coverage.iter().enumerate() {
            for (k, want) in [0.3f32, 0.6, 0.9].into_iter().enumerate() {
                let v = out.image[3 * i + k];
                assert!((v - want * c).abs() < 2e-6, "{r}: constant {want} became {v} (coverage {c})");
            }
        }
        // bilinear is exact on a ramp, so every kernel that reproduces ramps agrees with it
        // away from the mirrored borders (the shift is about 1 px); the normalised Lanczos
        // window reproduces ramps only nearly (its weights' first moment is not exactly 0)
        let tol = if r == Resample::Lanczos3 { 1e-3 } else { 1e-4 };
        let out = render_with(&ramp, pose, r);
        let margin = 8;
        for y in margin..h - margin {
            for x in margin..w - margin {
                for k in 0..3 {
                    let i = 3 * (y * w + x) + k;
                    assert!(
                        (out.image[i] - lin.image[i]).abs() < tol,
                        "{r} at ({x}, {y}): {} vs {}",
                        out.image[i],
                        lin.image[i]
                    );
                }
            }
        }
    }
}

#[test]
fn windows_equal_the_full_frame_and_the_prefilter_is_the_renderers() {
    let mpi = checker_mpi(48, 40);
    let mask: Vec<f32> = (0..48 * 40).map(|i| ((i % 48) / 6 % 2) as f32).collect();
    let pose = poses()[1];
    for r in Resample::ALL {
        // without coefficients the renderer computes them: the same bytes
        let mut m = mpi.clone();
        prefilter(&mut m, r);
        let cached = render::<f32>(&m, &params(&m, pose, r), None).unwrap();
        let fresh = render::<f32>(&mpi, &params(&mpi, pose, r), None).unwrap();
        assert_eq!(cached.image, fresh.image, "{r}");
        let p = params(&m, pose, r);
        let full = render_window::<f32>(&m, &p, None, &Rect::full(48, 40), Channels::Broadcast(&mask), None).unwrap();
        let win = Rect { x0: 5, y0: 7, x1: 37, y1: 29 };
        let part = render_window::<f32>(&m, &p, None, &win, Channels::Broadcast(&mask), None).unwrap();
        for y in win.y0..win.y1 {
            for x in win.x0..win.x1 {
                let (i, j) = (y * 48 + x, (y - win.y0) * win.width() + x - win.x0);
                assert_eq!(full.out.image[3 * i..3 * i + 3], part.out.image[3 * j..3 * j + 3], "{r} ({x}, {y})");
                assert_eq!(full.out.extras[i], part.out.extras[j]);
            }
        }
    }
}

#[test]
fn the_reference_mode_stays_bilinear() {
    let mpi = checker_mpi(32, 24);
    let pose = poses()[1];
    let mut p = params(&mpi, pose, Resample::Bilinear);
    p.mode = Mode::Reference;
    let base = render::<f32>(&mpi, &p, None).unwrap();
    for r in Resample::ALL {
        let out = render::<f32>(&mpi, &RenderParams { resample: r, ..p }, None).unwrap();
        assert_eq!(out.image, base.image, "{r}");
    }
}

/// Rounds a [0, 1] rgb render to u8.
fn to_u8(v: &[f32]) -> Vec<u8> {
    v.iter().map(|&x| (x.clamp(0.0, 1.0) * 255.0).round() as u8).collect()
}

/// The sharpness ratio (variance of the Laplacian of the render over that of the photo, on the
/// covered interior) of a photo on one opaque plane under sub-pixel lateral translations: one
/// resampling of the photo. Bilinear keeps about a third of the Laplacian energy; the
/// higher-order kernels keep twice as much or more (bounds with a margin below the measured
/// values, which the test prints).
#[test]
fn higher_order_kernels_keep_a_photos_detail_under_lateral_translation() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/photos");
    let photo = load_rgb(&root.join("coffee.png"), &ImageLimits::default()).unwrap();
    let (w, h) = (photo.width, photo.height);
    let mpi = opaque_plane(w, h, |x, y| {
        let o = 3 * (y * w + x);
        [photo.data[o], photo.data[o + 1], photo.data[o + 2]]
    });
    let photo_u8 = to_u8(&photo.data);
    let inside = |x: usize, y: usize| x >= 8 && y >= 8 && x + 8 < w && y + 8 < h;
    let v1 = laplacian_variance(&photo_u8, w, h, |i| inside(i % w, i / w)).unwrap();
    // depth 2, fx = 0.58 W: tx = 2 d / fx shifts by d pixels
    let fx = 0.58 * w as f64;
    let shifts = [(0.5, 0.5), (0.3, -0.6), (-0.45, 0.2), (2.5, 1.5)];
    let mut mean = std::collections::BTreeMap::new();
    for r in Resample::ALL {
        let mut sum = 0.0;
        for &(dx, dy) in &shifts {
            let pose = Pose::from_axis_angle([0.0, 0.0, 0.0], [2.0 * dx / fx, 2.0 * dy / fx, 0.0]);
            let out = render_with(&mpi, pose, r);
            let img = to_u8(&out.image);
            let v2 = laplacian_variance(&img, w, h, |i| inside(i % w, i / w) && out.coverage[i] > 0.999).unwrap();
            sum += v2 / v1;
        }
        let m = sum / shifts.len() as f64;
        println!("{r}: sharpness {m:.3}");
        mean.insert(r.name(), m);
    }
    // measured (2-core VM): bilinear 0.318, bicubic 0.538, bspline3 0.695, bspline5 0.802,
    // lanczos3 0.751 (half-pixel shifts are the hardest case: they cancel the highest frequency)
    assert!(mean["bilinear"] < 0.4, "{mean:?}");
    assert!(mean["bicubic"] > 0.48, "{mean:?}");
    assert!(mean["bspline3"] > 0.62, "{mean:?}");
    assert!(mean["bspline5"] > mean["bspline3"] && mean["bspline5"] > 0.72, "{mean:?}");
    assert!(mean["lanczos3"] > 0.67, "{mean:?}");
    // OMOMS-3: the cubic B-spline's taps, about the quintic's detail
    assert!(mean["omoms3"] > mean["bspline3"] + 0.05 && mean["omoms3"] > 0.72, "{mean:?}");
}

/// The ideal warp of the quality report (`bench::quality::ideal_warp_sharpness`): image1's
/// quintic B-spline interpolates the photo (its value at every pixel centre is the pixel's), and a
/// sample whose camera does not move warps image1 to itself, so both ratios, the ideal warp's and
/// image2's over the same pixels, are 1.
#[test]
fn the_ideal_warp_interpolates_and_an_unmoved_camera_keeps_every_detail() {
    use mpiflow::bench::quality::ideal_warp_sharpness;
    use mpiflow::render::resample::SplineImage;
    use mpiflow::sample::config::{MotionSpec, SampleConfig};
    use mpiflow::sample::motion::{Component, MotionPreset};
    use mpiflow::sample::pipeline::{open_source, OpenOptions, Pipeline, SourceSpec};
    use mpiflow::scene::cache::SceneCache;
    use mpiflow::scene::models::ModelConfig;
    use std::sync::Arc;

    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let photo = load_rgb(&root.join("examples/photos/coffee.png"), &ImageLimits::default()).unwrap();
    let (w, h) = (photo.width, photo.height);
    let spline = SplineImage::new(&photo.data, w, h);
    for (x, y) in [(0, 0), (w - 1, h - 1), (17, 3), (w / 2, h / 3), (5, h - 2)] {
        let got = spline.sample(x as f32, y as f32);
        for (c, g) in got.iter().enumerate() {
            let want = photo.data[3 * (y * w + x) + c];
            assert!((g - want).abs() < 1e-4, "({x}, {y}) channel {c}: {g} against {want}");
        }
    }

    let mut still = MotionPreset::Reference.ranges();
    still.name = "still".into();
    for law in [&mut still.camera, &mut still.object] {
        for c in [
            &mut law.translation.x,
            &mut law.translation.y,
            &mut law.translation.z,
            &mut law.rotation.x,
            &mut law.rotation.y,
            &mut law.rotation.z,
        ] {
            *c = Component::constant(0.0);
        }
    }
    let config = SampleConfig {
        motion: MotionSpec::Ranges(Box::new(still)),
        max_objects: 0,
        backward: true,
        ..SampleConfig::default()
    };
    let stage = Arc::new(ModelConfig::default().build_stage().unwrap());
    let source = open_source(&SourceSpec::Path(root.join("examples/data")), &OpenOptions::default()).unwrap();
    let p = Pipeline::new(source, stage, Arc::new(SceneCache::new(1 << 28)), config).unwrap();
    let s = p.generator().sample(0, 0).unwrap();
    let (ideal, image2) = ideal_warp_sharpness(&s).unwrap();
    println!("unmoved camera: ideal warp {ideal:.4}, image2 {image2:.4}");
    assert!((ideal - 1.0).abs() < 1e-3, "ideal warp {ideal}");
    assert!((image2 - 1.0).abs() < 0.05, "image2 {image2}");
}

/// Standard deviation of the luminance-free grey value (channel 0) of `img` over the pixels of
/// the target that are fully covered and at least 4 pixels from anything uncovered.
fn covered_std(out: &RenderOutput) -> f64 {
    let (w, h) = (out.width, out.height);
    let full = |x: usize, y: usize| out.coverage[y * w + x] > 0.999;
    let mut v = Vec::new();
    for y in 4..h - 4 {
        for x in 4..w - 4 {
            if (0..9).all(|k| full(x + 4 * (k % 3) - 4, y + 4 * (k / 3) - 4)) {
                v.push(f64::from(out.image[3 * (y * w + x)]));
            }
        }
    }
    assert!(v.len() > 1000, "too few covered pixels: {}", v.len());
    let m = v.iter().sum::<f64>() / v.len() as f64;
    (v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / v.len() as f64).sqrt()
}

/// Alias-free minification: a grating of 0.4 cycles per pixel (below the
/// Nyquist limit, so image1 shows it faithfully) on one plane, the camera moving back so the
/// plane shrinks to half size: image2 would show it at 0.8 cycles per pixel, beyond the limit, so
/// a faithful image2 shows (almost) nothing there, while point sampling folds it into a strong
/// 0.2-cycle pattern image1 does not have. With `minify` that alias is gone; a coarse grating
/// (0.05 cycles) survives the same shrinking; and a view that shrinks nothing, the density,
/// coverage and flow are bit for bit those of the render without it.
#[test]
fn minification_removes_the_alias_and_keeps_what_the_view_can_show() {
    let (w, h) = (256, 192);
    let grating = |f: f64| {
        opaque_plane(w, h, move |x, _| {
            let v = (0.5 + 0.4 * (2.0 * std::f64::consts::PI * f * x as f64).sin()) as f32;
            [v, v, v]
        })
    };
    // depth 2 -> 4: every source step of 2 pixels is one target pixel at the centre
    let back = Pose::from_axis_angle([0.0, 0.0, 0.0], [0.0, 0.0, 2.0]);
    let render_minify = |mpi: &Mpi, pose: Pose, r: Resample, minify: bool| {
        let mut m = mpi.clone();
        prefilter(&mut m, r);
        let mut p = params(&m, pose, r);
        p.minify = minify;
        render::<f32>(&m, &p, None).unwrap()
    };
    assert!(
        (mpiflow::render::mip::plane_lod(&params(&grating(0.4), back, Resample::Bilinear), 0.5).unwrap() - 1.0).abs()
            < 1e-9
    );
    for r in [Resample::Bilinear, Resample::Bspline3] {
        let fine = grating(0.4);
        let plain = render_minify(&fine, back, r, false);
        let mip = render_minify(&fine, back, r, true);
        let (a, b) = (covered_std(&plain), covered_std(&mip));
        println!("{r}: fine grating, std of image2 {a:.4} without minify, {b:.4} with");
        assert!(a > 0.1, "{r}: point sampling aliases the fine grating ({a})");
        assert!(b < 0.1 * a, "{r}: minify leaves {b} of {a}");
        assert_eq!(plain.coverage, mip.coverage);
        assert_eq!(plain.depth, mip.depth);
        assert_eq!(plain.flow, mip.flow);
        assert_eq!(plain.valid, mip.valid);

        let coarse = grating(0.05);
        let (a, b) =
            (covered_std(&render_minify(&coarse, back, r, false)), covered_std(&render_minify(&coarse, back, r, true)));
        println!("{r}: coarse grating, std {a:.4} without, {b:.4} with");
        assert!(b > 0.85 * a, "{r}: minify keeps a coarse grating: {b} of {a}");

        // a forward motion magnifies: nothing changes
        let fwd = Pose::from_axis_angle([0.01, -0.02, 0.0], [0.1, 0.05, -0.5]);
        assert_eq!(render_minify(&fine, fwd, r, false).image, render_minify(&fine, fwd, r, true).image);

        // the levels kept with a prepared scene give the same bytes as levels built per render,
        // at moderate and extreme shrinking (beyond the levels kept)
        for far in [2.0, 3.5, 60.0] {
            let pose = Pose::from_axis_angle([0.0, 0.02, 0.0], [0.05, 0.0, far]);
            let mut cached = std::sync::Arc::new(fine.clone());
            prefilter(std::sync::Arc::make_mut(&mut cached), r);
            mpiflow::render::mip::prefilter_arc(&mut cached);
            assert!(cached.mip.is_some());
            let mut p = params(&cached, pose, r);
            p.minify = true;
            let with = render::<f32>(&cached, &p, None).unwrap();
            assert_eq!(with.image, render_minify(&fine, pose, r, true).image, "{r} back by {far}");
        }

        // a window of the minified view is the full frame's, pixel for pixel
        let mut m = fine.clone();
        prefilter(&mut m, r);
        let mut p = params(&m, back, r);
        p.minify = true;
        let win = Rect { x0: 40, y0: 30, x1: 200, y1: 150 };
        let wr = render_window::<f32>(&m, &p, None, &win, Channels::PerPlane, None).unwrap();
        for y in win.y0..win.y1 {
            for x in win.x0..win.x1 {
                let (i, j) = (y * w + x, (y - win.y0) * win.width() + x - win.x0);
                assert_eq!(mip.image[3 * i..3 * i + 3], wr.out.image[3 * j..3 * j + 3], "{r} ({x}, {y})");
            }
        }
    }
}

/// The cached scene keeps only the blocks of B-spline coefficients the colour kernel can reach
/// (where a plane has density): renders from them are the renders from every block, bit for
/// bit, for both B-spline degrees, in windows and full frames, under lateral, rotating,
/// forward and backward motions, and the store holds far fewer blocks.
#[test]
fn sparse_coefficients_render_the_bits_of_all_of_them() {
    let (w, h) = (160, 96);
    let mut m = Mpi::new(w, h, vec![0.9, 0.5, 0.2], 0);
    for i in 0..3 {
        for y in 0..h {
            for x in 0..w {
                let o = (i * h * w + y * w + x) * 4;
                let v = ((x * 13 + y * 7 + i * 5) % 17) as f32 / 16.0;
                m.rgba[o..o + 3].copy_from_slice(&[v, 1.0 - v, (v * 3.0) % 1.0]);
                // a disc, a thin ring, a corner block and lines on the first column and row of a
                // block (the blocks before them are reached by their bilinear taps): most blocks
                // of each plane are empty
                let (dx, dy) = (x as f64 - 50.0 - 30.0 * i as f64, y as f64 - 48.0);
                let r = (dx * dx + dy * dy).sqrt();
                let dense = match i {
                    0 => r < 14.0,
                    1 => (r - 30.0).abs() < 1.0,
                    _ => (x >= w - 9 && y >= h - 5) || (x == 64 && y < 40) || (y == 80 && x < 48),
                };
                m.rgba[o + 3] = if dense { 2.0 + (x % 3) as f32 } else { 0.0 };
            }
        }
    }
    let poses = [
        Pose::from_axis_angle([0.0, 0.0, 0.0], [0.0131, -0.0077, 0.0]),
        Pose::from_axis_angle([0.01, -0.02, 0.005], [0.05, 0.03, -0.1]),
        Pose::from_axis_angle([0.0, 0.0, 0.0], [0.0, 0.0, 0.3]),
        Pose::from_axis_angle([0.0, 0.03, 0.0], [-0.02, 0.0, 0.8]),
    ];
    for r in [Resample::Bspline3, Resample::Bspline5, Resample::Omoms3] {
        let prefilter_of = r.prefilter().unwrap();
        let mut sparse = m.clone();
        prefilter(&mut sparse, r);
        let kept = sparse.bspline_rgb.as_ref().unwrap().coefficients.stored();
        assert!(kept.0 * 3 < kept.1, "{r}: {} of {} blocks kept", kept.0, kept.1);
        let mut full = m.clone();
        full.bspline_rgb = Some(BsplineRgb {
            prefilter: prefilter_of,
            coefficients: Arc::new(bspline_bricks(&m, prefilter_of, false)),
        });
        assert_eq!(full.bspline_rgb.as_ref().unwrap().coefficients.stored().0, kept.1);
        assert!(sparse.byte_size() < full.byte_size());
        for pose in poses {
            let a = render::<f32>(&sparse, &params(&sparse, pose, r), None).unwrap();
            let b = render::<f32>(&full, &params(&full, pose, r), None).unwrap();
            assert_eq!(a.image, b.image, "{r} {pose:?}");
            assert_eq!(a.flow, b.flow);
            let win = Rect { x0: 30, y0: 20, x1: 131, y1: 77 };
            let wa = render_window::<f32>(&sparse, &params(&sparse, pose, r), None, &win, Channels::PerPlane, None);
            let wb = render_window::<f32>(&full, &params(&full, pose, r), None, &win, Channels::PerPlane, None);
            assert_eq!(wa.unwrap().out.image, wb.unwrap().out.image, "{r} {pose:?} window");
        }
    }
}
