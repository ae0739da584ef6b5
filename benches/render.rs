//! Criterion benches of the renderer's hot loops (target view, source-view flow) on the
//! synthetic benchmark MPI, of the built-in RGB-D layering and of Telea inpainting at 640 x 480.
//! `cargo bench --bench render`.

use criterion::{criterion_group, criterion_main, Criterion};
use mpiflow::bench::bench_pose;
use mpiflow::geometry::Intrinsics;
use mpiflow::mpi::layering::{build_mpi, Layering, LayeringOptions};
use mpiflow::mpi::synthetic::bench_mpi;
use mpiflow::render::{render, Fields, Mode, Occupancy, RenderParams, Skip};
use mpiflow::sample::inpaint::{inpaint, TeleaOptions, TeleaVariant};

fn hot_loops(c: &mut Criterion) {
    let (w, h, n) = (320, 240, 32);
    let mpi = bench_mpi(w, h, n);
    let occ = Occupancy::build(&mpi, 0.0);
    let k = Intrinsics::reference_default(w, h);
    let cases = [
        ("exact target", Mode::Exact, Skip::DEFAULT, Fields { target: true, flow: false, occlusion: false }),
        ("exact flow", Mode::Exact, Skip::DEFAULT, Fields { target: false, flow: true, occlusion: false }),
        ("exact target no-skip", Mode::Exact, Skip::NONE, Fields { target: true, flow: false, occlusion: false }),
        ("reference target", Mode::Reference, Skip::NONE, Fields { target: true, flow: false, occlusion: false }),
        ("reference flow", Mode::Reference, Skip::NONE, Fields { target: false, flow: true, occlusion: false }),
    ];
    let mut g = c.benchmark_group("render 320x240x32");
    g.sample_size(10);
    for (name, mode, skip, fields) in cases {
        let p = RenderParams { mode, skip, fields, ..RenderParams::new(k, bench_pose()) };
        g.bench_function(name, |b| b.iter(|| render::<f32>(&mpi, &p, Some(&occ)).unwrap()));
    }
    g.finish();
}

/// A smooth texture in [0, 1], H x W x 3.
fn texture(w: usize, h: usize) -> Vec<f32> {
    (0..w * h)
        .flat_map(|p| {
            let (x, y) = ((p % w) as f32, (p / w) as f32);
            [
                0.5 + 0.4 * (0.31 * x + 0.17 * y).sin(),
                0.5 + 0.4 * (0.23 * y - 0.11 * x).cos(),
                ((p * 7) % 17) as f32 / 16.0,
            ]
        })
        .collect()
}

/// The built-in layering of a 640 x 480 RGB-D image into 32 planes (a receding floor, a near box;
/// the scene of `tests/render/layering.rs::full_size_layering_is_well_formed_and_independent_of_threads`).
fn layering(c: &mut Criterion) {
    let (w, h) = (640, 480);
    let rgb = texture(w, h);
    let depth: Vec<f32> = (0..w * h)
        .map(|p| {
            let (x, y) = (p % w, p / w);
            if (200..320).contains(&x) && (150..300).contains(&y) {
                0.8
            } else {
                1.0 + 9.0 * y as f32 / h as f32 + 0.5 * (0.05 * x as f32).sin()
            }
        })
        .collect();
    let mut g = c.benchmark_group("build_mpi 640x480x32");
    g.sample_size(10);
    for layering in [Layering::Hard, Layering::Soft] {
        let o = LayeringOptions {
            planes: 32,
            layering,
            disparity_range: None,
            backdrop: false,
            ..LayeringOptions::default()
        };
        g.bench_function(format!("{layering:?}"), |b| b.iter(|| build_mpi(&rgb, &depth, w, h, &o).unwrap()));
    }
    g.finish();
}

/// Telea inpainting of a 640 x 480 RGB image with 10% of its pixels in discs (radius 5): the
/// paper's variant on f32 and u8, OpenCV's on f32.
fn inpainting(c: &mut Criterion) {
    let (w, h, ch) = (640, 480, 3);
    let src = texture(w, h);
    let src_u8: Vec<u8> = src.iter().map(|&v| (v * 255.0).round() as u8).collect();
    // discs on a fixed grid, radius 4 to 20, until 10% of the pixels are holes
    let mut hole = vec![0u8; w * h];
    let mut k = 0usize;
    while hole.iter().filter(|&&v| v != 0).count() < w * h / 10 {
        let (cx, cy, r) = ((k * 137) % w, (k * 89) % h, 4 + (k * 7) % 17);
        for y in cy.saturating_sub(r)..(cy + r + 1).min(h) {
            for x in cx.saturating_sub(r)..(cx + r + 1).min(w) {
                if (x.abs_diff(cx)).pow(2) + (y.abs_diff(cy)).pow(2) <= r * r {
                    hole[y * w + x] = 1;
                }
            }
        }
        k += 1;
    }
    let mut g = c.benchmark_group("inpaint 640x480");
    g.sample_size(10);
    let paper = TeleaOptions { radius: 5.0, ..TeleaOptions::default() };
    let opencv = TeleaOptions { variant: TeleaVariant::OpenCv, ..paper };
    g.bench_function("paper f32", |b| b.iter(|| inpaint(&mut src.clone(), w, h, ch, &hole, &paper)));
    g.bench_function("opencv f32", |b| b.iter(|| inpaint(&mut src.clone(), w, h, ch, &hole, &opencv)));
    g.bench_function("paper u8", |b| b.iter(|| inpaint(&mut src_u8.clone(), w, h, ch, &hole, &paper)));
    g.finish();
}

criterion_group!(benches, hot_loops, layering, inpainting);
criterion_main!(benches);
