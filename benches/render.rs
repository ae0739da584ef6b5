//! Criterion benches of the renderer's hot loops (target view, source-view flow) on the
//! synthetic benchmark MPI. `cargo bench --bench render`.

use criterion::{criterion_group, criterion_main, Criterion};
use mpiflow::bench::bench_pose;
use mpiflow::geometry::Intrinsics;
use mpiflow::mpi::synthetic::bench_mpi;
use mpiflow::render::{render, Fields, Mode, Occupancy, RenderParams, Skip};

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

criterion_group!(benches, hot_loops);
criterion_main!(benches);
