//! Laws and extremes of the renderer: closed-form flows, degenerate poses,
//! depths and densities, NaN/Inf inputs, tiny and huge images, parallel = serial, f32 ~ f64.
//! Every render here is also checked to contain no NaN or Inf.

use mpiflow::geometry::{Intrinsics, Pose};
use mpiflow::mpi::synthetic::bench_mpi;
use mpiflow::mpi::Mpi;
use mpiflow::render::{render, Mode, Real, RenderOutput, RenderParams, Skip};

const MODES: [Mode; 2] = [Mode::Exact, Mode::Reference];

fn assert_finite(out: &RenderOutput, what: &str) {
    for (name, buf) in [
        ("image", &out.image),
        ("depth", &out.depth),
        ("coverage", &out.coverage),
        ("extras", &out.extras),
        ("flow", &out.flow),
        ("source depth", &out.source_depth_in_target),
    ] {
        if let Some(i) = buf.iter().position(|v| !v.is_finite()) {
            panic!("{what}: {name}[{i}] = {}", buf[i]);
        }
    }
    assert_eq!(out.stats.repaired, 0, "{what}: the renderer produced non-finite values that had to be repaired");
}

fn run<T: Real>(mpi: &Mpi, pose: Pose, mode: Mode, skip: Skip) -> RenderOutput {
    let k = Intrinsics::reference_default(mpi.width, mpi.height);
    let mut p = RenderParams::new(k, pose);
    p.mode = mode;
    p.skip = skip;
    let out = render::<T>(mpi, &p, None).unwrap();
    assert_finite(&out, &format!("{mode:?} {pose:?}"));
    out
}

/// A single plane at `depth`, opaque, with a colour pattern.
fn opaque_plane(w: usize, h: usize, depth: f64) -> Mpi {
    let mut m = Mpi::new(w, h, vec![1.0 / depth], 1);
    for (j, px) in m.rgba.chunks_exact_mut(4).enumerate() {
        let (x, y) = ((j % w) as f32, (j / w) as f32);
        px.copy_from_slice(&[(x / w as f32), (y / h as f32), 0.5, 50.0]);
    }
    m.extras.iter_mut().for_each(|v| *v = 1.0);
    m
}

/// Each pixel opaque on exactly one of `n` planes (a hard-layered scene).
fn layered(w: usize, h: usize, n: usize) -> Mpi {
    let disp: Vec<f64> = (0..n).map(|i| 0.9 - 0.8 * i as f64 / n.max(2) as f64).collect();
    let mut m = Mpi::new(w, h, disp, 0);
    for y in 0..h {
        for x in 0..w {
            let own = (x / 5 + y / 7) % n;
            for i in 0..n {
                let o = (i * h * w + y * w + x) * 4;
                m.rgba[o] = ((x * 7 + y * 3) % 255) as f32 / 255.0;
                m.rgba[o + 1] = ((x * 2 + y * 11) % 255) as f32 / 255.0;
                m.rgba[o + 2] = (i as f32 + 1.0) / (n as f32 + 1.0);
                m.rgba[o + 3] = if i == own || i == n - 1 { 1e4 } else { 0.0 };
            }
        }
    }
    m
}

#[test]
fn identity_pose_gives_zero_flow_and_the_same_image() {
    let m = layered(40, 30, 6);
    for mode in MODES {
        let out = run::<f32>(&m, Pose::identity(), mode, Skip::DEFAULT);
        assert!(out.flow.iter().all(|&f| f.abs() < 1e-4), "{mode:?}: flow not zero");
        assert!(out.valid.iter().all(|&v| v == 1), "{mode:?}: identity flow must be valid everywhere");
        assert!(out.occlusion.iter().all(|&v| v == 0));
        for (j, px) in out.image.chunks_exact(3).enumerate() {
            let (x, y) = (j % 40, j / 40);
            let own = (x / 5 + y / 7) % 6;
            let src = &m.rgba[(own * 1200 + j) * 4..(own * 1200 + j) * 4 + 3];
            for c in 0..3 {
                assert!((px[c] - src[c]).abs() <= 1.0 / 255.0, "{mode:?} pixel {j}: {} vs {}", px[c], src[c]);
            }
        }
    }
}

#[test]
fn opaque_plane_under_translation_has_the_closed_form_flow() {
    let (w, h, d) = (64usize, 48usize, 2.5);
    let m = opaque_plane(w, h, d);
    let k = Intrinsics::reference_default(w, h);
    let t = [0.1, -0.05, -0.3];
    for mode in MODES {
        let out = run::<f32>(&m, Pose::from_axis_angle([0.0; 3], t), mode, Skip::NONE);
        let mut worst = 0.0f64;
        for y in 0..h {
            for x in 0..w {
                let (xs, ys) = ((x as f64 - k.cx) / k.fx * d, (y as f64 - k.cy) / k.fy * d);
                let z = d + t[2];
                let u = k.fx * (xs + t[0]) / z + k.cx - x as f64;
                let v = k.fy * (ys + t[1]) / z + k.cy - y as f64;
                let i = y * w + x;
                worst = worst.max((out.flow[2 * i] as f64 - u).abs()).max((out.flow[2 * i + 1] as f64 - v).abs());
                // the target depth of an opaque plane seen straight on is d + tz
                if mode == Mode::Exact && out.coverage[i] > 0.999 {
                    assert!((out.depth[i] as f64 - z).abs() < 1e-4 * z, "depth {} vs {z}", out.depth[i]);
                }
            }
        }
        assert!(worst < 1e-3, "{mode:?}: flow differs from the closed form by {worst} px");
    }
}

#[test]
fn pure_rotation_flow_does_not_depend_on_depth() {
    let pose = Pose::from_axis_angle([0.03, -0.05, 0.02], [0.0; 3]);
    for mode in MODES {
        let near = run::<f32>(&opaque_plane(48, 32, 0.5), pose, mode, Skip::NONE);
        let far = run::<f32>(&opaque_plane(48, 32, 500.0), pose, mode, Skip::NONE);
        let worst = near.flow.iter().zip(&far.flow).map(|(a, b)| (a - b).abs()).fold(0.0, f32::max);
        assert!(worst < 1e-3, "{mode:?}: rotation flow varies with depth by {worst}");
        assert!(near.flow.iter().any(|f| f.abs() > 0.5), "the rotation should move pixels");
    }
}

#[test]
fn zoom_between_intrinsics_scales_about_the_principal_point() {
    let m = opaque_plane(32, 24, 3.0);
    let ks = Intrinsics::reference_default(32, 24);
    let kt = Intrinsics::new(2.0 * ks.fx, 2.0 * ks.fy, ks.cx, ks.cy);
    let mut p = RenderParams::new(ks, Pose::identity());
    p.k_tgt = kt;
    let out = render::<f32>(&m, &p, None).unwrap();
    for y in 0..24 {
        for x in 0..32 {
            let i = y * 32 + x;
            assert!((out.flow[2 * i] as f64 - (x as f64 - ks.cx)).abs() < 1e-4);
            assert!((out.flow[2 * i + 1] as f64 - (y as f64 - ks.cy)).abs() < 1e-4);
        }
    }
}

#[test]
fn camera_moving_through_the_nearest_planes() {
    let m = layered(40, 30, 8);
    // plane depths are 1/0.9 .. 1/0.2; move the camera 3 units forward, past the first planes
    for tz in [-1.0 / 0.9, -1.5, -3.0, -4.9] {
        for mode in MODES {
            let out = run::<f32>(&m, Pose::from_axis_angle([0.0; 3], [0.02, 0.01, tz]), mode, Skip::DEFAULT);
            if mode == Mode::Exact {
                // every rendered depth is in front of the camera
                assert!(out.depth.iter().all(|&d| d >= 0.0));
            }
        }
    }
}

#[test]
fn points_behind_the_target_camera_are_invalid_not_nan() {
    let m = layered(32, 24, 4);
    // turn around (180 degrees about y) and step back: everything is behind the camera
    let out = run::<f32>(
        &m,
        Pose::from_axis_angle([0.0, std::f64::consts::PI, 0.0], [0.0, 0.0, -0.5]),
        Mode::Exact,
        Skip::DEFAULT,
    );
    assert!(out.valid.iter().all(|&v| v == 0), "points behind the camera must be invalid");
    assert!(out.coverage.iter().all(|&c| c < 1e-6), "nothing can be seen behind the camera");
    let _ = run::<f32>(
        &m,
        Pose::from_axis_angle([0.0, std::f64::consts::PI, 0.0], [0.0, 0.0, -0.5]),
        Mode::Reference,
        Skip::NONE,
    );
}

#[test]
fn rotations_up_to_ninety_degrees() {
    let m = layered(24, 16, 4);
    for deg in [0.0f64, 15.0, 45.0, 60.0, 89.0, 90.0] {
        let a = deg.to_radians();
        for axis in [[a, 0.0, 0.0], [0.0, a, 0.0], [0.0, 0.0, a], [a / 2.0, a / 2.0, a / 2.0]] {
            for mode in MODES {
                let out = run::<f32>(&m, Pose::from_axis_angle(axis, [0.05, 0.0, -0.1]), mode, Skip::DEFAULT);
                if deg >= 89.0 && axis[0] == a {
                    // looking 90 degrees up: almost nothing of the scene stays in view
                    let v = out.valid.iter().filter(|&&v| v == 1).count();
                    assert!(v < out.valid.len() / 4, "{mode:?}: {v} valid after a 90 degree tilt");
                }
            }
        }
    }
}

#[test]
fn extreme_depths_and_infinitely_far_planes() {
    let disp = vec![1e3, 1e1, 1.0, 1e-2, 1e-4, 1e-6, 0.0];
    let n = disp.len();
    let mut m = Mpi::new(24, 16, disp, 0);
    for (j, px) in m.rgba.chunks_exact_mut(4).enumerate() {
        let plane = j / (24 * 16);
        px.copy_from_slice(&[0.2, 0.4, 0.6, if plane == n - 1 || j % 3 == 0 { 5.0 } else { 0.0 }]);
    }
    for mode in MODES {
        for pose in [
            Pose::from_axis_angle([0.0; 3], [0.1, 0.0, 0.0]),
            Pose::from_axis_angle([0.01, 0.02, 0.0], [0.1, 0.05, -0.2]),
            Pose::identity(),
        ] {
            let out = run::<f32>(&m, pose, mode, Skip::DEFAULT);
            if mode == Mode::Exact {
                assert!(out.depth.iter().all(|&d| (0.0..=1e12).contains(&d)));
            }
        }
    }
    // an infinitely far opaque plane alone: translation produces no flow
    let mut far = opaque_plane(16, 12, 1.0);
    far.disparity = vec![0.0];
    let out = run::<f32>(&far, Pose::from_axis_angle([0.0; 3], [5.0, 3.0, -2.0]), Mode::Exact, Skip::NONE);
    assert!(out.flow.iter().all(|f| f.abs() < 1e-4), "a plane at infinity does not move under translation");
}

#[test]
fn densities_zero_tiny_and_huge() {
    for sigma in [0.0f32, 1e-12, 1e12, f32::MAX] {
        let mut m = layered(20, 14, 3);
        for px in m.rgba.chunks_exact_mut(4) {
            px[3] = sigma;
        }
        for mode in MODES {
            let out = run::<f32>(&m, Pose::from_axis_angle([0.01, 0.0, 0.0], [0.1, 0.0, -0.1]), mode, Skip::DEFAULT);
            if sigma == 0.0 && mode == Mode::Exact {
                assert!(out.coverage.iter().all(|&c| c == 0.0));
                assert!(out.valid.iter().all(|&v| v == 0), "an empty MPI has no valid flow");
            }
        }
    }
}

#[test]
fn nan_and_inf_in_the_mpi_are_sanitised_and_reported() {
    let mut m = layered(20, 14, 3);
    m.rgba[0] = f32::NAN;
    m.rgba[5] = f32::INFINITY;
    m.rgba[7] = f32::NAN;
    m.rgba[11] = f32::INFINITY;
    m.rgba[15] = f32::NEG_INFINITY;
    let report = m.sanitize();
    assert_eq!(report.nonfinite_color, 2);
    assert_eq!(report.bad_sigma, 3);
    for mode in MODES {
        run::<f32>(&m, Pose::from_axis_angle([0.0; 3], [0.1, 0.0, 0.0]), mode, Skip::DEFAULT);
    }
}

#[test]
fn degenerate_image_sizes() {
    for (w, h) in [(1usize, 1usize), (1, 17), (23, 1), (2, 2)] {
        let m = layered(w, h, 3);
        for mode in MODES {
            let out = run::<f32>(&m, Pose::from_axis_angle([0.01, 0.02, 0.03], [0.1, -0.1, -0.2]), mode, Skip::DEFAULT);
            assert_eq!(out.image.len(), w * h * 3);
            let id = run::<f32>(&m, Pose::identity(), mode, Skip::DEFAULT);
            assert!(id.flow.iter().all(|f| f.abs() < 1e-4), "{w}x{h} identity flow");
        }
    }
}

#[test]
fn a_4096_square_image_renders() {
    let m = layered(4096, 4096, 2);
    let out = run::<f32>(&m, Pose::from_axis_angle([0.0, 0.01, 0.0], [0.05, 0.0, -0.05]), Mode::Exact, Skip::DEFAULT);
    assert_eq!(out.flow.len(), 4096 * 4096 * 2);
    assert!(out.valid.iter().filter(|&&v| v == 1).count() > 4096 * 4096 / 2);
}

#[test]
fn parallel_output_is_bit_identical_to_serial() {
    let m = bench_mpi(96, 64, 12);
    let pose = Pose::from_axis_angle([0.02, -0.01, 0.03], [0.1, -0.1, -0.15]);
    for mode in MODES {
        let serial = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap()
            .install(|| run::<f32>(&m, pose, mode, Skip::DEFAULT));
        let parallel = rayon::ThreadPoolBuilder::new()
            .num_threads(4)
            .build()
            .unwrap()
            .install(|| run::<f32>(&m, pose, mode, Skip::DEFAULT));
        let bits = |v: &[f32]| v.iter().map(|f| f.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&serial.image), bits(&parallel.image));
        assert_eq!(bits(&serial.flow), bits(&parallel.flow));
        assert_eq!(bits(&serial.depth), bits(&parallel.depth));
        assert_eq!(serial.valid, parallel.valid);
        assert_eq!(serial.occlusion, parallel.occlusion);
    }
}

/// f32 against f64 on the synthetic benchmark scene. Stated tolerances: image 1e-4, flow
/// 1e-3 px, depth 1e-4 relative (observed values are printed).
#[test]
fn f32_is_close_to_f64() {
    let m = bench_mpi(128, 96, 32);
    let pose = Pose::from_axis_angle([0.021, -0.013, 0.008], [0.15, -0.12, -0.17]);
    for mode in MODES {
        let a = run::<f32>(&m, pose, mode, Skip::NONE);
        let b = run::<f64>(&m, pose, mode, Skip::NONE);
        let maxd = |x: &[f32], y: &[f32]| x.iter().zip(y).map(|(p, q)| (p - q).abs()).fold(0.0, f32::max);
        let rel = a.depth.iter().zip(&b.depth).map(|(p, q)| (p - q).abs() / q.abs().max(1e-3)).fold(0.0, f32::max);
        let (di, df) = (maxd(&a.image, &b.image), maxd(&a.flow, &b.flow));
        println!("{mode:?}: image {di:.2e}, flow {df:.2e} px, depth {rel:.2e} relative");
        assert!(di < 1e-4 && df < 1e-3 && rel < 1e-4, "{mode:?}: image {di}, flow {df}, depth {rel}");
    }
}

#[test]
fn work_skipping_is_exact_for_empty_tiles() {
    let m = bench_mpi(128, 96, 24);
    let pose = Pose::from_axis_angle([0.02, -0.01, 0.03], [0.1, -0.1, -0.15]);
    let none = run::<f32>(&m, pose, Mode::Exact, Skip::NONE);
    let tiles = run::<f32>(&m, pose, Mode::Exact, Skip { tiles: true, ..Skip::NONE });
    assert!(tiles.stats.skipped_tile > 0, "the synthetic scene has empty tiles");
    assert_eq!(none.image, tiles.image, "skipping exactly-empty planes must not change the image");
    assert_eq!(none.depth, tiles.depth);
    let early = run::<f32>(&m, pose, Mode::Exact, Skip { transmittance_eps: 1e-4, ..Skip::NONE });
    assert!(early.stats.skipped_early > 0);
    let worst = none.image.iter().zip(&early.image).map(|(a, b)| (a - b).abs()).fold(0.0, f32::max);
    assert!(worst <= 1e-4, "early termination at T < 1e-4 changes a colour by at most 1e-4, got {worst}");
}
