//! The reference-compatible mode reproduces the public implementation's renders
//! (`tests/data/case_*.npz`): rgb, flow and mask within 1e-4 absolute, depth within 1e-3
//! relative, in f32; and far closer in f64.

use mpiflow::geometry::Intrinsics;
use mpiflow::io::npy::read_array;
use mpiflow::mpi::npz::load_npz;
use mpiflow::render::{render, Mode, Real, RenderOutput, RenderParams, Skip};
use std::path::PathBuf;

fn case(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/data").join(format!("{name}.npz"))
}

fn expected(name: &str, key: &str) -> Vec<f64> {
    let mut npz = npyz::npz::NpzArchive::open(case(name)).unwrap();
    read_array(npz.by_name(key).unwrap().unwrap()).unwrap().data
}

fn run<T: Real>(name: &str) -> RenderOutput {
    let mpi = load_npz(&case(name)).unwrap();
    let k: Intrinsics = mpi.intrinsics.unwrap();
    let mut p = RenderParams::new(k, mpi.pose.unwrap());
    p.mode = Mode::Reference;
    p.skip = Skip::NONE;
    render::<T>(&mpi, &p, None).unwrap()
}

/// max |a - b| between our HWC output and the reference's CHW array.
fn max_diff_chw(ours: &[f32], reference: &[f64], channels: usize, hw: usize, relative: bool) -> f64 {
    let mut worst = 0.0f64;
    for c in 0..channels {
        for i in 0..hw {
            let r = reference[c * hw + i];
            let o = ours[i * channels + c] as f64;
            let d = if relative { (o - r).abs() / r.abs().max(1e-6) } else { (o - r).abs() };
            worst = worst.max(d);
        }
    }
    worst
}

fn check<T: Real>(name: &str, tol_abs: f64, tol_rel: f64) {
    let out = run::<T>(name);
    let hw = out.width * out.height;
    let rgb = max_diff_chw(&out.image, &expected(name, "out_rgb"), 3, hw, false);
    let flow = max_diff_chw(&out.flow, &expected(name, "out_flow"), 2, hw, false);
    let mask = max_diff_chw(&out.extras, &expected(name, "out_mask"), 1, hw, false);
    let depth = max_diff_chw(&out.depth, &expected(name, "out_depth"), 1, hw, true);
    println!(
        "{name} ({}): rgb {rgb:.2e} flow {flow:.2e} mask {mask:.2e} depth(rel) {depth:.2e}",
        std::any::type_name::<T>()
    );
    assert!(rgb <= tol_abs, "rgb differs by {rgb}");
    assert!(flow <= tol_abs, "flow differs by {flow}");
    assert!(mask <= tol_abs, "mask differs by {mask}");
    assert!(depth <= tol_rel, "depth differs by {depth} (relative)");
    assert_eq!(out.stats.repaired, 0);
}

#[test]
fn case_tx_f32() {
    check::<f32>("case_tx", 1e-4, 1e-3);
}

#[test]
fn case_cam_f32() {
    check::<f32>("case_cam", 1e-4, 1e-3);
}

#[test]
fn case_tx_f64() {
    check::<f64>("case_tx", 1e-6, 1e-6);
}

#[test]
fn case_cam_f64() {
    check::<f64>("case_cam", 1e-6, 1e-6);
}
