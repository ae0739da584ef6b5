//! The built-in RGB-D layering (`mpi::layering`): identity renders reproduce the image, analytic
//! scenes (constant depth, a tilted plane, a square in front of a wall) render as they should,
//! disocclusions show background, unknown depths and bad inputs are handled.

use mpiflow::geometry::{Intrinsics, Pose};
use mpiflow::mpi::layering::*;
use mpiflow::mpi::Mpi;
use mpiflow::render::{render, Mode, RenderOutput, RenderParams, Skip};

fn opts(planes: usize, layering: Layering) -> LayeringOptions {
    LayeringOptions { planes, layering, disparity_range: None, backdrop: false, ..LayeringOptions::default() }
}

/// A smooth but varied texture in [0, 1].
fn texture(w: usize, h: usize) -> Vec<f32> {
    let mut rgb = vec![0.0f32; w * h * 3];
    for y in 0..h {
        for x in 0..w {
            let (xf, yf) = (x as f32, y as f32);
            let p = 3 * (y * w + x);
            rgb[p] = 0.5 + 0.4 * (0.31 * xf + 0.17 * yf).sin();
            rgb[p + 1] = 0.5 + 0.4 * (0.23 * yf - 0.11 * xf).cos();
            rgb[p + 2] = ((x * 7 + y * 13) % 17) as f32 / 16.0;
        }
    }
    rgb
}

fn solid(w: usize, h: usize, c: [f32; 3]) -> Vec<f32> {
    (0..w * h).flat_map(|_| c).collect()
}

fn render_with(mpi: &Mpi, pose: Pose) -> RenderOutput {
    let k = Intrinsics::reference_default(mpi.width, mpi.height);
    let mut p = RenderParams::new(k, pose);
    p.mode = Mode::Exact;
    p.skip = Skip::NONE;
    let out = render::<f32>(mpi, &p, None).unwrap();
    assert_eq!(out.stats.repaired, 0);
    out
}

fn check_structure(mpi: &Mpi) {
    mpi.validate().unwrap();
    assert!(mpi.rgba.iter().all(|v| v.is_finite()), "non-finite value in the MPI");
    assert!(mpi.disparity.iter().all(|&d| d.is_finite() && d >= 0.0));
    assert!(mpi.disparity.windows(2).all(|p| p[1] < p[0]));
    assert!(mpi.rgba.chunks_exact(4).all(|px| px[3] >= 0.0));
    // the farthest plane is opaque everywhere
    let last = mpi.plane_rgba(mpi.planes() - 1);
    assert!(last.chunks_exact(4).all(|px| px[3] > 0.0));
}

fn max_abs(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
}

#[test]
fn identity_pose_renders_the_image_back() {
    let (w, h) = (48, 32);
    let rgb = texture(w, h);
    let mut depth = vec![0.0f32; w * h];
    for y in 0..h {
        for x in 0..w {
            // a slanted background, a step, and a near box
            let mut z = 2.0 + 3.0 * x as f32 / w as f32 + 0.5 * (0.3 * y as f32).sin();
            if x > 30 {
                z *= 0.6;
            }
            if (10..20).contains(&x) && (8..18).contains(&y) {
                z = 0.7;
            }
            depth[y * w + x] = z;
        }
    }
    for layering in [Layering::Hard, Layering::Soft] {
        for planes in [1, 2, 8, 32] {
            let mpi = build_mpi(&rgb, &depth, w, h, &opts(planes, layering)).unwrap();
            check_structure(&mpi);
            assert_eq!(mpi.planes(), planes);
            let out = render_with(&mpi, Pose::identity());
            let err = max_abs(&out.image, &rgb);
            assert!(err <= 1.0 / 255.0, "{layering:?} {planes} planes: max error {err}");
            assert!(out.coverage.iter().all(|&c| c > 0.999));
        }
    }
}

#[test]
fn constant_depth_scene_is_one_fronto_parallel_plane() {
    let (w, h) = (40, 30);
    let rgb = texture(w, h);
    let depth = vec![2.0f32; w * h];
    let mpi = build_mpi(&rgb, &depth, w, h, &opts(8, Layering::Soft)).unwrap();
    check_structure(&mpi);
    // the nearest plane sits at the scene's depth; the range was widened towards the far side
    assert_eq!(mpi.disparity[0], 0.5);
    assert!(mpi.disparity[7] < 0.5 && mpi.disparity[7] > 0.49);
    // all content on plane 0; the planes between are empty (sigma exactly 0)
    assert!(mpi.plane_rgba(0).chunks_exact(4).all(|px| px[3] > 0.0));
    for i in 1..7 {
        assert!(mpi.plane_rgba(i).chunks_exact(4).all(|px| px[3] == 0.0), "plane {i}");
    }
    let out = render_with(&mpi, Pose::identity());
    for &z in &out.source_depth_in_target {
        assert!((z - 2.0).abs() < 1e-4, "depth {z}");
    }
    // a sideways motion shifts the whole image by fx * tx / z
    let k = Intrinsics::reference_default(w, h);
    let tx = 0.1;
    let shift = (k.fx * tx / 2.0) as f32;
    let out = render_with(&mpi, Pose::from_axis_angle([0.0; 3], [tx, 0.0, 0.0]));
    for y in 2..h - 2 {
        for x in 6..w - 2 {
            let sx = x as f32 - shift;
            let x0 = sx.floor() as usize;
            let f = sx - x0 as f32;
            for c in 0..3 {
                let a = rgb[3 * (y * w + x0) + c];
                let b = rgb[3 * (y * w + x0 + 1) + c];
                let expect = a + f * (b - a);
                let got = out.image[3 * (y * w + x) + c];
                assert!((got - expect).abs() < 2e-3, "({x}, {y}) c{c}: {got} vs {expect}");
            }
            let u = out.flow[2 * (y * w + x)];
            assert!((u - shift).abs() < 1e-3, "flow {u} vs {shift}");
        }
    }
}

/// A red square at depth 1 in front of a uniform wall at depth 4.
fn square_scene(w: usize, h: usize) -> (Vec<f32>, Vec<f32>) {
    let wall = [0.2, 0.4, 0.8];
    let fg = [0.9, 0.1, 0.1];
    let mut rgb = solid(w, h, wall);
    let mut depth = vec![4.0f32; w * h];
    for y in 20..44 {
        for x in 36..60 {
            rgb[3 * (y * w + x)..3 * (y * w + x) + 3].copy_from_slice(&fg);
            depth[y * w + x] = 1.0;
        }
    }
    (rgb, depth)
}

#[test]
fn disocclusion_shows_background_not_foreground() {
    let (w, h) = (96, 64);
    let (rgb, depth) = square_scene(w, h);
    let k = Intrinsics::reference_default(w, h);
    let tx = 0.2;
    // the square moves by fx tx / 1 = 11.1 px, the wall by fx tx / 4 = 2.8 px: target columns
    // between 36 + 2.8 and 36 + 11.1 show what was behind the square's left part
    let (wall_shift, fg_shift) = (k.fx * tx / 4.0, k.fx * tx);
    assert!(wall_shift < 3.0 && fg_shift > 11.0);
    for layering in [Layering::Hard, Layering::Soft] {
        let mpi = build_mpi(&rgb, &depth, w, h, &opts(16, layering)).unwrap();
        check_structure(&mpi);
        let out = render_with(&mpi, Pose::from_axis_angle([0.0; 3], [tx, 0.0, 0.0]));
        for y in 24..40 {
            for x in 40..=45 {
                let px = &out.image[3 * (y * w + x)..3 * (y * w + x) + 3];
                let err = max_abs(px, &[0.2, 0.4, 0.8]);
                assert!(err < 0.02, "{layering:?} ({x}, {y}): {px:?} is not the wall colour");
            }
            // the square itself, shifted
            let px = &out.image[3 * (y * w + 55)..3 * (y * w + 55) + 3];
            assert!(max_abs(px, &[0.9, 0.1, 0.1]) < 0.02, "{layering:?} square at (55, {y}): {px:?}");
        }
    }
}

#[test]
fn disocclusion_shows_the_local_background() {
    // a red square at depth 1 in front of a green wall at depth 2; a blue sky at depth 50 above
    let (w, h) = (96, 64);
    let (sky, wall, fg) = ([0.1, 0.2, 0.9], [0.2, 0.7, 0.2], [0.9, 0.1, 0.1]);
    let mut rgb = vec![0.0f32; w * h * 3];
    let mut depth = vec![0.0f32; w * h];
    for y in 0..h {
        for x in 0..w {
            let (c, z) = if (28..52).contains(&y) && (36..60).contains(&x) {
                (fg, 1.0)
            } else if y >= 16 {
                (wall, 2.0)
            } else {
                (sky, 50.0)
            };
            rgb[3 * (y * w + x)..3 * (y * w + x) + 3].copy_from_slice(&c);
            depth[y * w + x] = z;
        }
    }
    let tx = 0.2; // square moves 11.1 px, wall 5.6 px: target columns 42..47 are uncovered
    for layering in [Layering::Hard, Layering::Soft] {
        let mpi = build_mpi(&rgb, &depth, w, h, &opts(16, layering)).unwrap();
        check_structure(&mpi);
        let out = render_with(&mpi, Pose::from_axis_angle([0.0; 3], [tx, 0.0, 0.0]));
        for y in 32..48 {
            for x in 43..=46 {
                let px = &out.image[3 * (y * w + x)..3 * (y * w + x) + 3];
                assert!(max_abs(px, &wall) < 0.05, "{layering:?} ({x}, {y}): {px:?} is not the wall colour");
            }
        }
    }
}

/// Mean |expected source depth - true depth| under the identity pose.
fn depth_mae(mpi: &Mpi, depth: &[f32]) -> f64 {
    let out = render_with(mpi, Pose::identity());
    let s: f64 = out.source_depth_in_target.iter().zip(depth).map(|(&a, &b)| (a as f64 - b as f64).abs()).sum();
    s / depth.len() as f64
}

#[test]
fn soft_layering_follows_a_tilted_plane_better_than_hard() {
    let (w, h) = (64, 48);
    let rgb = texture(w, h);
    // disparity affine in the pixel coordinates: a plane in 3-D
    let depth: Vec<f32> = (0..w * h)
        .map(|p| {
            let (x, y) = ((p % w) as f64, (p / w) as f64);
            (1.0 / (0.2 + 0.6 * y / (h - 1) as f64 + 0.1 * x / (w - 1) as f64)) as f32
        })
        .collect();
    let hard = build_mpi(&rgb, &depth, w, h, &opts(8, Layering::Hard)).unwrap();
    let soft = build_mpi(&rgb, &depth, w, h, &opts(8, Layering::Soft)).unwrap();
    let k = Intrinsics::reference_default(w, h);
    let cam = build_mpi_for_camera(&rgb, &depth, w, h, &opts(8, Layering::Soft), &k).unwrap();
    for m in [&hard, &soft, &cam] {
        check_structure(m);
    }
    let (e_hard, e_soft, e_cam) = (depth_mae(&hard, &depth), depth_mae(&soft, &depth), depth_mae(&cam, &depth));
    println!("mean abs depth error, 8 planes: hard {e_hard:.4}, soft {e_soft:.4}, soft for the camera {e_cam:.4}");
    assert!(e_soft < 0.5 * e_hard, "soft {e_soft} vs hard {e_hard}");
    // (the camera-compensated build is exact in *disparity*; linear-in-disparity weights
    // overestimate depth slightly, which the off-axis near bias of plain `build_mpi` partly
    // offsets, so its depth error is not necessarily smaller)
    assert!(e_cam < 0.5 * e_hard, "camera {e_cam} vs hard {e_hard}");

    // with the camera's ray lengths the composited weights are exactly the linear split in
    // disparity: expected depth = t d_k + (1 - t) d_{k+1}
    let out = render_with(&cam, Pose::identity());
    let disp = &cam.disparity;
    for (p, &z) in depth.iter().enumerate() {
        let d = 1.0 / z as f64;
        let j = disp.partition_point(|&q| q >= d).clamp(1, disp.len() - 1);
        let t = ((d - disp[j]) / (disp[j - 1] - disp[j])).clamp(0.0, 1.0);
        let expect = t / disp[j - 1] + (1.0 - t) / disp[j];
        let got = out.source_depth_in_target[p] as f64;
        assert!((got - expect).abs() < 1e-4 * expect, "pixel {p}: {got} vs {expect}");
    }
}

#[test]
fn unknown_depths_are_filled_from_known_neighbours() {
    let (w, h) = (40, 30);
    let rgb = texture(w, h);
    let mut depth: Vec<f32> = (0..w * h).map(|p| if p % w < 20 { 1.0 } else { 3.0 }).collect();
    let holes_left = [(5usize, 5usize), (6, 5), (7, 12), (8, 12), (9, 12)];
    let holes_right = [(30usize, 20usize), (31, 20), (35, 3)];
    let bad = [f32::NAN, 0.0, -1.0, f32::INFINITY, f32::NEG_INFINITY];
    for (i, &(x, y)) in holes_left.iter().chain(&holes_right).enumerate() {
        depth[y * w + x] = bad[i % bad.len()];
    }
    // a larger unknown block inside the left half
    for y in 15..25 {
        for x in 3..12 {
            depth[y * w + x] = f32::NAN;
        }
    }
    for layering in [Layering::Hard, Layering::Soft] {
        let mpi = build_mpi(&rgb, &depth, w, h, &opts(8, layering)).unwrap();
        check_structure(&mpi);
        let out = render_with(&mpi, Pose::identity());
        assert!(max_abs(&out.image, &rgb) <= 1.0 / 255.0);
        let z = |x: usize, y: usize| out.source_depth_in_target[y * w + x];
        for &(x, y) in holes_left.iter().chain(&[(7, 20), (3, 15), (11, 24)]) {
            assert!((z(x, y) - 1.0).abs() < 1e-3, "{layering:?} ({x}, {y}): {}", z(x, y));
        }
        for &(x, y) in &holes_right {
            assert!((z(x, y) - 3.0).abs() < 1e-3, "{layering:?} ({x}, {y}): {}", z(x, y));
        }
    }
}

#[test]
fn all_unknown_depth_is_an_error() {
    let (w, h) = (8, 6);
    let rgb = texture(w, h);
    for v in [f32::NAN, 0.0, -2.0, f32::INFINITY] {
        let depth = vec![v; w * h];
        let err = build_mpi(&rgb, &depth, w, h, &LayeringOptions::default()).unwrap_err();
        assert!(err.to_string().contains("no known"), "{err}");
    }
}

#[test]
fn invalid_inputs_are_errors() {
    let (w, h) = (8, 6);
    let rgb = texture(w, h);
    let depth = vec![1.5f32; w * h];
    let o = LayeringOptions::default();
    assert!(build_mpi(&rgb[..rgb.len() - 1], &depth, w, h, &o).is_err());
    assert!(build_mpi(&rgb, &depth[1..], w, h, &o).is_err());
    assert!(build_mpi(&rgb, &depth, w + 1, h, &o).is_err());
    assert!(build_mpi(&[], &[], 0, 0, &o).is_err());
    for planes in [0, 257] {
        let e = build_mpi(&rgb, &depth, w, h, &opts(planes, Layering::Soft)).unwrap_err();
        assert!(e.to_string().contains("planes"), "{e}");
    }
    assert!(build_mpi(&rgb, &depth, w, h, &opts(256, Layering::Soft)).is_ok());
    let mut bad_rgb = rgb.clone();
    bad_rgb[5] = f32::NAN;
    assert!(build_mpi(&bad_rgb, &depth, w, h, &o).is_err());
    let k = Intrinsics::new(0.0, 1.0, 0.0, 0.0);
    assert!(build_mpi_for_camera(&rgb, &depth, w, h, &o, &k).is_err());
}

#[test]
fn disparity_range_is_used_and_checked() {
    let (w, h) = (16, 12);
    let rgb = texture(w, h);
    let depth: Vec<f32> = (0..w * h).map(|p| 1.0 + (p % w) as f32).collect();
    let mut o = opts(5, Layering::Soft);
    o.disparity_range = Some((2.0, 0.0));
    let mpi = build_mpi(&rgb, &depth, w, h, &o).unwrap();
    check_structure(&mpi);
    assert_eq!(mpi.disparity, vec![2.0, 1.5, 1.0, 0.5, 0.0]);
    let out = render_with(&mpi, Pose::identity());
    assert!(max_abs(&out.image, &rgb) <= 1.0 / 255.0);
    let moved = render_with(&mpi, Pose::from_axis_angle([0.0, 0.05, 0.0], [0.1, 0.0, -0.2]));
    assert!(moved.image.iter().chain(&moved.flow).chain(&moved.depth).all(|v| v.is_finite()));
    // content nearer or farther than the range lands on the first or last plane
    o.disparity_range = Some((0.5, 0.2));
    let mpi = build_mpi(&rgb, &depth, w, h, &o).unwrap();
    check_structure(&mpi);
    assert!(max_abs(&render_with(&mpi, Pose::identity()).image, &rgb) <= 1.0 / 255.0);
    for bad in [(1.0, 1.0), (0.5, 1.0), (1.0, -0.5), (f64::NAN, 0.0), (1.0, f64::INFINITY), (f64::INFINITY, 0.0)] {
        o.disparity_range = Some(bad);
        let e = build_mpi(&rgb, &depth, w, h, &o).unwrap_err();
        assert!(e.to_string().contains("disparity range"), "{bad:?}: {e}");
    }
}

#[test]
fn one_plane_is_a_single_opaque_plane() {
    let (w, h) = (10, 7);
    let rgb = texture(w, h);
    let depth: Vec<f32> = (0..w * h).map(|p| 1.0 + (p % 3) as f32).collect();
    let mpi = build_mpi(&rgb, &depth, w, h, &opts(1, Layering::Hard)).unwrap();
    check_structure(&mpi);
    assert_eq!(mpi.disparity, vec![0.5 * (1.0 + 1.0 / 3.0)]);
    let out = render_with(&mpi, Pose::identity());
    assert!(max_abs(&out.image, &rgb) <= 1.0 / 255.0);
    // 1 x 1 images
    let one = build_mpi(&[0.3, 0.6, 0.9], &[2.0], 1, 1, &opts(4, Layering::Soft)).unwrap();
    check_structure(&one);
    assert!(max_abs(&render_with(&one, Pose::identity()).image, &[0.3, 0.6, 0.9]) <= 1.0 / 255.0);
}

#[test]
fn extreme_depths_stay_finite() {
    let (w, h) = (12, 8);
    let rgb = texture(w, h);
    let depth: Vec<f32> = (0..w * h).map(|p| if p % 2 == 0 { 1e-30 } else { 1e30 }).collect();
    for layering in [Layering::Hard, Layering::Soft] {
        let mpi = build_mpi(&rgb, &depth, w, h, &opts(16, layering)).unwrap();
        check_structure(&mpi);
        let out = render_with(&mpi, Pose::from_axis_angle([0.0; 3], [0.1, 0.0, 0.0]));
        assert!(out.image.iter().all(|v| v.is_finite()));
    }
}

/// A full-size scene (640 x 480, 32 planes: a tilted floor, a near box): both layerings give a
/// well-formed MPI whose identity render is the image, and the same bytes on one rayon thread as
/// on the default pool (the planes are built in parallel). Its build time is measured by
/// `cargo bench --bench render` ("build_mpi 640x480x32").
#[test]
fn full_size_layering_is_well_formed_and_independent_of_threads() {
    let (w, h) = (640, 480);
    let rgb = texture(w, h);
    let depth = full_size_depth(w, h);
    let one_thread = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    for layering in [Layering::Hard, Layering::Soft] {
        let o = opts(32, layering);
        let mpi = build_mpi(&rgb, &depth, w, h, &o).unwrap();
        assert_eq!(mpi.planes(), 32);
        check_structure(&mpi);
        let serial = one_thread.install(|| build_mpi(&rgb, &depth, w, h, &o).unwrap());
        let bits = |m: &Mpi| m.rgba.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert!(bits(&serial) == bits(&mpi), "{layering:?}: one thread gave other planes");
        assert_eq!(serial.disparity, mpi.disparity, "{layering:?}");
        let err = max_abs(&render_with(&mpi, Pose::identity()).image, &rgb);
        assert!(err <= 1.0 / 255.0, "{layering:?}: identity render, max error {err}");
    }
}

/// The depth of [`full_size_layering_is_well_formed_and_independent_of_threads`] (and of the
/// bench): a floor receding from 1 to 10 with a ripple, and a box at depth 0.8.
fn full_size_depth(w: usize, h: usize) -> Vec<f32> {
    (0..w * h)
        .map(|p| {
            let (x, y) = ((p % w) as f32, (p / w) as f32);
            let z = 1.0 + 9.0 * y / h as f32 + 0.5 * (0.05 * x).sin();
            if (200..320).contains(&(p % w)) && (150..300).contains(&(p / w)) {
                0.8
            } else {
                z
            }
        })
        .collect()
}

/// Image1 (H x W x 3) sampled bilinearly at (x, y) inside the frame.
fn bilinear_rgb(rgb: &[f32], w: usize, x: f64, y: f64) -> [f64; 3] {
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (fx, fy) = (x - x0 as f64, y - y0 as f64);
    let at = |xx: usize, yy: usize, c: usize| rgb[3 * (yy * w + xx) + c] as f64;
    std::array::from_fn(|c| {
        let top = at(x0, y0, c) * (1.0 - fx) + at(x0 + 1, y0, c) * fx;
        let bottom = at(x0, y0 + 1, c) * (1.0 - fx) + at(x0 + 1, y0 + 1, c) * fx;
        top * (1.0 - fy) + bottom * fy
    })
}

/// The errors of a render of a tilted plane against its closed form: the largest forward-flow
/// error over valid pixels (px) and the mean image2 error (0..1) over the target pixels whose
/// source point lies inside the photo, one pixel from its border.
fn tilted_plane_errors(layering: Layering, planes: usize) -> (f64, f64) {
    use glam::{DMat3, DVec3};
    let (w, h) = (96, 72);
    let k = Intrinsics::reference_default(w, h);
    // disparity affine in the pixel coordinates, d = d0 + dx x + dy y: the 3-D plane n . X = 1
    let (d0, dx, dy) = (0.3, 0.1 / (w - 1) as f64, 0.5 / (h - 1) as f64);
    let depth: Vec<f32> = (0..w * h).map(|p| (1.0 / (d0 + dx * (p % w) as f64 + dy * (p / w) as f64)) as f32).collect();
    let n = DVec3::new(dx * k.fx, dy * k.fy, d0 + dx * k.cx + dy * k.cy);
    let pose = Pose::from_axis_angle([0.01, -0.02, 0.005], [0.06, -0.03, -0.05]);
    let t = pose.translation;
    let homography = k.matrix() * (pose.rotation + DMat3::from_cols(t * n.x, t * n.y, t * n.z)) * k.inverse_matrix();
    let inverse = homography.inverse();
    let project = |m: &DMat3, x: f64, y: f64| {
        let v = *m * DVec3::new(x, y, 1.0);
        (v.x / v.z, v.y / v.z)
    };
    let rgb = texture(w, h);
    let mpi = build_mpi_for_camera(&rgb, &depth, w, h, &opts(planes, layering), &k).unwrap();
    check_structure(&mpi);
    let out = render_with(&mpi, pose);
    let mut flow_err: f64 = 0.0;
    for p in (0..w * h).filter(|&p| out.valid[p] != 0) {
        let (x, y) = ((p % w) as f64, (p / w) as f64);
        let (qx, qy) = project(&homography, x, y);
        let (fu, fv) = (out.flow[2 * p] as f64, out.flow[2 * p + 1] as f64);
        flow_err = flow_err.max((x + fu - qx).hypot(y + fv - qy));
    }
    let (mut sum, mut count) = (0.0, 0usize);
    for q in 0..w * h {
        let (sx, sy) = project(&inverse, (q % w) as f64, (q / w) as f64);
        if !(sx >= 1.0 && sx <= (w - 2) as f64 && sy >= 1.0 && sy <= (h - 2) as f64) || out.coverage[q] < 0.999 {
            continue;
        }
        let want = bilinear_rgb(&rgb, w, sx, sy);
        sum += (0..3).map(|c| (out.image[3 * q + c] as f64 - want[c]).abs()).sum::<f64>() / 3.0;
        count += 1;
    }
    assert!(count > w * h / 2, "{count} target pixels see the plane's interior");
    (flow_err, sum / count as f64)
}

#[test]
fn true_depth_layers_move_every_pixel_by_its_own_depth() {
    let (flow_td, image_td) = tilted_plane_errors(Layering::TrueDepth, 8);
    let (flow_soft, image_soft) = tilted_plane_errors(Layering::Soft, 8);
    println!("tilted plane, 8 planes: flow error {flow_td:.2e} px (soft {flow_soft:.2e}), image2 error {image_td:.2e} (soft {image_soft:.2e})");
    // the flow of a true-depth texel is its pixel's own (f32 rounding); a soft pixel's is the
    // mean of its two planes' flows
    assert!(flow_td < 1e-4, "true-depth flow error {flow_td} px");
    assert!(flow_soft > 10.0 * flow_td, "soft flow error {flow_soft} px vs true-depth {flow_td}");
    // image2 shows image1 where the plane's exact inverse puts it; a soft pixel's two copies part
    assert!(image_td < 1e-4, "true-depth image2 error {image_td}");
    assert!(image_soft > 100.0 * image_td, "soft image2 error {image_soft} vs true-depth {image_td}");
    // the plane count does not change a true-depth render's geometry
    let (flow_32, image_32) = tilted_plane_errors(Layering::TrueDepth, 32);
    assert!(flow_32 < 1e-4 && image_32 < 1e-4, "32 planes: flow {flow_32}, image {image_32}");
}

/// `bench quality` states what a source's scenes cost before its table: the build time and the
/// size in the scene cache, its parts adding up to the largest; and a true-depth layering of 8
/// planes (which keeps each pixel's depth with fewer planes) takes less of the cache than the
/// soft layering's 32 on the same scenes.
#[test]
fn bench_quality_states_the_scenes_cost_and_fewer_true_depth_planes_take_less() {
    let scenes = |layering: &str, planes: &str| -> (f64, f64) {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_mpiflow"))
            .args(["bench", "quality", "--count", "1", "--sharpness", "--size", "64x48"])
            .args(["--layering", layering, "--planes", planes])
            .output()
            .expect("run mpiflow bench quality");
        let text = String::from_utf8_lossy(&out.stdout).into_owned();
        assert!(out.status.success(), "{text}{}", String::from_utf8_lossy(&out.stderr));
        let line = text.lines().find(|l| l.starts_with("scenes: ")).unwrap_or_else(|| panic!("no scenes line: {text}"));
        assert!(line.contains("8 of the first 8 items built"), "{line}");
        // the figures in order: items, first, build median and max, size median and max, parts
        let nums: Vec<f64> = line
            .split(|c: char| !(c.is_ascii_digit() || c == '.'))
            .filter_map(|w| w.trim_matches('.').parse().ok())
            .collect();
        assert_eq!(nums.len(), 10, "{line}");
        let (median, max, parts) = (nums[4], nums[5], nums[6..].to_vec());
        assert!(median > 0.0 && median <= max, "{line}");
        // the parts are rounded to 0.1 MiB each
        assert!((parts.iter().sum::<f64>() - max).abs() <= 0.25, "{line}");
        (median, max)
    };
    let (soft, _) = scenes("soft", "32");
    let (true_depth, _) = scenes("true-depth", "8");
    assert!(true_depth < 0.6 * soft, "true-depth 8 planes {true_depth} MiB, soft 32 planes {soft} MiB");
}
