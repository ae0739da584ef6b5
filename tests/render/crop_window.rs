//! A cropped sample is made over its window only (`Generator::sample_cropped`), and it is the
//! whole frame's sample cut to the window wherever the window alone decides: image1, the flow,
//! `valid`, the occlusion, mask1, depth1 and the camera bit for bit, image2 and its labels and
//! depth wherever no hole is filled. The holes are the whole frame's except where the planes
//! fill's vertical opening meets the window's top or bottom edge. A crop the size of the frame
//! is no crop; a larger one is refused with both sizes.

use std::sync::Arc;

use mpiflow::sample::config::SampleConfig;
use mpiflow::sample::crop::{crop_sample, CropSpec};
use mpiflow::sample::error::SampleError;
use mpiflow::sample::pipeline::{open_source, OpenOptions, Pipeline, SourceSpec};
use mpiflow::scene::cache::SceneCache;
use mpiflow::scene::models::ModelConfig;

fn pipeline(w: usize, h: usize) -> Pipeline {
    let open = OpenOptions { resize: Some((w, h)), ..OpenOptions::default() };
    let stage = Arc::new(ModelConfig::default().build_stage().unwrap());
    let source = open_source(&SourceSpec::Builtin, &open).unwrap();
    Pipeline::new(source, stage, Arc::new(SceneCache::new(1 << 30)), SampleConfig::default()).unwrap()
}

#[test]
fn a_cropped_sample_is_the_whole_frames_cut_to_its_window() {
    let (fw, fh) = (192, 144);
    let p = pipeline(fw, fh);
    let g = p.generator();
    let (mut holes_seen, mut objects_seen, mut edge_only) = (0u64, 0usize, 0usize);
    for (index, crop) in (0..8u64).zip(
        [CropSpec { width: 120, height: 88, random: true }, CropSpec { width: 96, height: 0, random: false }]
            .iter()
            .cycle(),
    ) {
        let full = g.sample(5, index).unwrap();
        let (s, (x0, y0)) = g.sample_cropped(5, index, crop).unwrap();
        let (cw, ch) = (s.width, s.height);
        assert_eq!((cw, ch), (crop.width as usize, if crop.height == 0 { fh } else { crop.height as usize }));
        assert!(x0 + cw <= fw && y0 + ch <= fh);
        let cut = crop_sample(&full, x0, y0, cw, ch);
        assert_eq!(s.intrinsics, cut.intrinsics, "sample {index}");
        assert_eq!(s.image1, cut.image1, "image1 of sample {index}");
        assert_eq!(s.flow, cut.flow, "flow of sample {index}");
        assert_eq!(s.valid, cut.valid, "valid of sample {index}");
        assert_eq!(s.occlusion, cut.occlusion, "occlusion of sample {index}");
        assert_eq!(s.mask1, cut.mask1, "mask1 of sample {index}");
        assert_eq!(s.depth1, cut.depth1, "depth1 of sample {index}");
        assert_eq!(s.objects.len(), cut.objects.len());
        objects_seen += s.objects.len();
        for i in 0..cw * ch {
            let (x, y) = (i % cw, i / cw);
            if s.holes[i] != cut.holes[i] {
                // the planes fill keeps column runs of three holes or more: the window cuts runs
                assert!(y < 2 || y + 2 >= ch, "sample {index}: hole at ({x}, {y}) differs inside the window");
                edge_only += 1;
                continue;
            }
            if s.holes[i] != 0 {
                holes_seen += 1;
                continue;
            }
            assert_eq!(
                s.image2[3 * i..3 * i + 3],
                cut.image2[3 * i..3 * i + 3],
                "image2 of sample {index} at ({x}, {y})"
            );
            assert_eq!(s.mask2[i], cut.mask2[i], "mask2 of sample {index} at ({x}, {y})");
            assert_eq!(s.depth2[i].to_bits(), cut.depth2[i].to_bits(), "depth2 of sample {index} at ({x}, {y})");
        }
        assert_eq!(s.inpainted_pixels, s.holes.iter().filter(|&&o| o != 0).count() as u64);
        assert!(s.image2.len() == 3 * cw * ch && s.depth2.iter().all(|d| d.is_finite()));
    }
    assert!(
        holes_seen > 0 && objects_seen > 0,
        "the samples exercise holes ({holes_seen}) and objects ({objects_seen})"
    );
    assert!(edge_only < 200, "{edge_only} hole pixels differ at the window's edges");
}

#[test]
fn a_crop_of_the_whole_frame_is_no_crop_and_a_larger_one_is_refused() {
    let p = pipeline(96, 64);
    let g = p.generator();
    let full = g.sample(1, 3).unwrap();
    let (same, corner) = g.sample_cropped(1, 3, &CropSpec { width: 96, height: 64, random: true }).unwrap();
    assert_eq!(corner, (0, 0));
    assert_eq!((same.image2, same.flow, same.holes), (full.image2, full.flow, full.holes));
    let e = g.sample_cropped(1, 3, &CropSpec { width: 97, height: 10, random: false }).unwrap_err();
    assert!(matches!(e, SampleError::Crop(_)), "{e:?}");
    assert_eq!(e.to_string(), "97x10 is larger than the rendered frame 96x64");
}
