//! The same bytes on every instruction set: renders and whole samples made on each vector path
//! this CPU runs (`mpiflow::isa`: the SSE2 baseline, AVX2, AVX-512) are compared byte for byte
//! with the baseline's. Only the first test changes the path, a process-wide choice.

use std::sync::Arc;

use mpiflow::bench::bench_pose;
use mpiflow::geometry::Intrinsics;
use mpiflow::isa::{self, Isa};
use mpiflow::mpi::synthetic::bench_mpi;
use mpiflow::render::{render, Mode, Occupancy, RenderParams, Resample};
use mpiflow::sample::config::SampleConfig;
use mpiflow::sample::pipeline::{open_source, OpenOptions, Pipeline, SourceSpec};
use mpiflow::scene::cache::SceneCache;
use mpiflow::scene::models::ModelConfig;

/// Every output buffer of a render of the synthetic benchmark MPI (both passes, the links'
/// buffers included) with `resample`, as bytes.
fn render_bytes(resample: Resample, mode: Mode) -> Vec<u8> {
    let (w, h) = (123, 77);
    let mut mpi = bench_mpi(w, h, 12);
    mpiflow::render::resample::prefilter(&mut mpi, resample);
    if mpiflow::render::store::packs(mode, resample, false) {
        mpiflow::render::store::pack(&mut mpi);
    }
    let mut p = RenderParams::new(Intrinsics::reference_default(w, h), bench_pose());
    p.mode = mode;
    p.resample = resample;
    let occ = Occupancy::build(&mpi, p.skip.tile_sigma_eps);
    let out = render::<f32>(&mpi, &p, Some(&occ)).expect("render");
    let mut bytes = Vec::new();
    for buf in [&out.image, &out.depth, &out.coverage, &out.extras, &out.flow, &out.source_depth_in_target] {
        bytes.extend(buf.iter().flat_map(|v| v.to_le_bytes()));
    }
    bytes.extend(&out.valid);
    bytes.extend(&out.occlusion);
    bytes
}

/// The bytes of samples 0..4 of the bundled scenes at 160 x 120 (one moving object, the
/// occlusion mask on): images, flow, masks, depths.
fn sample_bytes(p: &Pipeline) -> Vec<u8> {
    let mut bytes = Vec::new();
    for index in 0..4 {
        let s = p.generator().sample(7, index).expect("sample");
        for b in [&s.image1, &s.image2, &s.valid, &s.occlusion, &s.mask1, &s.mask2] {
            bytes.extend(b.iter());
        }
        for f in [&s.flow, &s.depth1, &s.depth2] {
            bytes.extend(f.iter().flat_map(|v| v.to_le_bytes()));
        }
    }
    bytes
}

#[test]
fn every_vector_path_makes_the_baselines_bytes() {
    let paths = Isa::available_all();
    assert_eq!(paths[0], Isa::Sse2, "the baseline is always available");
    let open = OpenOptions { resize: Some((160, 120)), ..OpenOptions::default() };
    let stage = Arc::new(ModelConfig::default().build_stage().unwrap());
    let source = open_source(&SourceSpec::Builtin, &open).unwrap();
    let config = SampleConfig { occlusion: true, ..SampleConfig::default() };
    let pipeline = Pipeline::new(source, stage, Arc::new(SceneCache::new(1 << 30)), config.clone()).unwrap();
    // the same with true-depth layers (each texel at its own disparity)
    let models = ModelConfig { layering: mpiflow::mpi::layering::Layering::TrueDepth, ..ModelConfig::default() };
    let source = open_source(&SourceSpec::Builtin, &open).unwrap();
    let true_depth =
        Pipeline::new(source, Arc::new(models.build_stage().unwrap()), Arc::new(SceneCache::new(1 << 30)), config)
            .unwrap();
    let kernels = [Resample::Bilinear, Resample::Bspline3, Resample::Bicubic, Resample::Omoms3];
    let mut baseline: Option<(Vec<Vec<u8>>, Vec<u8>)> = None;
    for &isa in &paths {
        isa::force(isa).unwrap();
        assert_eq!(isa::current(), isa);
        let renders: Vec<Vec<u8>> =
            kernels.iter().flat_map(|&k| [render_bytes(k, Mode::Exact), render_bytes(k, Mode::Reference)]).collect();
        let mut samples = sample_bytes(&pipeline);
        samples.extend(sample_bytes(&true_depth));
        match &baseline {
            None => baseline = Some((renders, samples)),
            Some((r0, s0)) => {
                for (j, (a, b)) in r0.iter().zip(&renders).enumerate() {
                    let first = a.iter().zip(b).position(|(x, y)| x != y);
                    assert!(a == b, "{isa}: render {j} differs from sse2's (first byte {first:?})");
                }
                let first = s0.iter().zip(&samples).position(|(x, y)| x != y);
                assert!(*s0 == samples, "{isa}: samples differ from sse2's (first byte {first:?})");
            }
        }
    }
    eprintln!("compared paths: {}", paths.iter().map(|i| i.name()).collect::<Vec<_>>().join(", "));
}

#[test]
fn an_unavailable_or_unknown_path_is_refused_with_the_available_ones() {
    assert!(Isa::parse("mmx").is_err());
    for isa in Isa::ALL.into_iter().filter(|i| !i.available()) {
        let e = isa::force(isa).unwrap_err().to_string();
        assert!(e.contains(isa.name()) && e.contains("sse2"), "{e}");
    }
}
