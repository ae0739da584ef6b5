//! Laws of the accuracy benchmark (`mpiflow bench accuracy`): scenes, exact flow, metrics, the
//! sweep and its writers. No timings are asserted.

use mpiflow::bench::accuracy::{
    convergence_orders, discontinuity_band, exact_flow, exact_flow_at, flow_epe, image_error, log_log_slope, markdown,
    photo_scene, plot_rgb, run_accuracy, sphere_scene, tilted_plane_scene, write_plot, AccuracyConfig, ReportMeta,
    SceneGeometry,
};
use mpiflow::bench::bench_pose;
use mpiflow::geometry::Pose;
use mpiflow::io::image::RgbImage;
use mpiflow::mpi::layering::Layering;

fn tiny_config(planes: Vec<usize>) -> AccuracyConfig {
    let mut cfg = AccuracyConfig::new(48, 32, 1);
    cfg.planes = planes;
    cfg.reference_planes = 32;
    cfg.detail_planes = vec![8];
    cfg
}

#[test]
fn identity_pose_gives_zero_exact_flow() {
    let s = tilted_plane_scene(40, 30);
    let e = exact_flow(&s, &Pose::identity());
    assert!(e.flow.iter().all(|v| v.abs() < 1e-9));
    assert!(e.valid.iter().all(|&v| v), "every pixel maps onto itself");
    assert!(e.occluded.iter().all(|&o| !o));
}

#[test]
fn tilted_plane_depth_is_the_plane_and_smooth() {
    let s = tilted_plane_scene(64, 48);
    let SceneGeometry::Plane { normal, offset } = s.geometry else { panic!("not a plane") };
    for &(x, y) in &[(0.0, 0.0), (31.0, 20.0), (63.0, 47.0)] {
        let p = s.k.unproject(x, y) * s.depth_at(x, y);
        assert!((normal.dot(p) - offset).abs() < 1e-12);
    }
    let dmin = s.depth.iter().copied().fold(f32::MAX, f32::min);
    let dmax = s.depth.iter().copied().fold(f32::MIN, f32::max);
    assert!((dmin - 1.5).abs() < 1e-5 && dmax > 3.0 && dmax < 5.0, "{dmin} .. {dmax}");
    assert!(discontinuity_band(&s.depth, 64, 48).iter().all(|&b| !b));
    let e = exact_flow(&s, &bench_pose());
    assert!(e.occluded.iter().all(|&o| !o), "a plane seen from its front side hides nothing of itself");
}

#[test]
fn sphere_depth_is_closed_form() {
    let s = sphere_scene(320, 240);
    let SceneGeometry::SphereWall { centre, radius, wall_z } = s.geometry else { panic!("not a sphere") };
    assert_eq!((radius, wall_z), (0.6, 4.0));
    // the principal point's ray (0, 0, 1): z = c_z - sqrt(r^2 - c_x^2 - c_y^2)
    let (cx, cy) = (s.k.cx, s.k.cy);
    let expect = centre.z - (radius * radius - centre.x * centre.x - centre.y * centre.y).sqrt();
    assert!((s.depth_at(cx, cy) - expect).abs() < 1e-12);
    let i = cy as usize * 320 + cx as usize;
    assert!((s.depth[i] as f64 - expect).abs() < 1e-6);
    // the ray through the centre meets the sphere at distance |c| - r
    let (px, py) = (s.k.fx * centre.x / centre.z + cx, s.k.fy * centre.y / centre.z + cy);
    let len = centre.length();
    assert!((s.depth_at(px, py) - (len - radius) * centre.z / len).abs() < 1e-12);
    // a corner sees the wall
    assert_eq!(s.depth_at(0.0, 0.0), wall_z);
    assert_eq!(s.depth[0], 4.0);
    // its silhouette is a discontinuity, and the motion hides some wall behind the sphere
    let band = discontinuity_band(&s.depth, 320, 240);
    assert!(!band[i] && band.iter().any(|&b| b));
    let e = exact_flow(&s, &bench_pose());
    let occluded = e.occluded.iter().filter(|&&o| o).count();
    assert!(occluded > 100, "{occluded} occluded pixels");
    // a sphere point is hidden exactly when it faces away from the target camera (the wall
    // cannot hide it); the march decides near-grazing points within a small tolerance
    let c = bench_pose().target_centre_in_source();
    for (j, &o) in e.occluded.iter().enumerate() {
        if !e.valid[j] || s.depth[j] > 3.9 {
            continue;
        }
        let (x, y) = ((j % 320) as f64, (j / 320) as f64);
        let p = s.k.unproject(x, y) * s.depth_at(x, y);
        let facing = ((p - centre) / radius).dot((c - p).normalize());
        if o {
            assert!(facing < 0.05, "pixel ({x}, {y}) hidden while facing the camera ({facing})");
        } else {
            assert!(facing > -0.05, "pixel ({x}, {y}) seen from behind ({facing})");
        }
    }
}

#[test]
fn exact_flow_matches_the_3d_motion() {
    let s = sphere_scene(64, 48);
    let pose = bench_pose();
    let e = exact_flow(&s, &pose);
    let (x, y) = (20.0, 30.0);
    let z = s.depth_at(x, y);
    let xt = pose.apply(s.k.unproject(x, y) * z);
    let (u, v) = exact_flow_at(&s.k, &pose, x, y, z).unwrap();
    assert!((x + u - (s.k.fx * xt.x / xt.z + s.k.cx)).abs() < 1e-9);
    assert!((y + v - (s.k.fy * xt.y / xt.z + s.k.cy)).abs() < 1e-9);
    let i = 30 * 64 + 20;
    assert!(e.valid[i]);
    assert_eq!((e.flow[2 * i], e.flow[2 * i + 1]), (u, v));
    assert!(exact_flow_at(&s.k, &pose, x, y, -1.0).is_none());
}

#[test]
fn metrics_are_zero_on_identical_inputs_and_slopes_are_exponents() {
    let s = tilted_plane_scene(16, 12);
    let e = exact_flow(&s, &bench_pose());
    let flow: Vec<f32> = e.flow.iter().map(|&v| v as f32).collect();
    let vis = e.visible();
    assert!(flow_epe(&flow, &e, &vis) < 1e-5);
    let img = vec![0.5f32; 16 * 12 * 3];
    let cov = vec![1.0f32; 16 * 12];
    let err = image_error(&img, &img, &cov);
    assert_eq!(err.mae, 0.0);
    let shifted: Vec<f32> = img.iter().map(|v| v + 0.01).collect();
    assert!((image_error(&shifted, &img, &cov).mae - 0.01).abs() < 1e-6);
    assert!(image_error(&shifted, &img, &vec![0.5; 16 * 12]).mae.is_nan(), "no covered pixel");
    let pts: Vec<(f64, f64)> = [4.0, 8.0, 16.0, 32.0].iter().map(|&n: &f64| (n, 3.0 * n.powf(-1.7))).collect();
    assert!((log_log_slope(&pts) + 1.7).abs() < 1e-12);
}

#[test]
fn flow_error_falls_with_planes_on_the_tilted_plane() {
    let s = tilted_plane_scene(64, 48);
    let mut cfg = tiny_config(vec![4, 64]);
    cfg.width = 64;
    cfg.height = 48;
    cfg.detail_planes.clear();
    let report = run_accuracy(&cfg, &[s], &mut |_| {}).unwrap();
    let soft =
        |n: usize| report.rows.iter().find(|r| r.planes == n && r.layering == Layering::Soft).map(|r| r.m).unwrap();
    let hard =
        |n: usize| report.rows.iter().find(|r| r.planes == n && r.layering == Layering::Hard).map(|r| r.m).unwrap();
    assert!(soft(64).epe_edge_free < soft(4).epe_edge_free / 10.0, "{:?} {:?}", soft(4), soft(64));
    assert!(hard(64).epe_edge_free < hard(4).epe_edge_free / 4.0);
    assert!(soft(64).image.mae < soft(4).image.mae);
    assert!(soft(4).epe_edge_free < hard(4).epe_edge_free, "soft layering keeps each pixel's disparity");
}

#[test]
#[cfg(feature = "plots")]
fn tiny_sweep_writes_markdown_and_a_png() {
    let (w, h) = (48, 32);
    let photo =
        RgbImage { width: 30, height: 20, data: (0..30 * 20 * 3).map(|i| ((i * 37) % 101) as f32 / 100.0).collect() };
    let scenes = [tilted_plane_scene(w, h), sphere_scene(w, h), photo_scene("photo (test)", &photo, w, h)];
    let cfg = tiny_config(vec![4, 8]);
    let report = run_accuracy(&cfg, &scenes, &mut |_| {}).unwrap();
    assert_eq!(report.rows.len(), 3 * 2 * 2);
    assert!(report.rows.iter().all(|r| r.m.epe.is_finite() && r.m.image.mae.is_finite() && r.m.time.median >= 0.0));
    assert_eq!(report.precision.len(), 3);
    assert_eq!(report.storage.len(), 3);
    for r in &report.storage {
        // f16 keeps 11 significant bits: colours within about 5e-4 of the f32 ones
        assert!(r.image_diff.0 > 0.0 && r.image_diff.0 < 1e-2, "{}: {:?}", r.scene, r.image_diff);
        assert!(r.flow_diff.0.is_finite() && r.flow_diff.1 < 1e-2, "{}: {:?}", r.scene, r.flow_diff);
        assert!(r.bytes.1 < r.bytes.0, "{}: {:?}", r.scene, r.bytes);
    }
    assert_eq!(report.reference_mode.len(), 3);
    // every colour kernel once per scene; the bilinear kernel's same-kernel reference is the
    // bilinear reference itself
    assert_eq!(report.kernels.len(), 3 * mpiflow::render::Resample::ALL.len());
    for r in &report.kernels {
        assert!(r.m.image.mae.is_finite() && r.same_kernel.mae.is_finite(), "{} {}", r.scene, r.kernel);
        if r.kernel == mpiflow::render::Resample::Bilinear {
            assert_eq!(r.same_kernel.mae, r.m.image.mae, "{}", r.scene);
        }
    }
    assert!(!report.skips.is_empty());
    // skipping that is exact by construction changes nothing
    for r in report.skips.iter().filter(|r| r.name == "tiles") {
        assert_eq!(r.image_diff.0, 0.0, "{}", r.scene);
        assert_eq!(r.flow_diff.0, 0.0, "{}", r.scene);
    }
    assert_eq!(convergence_orders(&report).len(), 3 * 2 * 3);

    let meta = ReportMeta {
        command: "cargo run --release -- bench accuracy --width 48 --height 32".into(),
        machine: "test".into(),
        plot: "accuracy.png".into(),
        total_s: 0.0,
    };
    let md = markdown(&report, &meta);
    assert!(md.contains(&meta.command));
    assert!(md.contains("](accuracy.png)"));
    for n in [4, 8] {
        for s in &scenes {
            for l in ["hard", "soft"] {
                let row = format!("| {} | {n} | {l} |", s.name);
                assert!(md.contains(&row), "missing row `{row}`");
            }
        }
    }
    assert!(md.contains("## Convergence order"));
    assert!(md.contains("## Colour kernels"));
    assert!(md.contains(&format!("| {} | 8 | bspline3 |", scenes[2].name)));

    let dir = std::env::temp_dir().join(format!("mpiflow-accuracy-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("accuracy.png");
    write_plot(&report, &path, 900, 400).unwrap();
    let img = image::open(&path).unwrap();
    assert_eq!((img.width(), img.height()), (900, 400));
    // something was drawn: not all white
    let rgb = img.to_rgb8();
    assert!(rgb.pixels().filter(|p| p.0 != [255, 255, 255]).count() > 1000);
    assert_eq!(plot_rgb(&report, 300, 200).unwrap().len(), 300 * 200 * 3);
    std::fs::remove_dir_all(&dir).ok();
}
