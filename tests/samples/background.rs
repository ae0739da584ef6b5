//! Background from the MPI before 2-D inpainting: where a moved object leaves
//! its place, image2 shows what the MPI's planes hold behind it, exactly, and only what no plane
//! covers is inpainted; `background = "inpaint"` and the reference merge keep the paper's rule.

use std::sync::Arc;

use mpiflow::bench::quality::label_laws;
use mpiflow::geometry::Intrinsics;
use mpiflow::io::image::RgbImage;
use mpiflow::mpi::Mpi;
use mpiflow::raster::{Instance, InstanceMasks};
use mpiflow::sample::background::Background;
use mpiflow::sample::config::{MotionSpec, SampleConfig};
use mpiflow::sample::merge::{unit_to_u8, MergeRule};
use mpiflow::sample::motion::{Axes, Component, MotionRanges, RigidLaw, RotationKind};
use mpiflow::sample::recipe::{assemble, assemble_with_target_depth};
use mpiflow::sample::SampleAddress;
use mpiflow::scene::{Disparity, Scene};

const W: usize = 96;
const H: usize = 64;
/// The object: `[x0, x1) x [y0, y1)`.
const SQUARE: (usize, usize, usize, usize) = (36, 60, 20, 44);
const OBJECT: [f32; 3] = [0.9, 0.1, 0.1];

fn inside(x: usize, y: usize) -> bool {
    (SQUARE.0..SQUARE.1).contains(&x) && (SQUARE.2..SQUARE.3).contains(&y)
}

/// The background texture, the same in front of and behind the object: a checkerboard of
/// 3-pixel cells no 2-D inpainting can guess from the pixels around the object.
fn texture(x: usize, y: usize) -> [f32; 3] {
    if (x / 3 + y / 3).is_multiple_of(2) {
        [0.15, 0.7, 0.3]
    } else {
        [0.8, 0.75, 0.2]
    }
}

/// A network-like MPI: five planes at disparities 1, 0.8, 0.6, 0.4, 0.2; the object opaque on
/// plane 1 (depth 1.25) over the square, the background opaque on the last plane everywhere,
/// holding the texture behind the object too (what an MPI network's back planes predict).
fn scene() -> Scene {
    let k = Intrinsics::reference_default(W, H);
    let disp = vec![1.0, 0.8, 0.6, 0.4, 0.2];
    let n = disp.len();
    let mut mpi = Mpi::new(W, H, disp.clone(), 0);
    let mut image = vec![0.0f32; W * H * 3];
    let mut disparity = vec![0.2f32; W * H];
    let mut mask = vec![0.0f32; W * H];
    for y in 0..H {
        for x in 0..W {
            let p = y * W + x;
            let back = 4 * ((n - 1) * W * H + p);
            mpi.rgba[back..back + 3].copy_from_slice(&texture(x, y));
            mpi.rgba[back + 3] = mpiflow::mpi::SIGMA_MAX;
            let mut c = texture(x, y);
            if inside(x, y) {
                let o = 4 * (W * H + p);
                mpi.rgba[o..o + 3].copy_from_slice(&OBJECT);
                mpi.rgba[o + 3] = 1e4;
                c = OBJECT;
                disparity[p] = 0.8;
                mask[p] = 1.0;
            }
            image[3 * p..3 * p + 3].copy_from_slice(&c);
        }
    }
    mpi.validate().unwrap();
    Scene {
        id: "checker".into(),
        image: RgbImage { width: W, height: H, data: image },
        disparity: Disparity { width: W, height: H, data: disparity },
        mpi: Arc::new(mpi),
        masks: InstanceMasks { width: W, height: H, masks: vec![Instance::new(1, 0.9, mask)] },
        intrinsics: k,
        provenance: vec!["test: checker".into()],
    }
}

fn rigid(t: [f64; 3]) -> RigidLaw {
    let c = Component::constant;
    RigidLaw {
        translation: Axes::new(c(t[0]), c(t[1]), c(t[2])),
        rotation_kind: RotationKind::AxisAngle,
        rotation: Axes::new(c(0.0), c(0.0), c(0.0)),
    }
}

fn config(camera: [f64; 3], object: [f64; 3], merge: MergeRule, background: Background) -> SampleConfig {
    let ranges = MotionRanges {
        name: "test".into(),
        camera: rigid(camera),
        object: rigid(object),
        stereo: false,
        reveal_budget: None,
    };
    SampleConfig {
        motion: MotionSpec::Ranges(Box::new(ranges)),
        merge,
        background,
        resample: mpiflow::render::Resample::Bilinear,
        ..SampleConfig::default()
    }
}

const ADDR: SampleAddress = SampleAddress { dataset: 1, seed: 2, index: 3 };

/// Camera still, object moved right by ~13 px. Its render carries the planes behind it along
/// (the reference's broadcast mask channel), so the holes it leaves are the strip at its trailing
/// edge where those back planes moved away too (~3 px wide here): there image2 shows the
/// texture behind the object, exactly, and no hole; with `inpaint` (and the reference merge)
/// the same pixels are holes filled by Telea, which cannot reproduce the texture.
#[test]
fn the_place_an_object_leaves_shows_the_planes_behind_it() {
    let scene = scene();
    let object = [0.3, 0.0, 0.0];
    let make = |merge, background| {
        assemble_with_target_depth(&scene, ADDR, &config([0.0; 3], object, merge, background), None).unwrap()
    };
    let (planes, planes_z) = make(MergeRule::DepthAware, Background::Planes);
    let (inpaint, inpaint_z) = make(MergeRule::DepthAware, Background::Inpaint);
    let (reference, _) = make(MergeRule::Reference, Background::Planes);
    // the holes the object leaves in its old place without the planes
    let (mut strip, mut texture_exact, mut inpaint_exact) = (0usize, 0usize, 0usize);
    for y in SQUARE.2 + 1..SQUARE.3 - 1 {
        for x in SQUARE.0..SQUARE.1 {
            let p = y * W + x;
            if inpaint.holes[p] == 0 {
                continue;
            }
            strip += 1;
            let want = texture(x, y).map(unit_to_u8);
            assert_eq!(planes.holes[p], 0, "({x},{y}) is shown by the planes, not inpainted");
            assert_eq!(reference.holes[p], 1, "({x},{y}) is a hole with the reference merge");
            assert_eq!(planes.mask2[p], 0, "the background carries no object label");
            assert!(
                (planes.depth2[p] - 5.0).abs() < 1e-3,
                "depth2 at ({x},{y}) is the back plane's: {}",
                planes.depth2[p]
            );
            let got = [0, 1, 2].map(|c| planes.image2[3 * p + c]);
            texture_exact += usize::from(got == want);
            inpaint_exact += usize::from([0, 1, 2].map(|c| inpaint.image2[3 * p + c]) == want);
        }
    }
    assert!(strip >= 40, "{strip} strip pixels");
    assert_eq!(texture_exact, strip, "every strip pixel shows the texture behind the object");
    assert!(inpaint_exact * 2 < strip, "Telea guessed {inpaint_exact} of {strip} texture pixels");
    assert!(
        planes.inpainted_pixels + strip as u64 <= inpaint.inpainted_pixels,
        "planes: {} inpainted, inpaint: {}",
        planes.inpainted_pixels,
        inpaint.inpainted_pixels
    );
    // nothing else changes: the source side and the labels are the merge's
    assert_eq!(planes.flow, inpaint.flow);
    assert_eq!(planes.valid, inpaint.valid);
    assert_eq!(planes.occlusion, inpaint.occlusion);
    assert_eq!(planes.mask1, inpaint.mask1);
    assert_eq!(planes.mask2, inpaint.mask2);
    for (s, z) in [(&planes, &planes_z), (&inpaint, &inpaint_z)] {
        let laws = label_laws(s, z);
        assert_eq!((laws.holes, laws.label, laws.depth), (0, 0, 0), "label laws: {laws:?}");
    }
}

/// Under a camera motion too (and in a clip, every frame), what the planes show is no hole and
/// the backward flow stays honest there: pixels filled from the planes are not valid backward
/// (their surface is hidden in image1).
#[test]
fn filled_pixels_under_camera_motion_and_in_clips() {
    let scene = scene();
    let mut cfg = config([0.02, 0.01, 0.0], [0.12, 0.02, 0.0], MergeRule::DepthAware, Background::Planes);
    cfg.frames = 3;
    cfg.backward = true;
    let s = assemble(&scene, ADDR, &cfg).unwrap();
    let mut off = cfg.clone();
    off.background = Background::Inpaint;
    let t = assemble(&scene, ADDR, &off).unwrap();
    let filled: Vec<usize> = (0..W * H).filter(|&p| s.holes[p] == 0 && t.holes[p] == 1).collect();
    assert!(filled.len() >= 40, "{} pixels filled from the planes in frame 2", filled.len());
    assert!((0..W * H).all(|p| s.holes[p] <= t.holes[p]), "the planes only ever remove holes");
    for &p in &filled {
        assert_eq!(s.backward.valid[p], 0, "pixel {p}: filled from the planes, no backward flow");
    }
    assert_eq!(s.backward.flow, t.backward.flow, "the backward fields do not change");
    assert_eq!(s.backward.valid, t.backward.valid);
    let (a, b) = (&s.clip[0], &t.clip[0]);
    let later: usize = (0..W * H).filter(|&p| a.holes[p] == 0 && b.holes[p] == 1).count();
    assert!(later >= 40, "{later} pixels of frame 3 filled from the planes");
    assert_eq!(a.forward.flow, b.forward.flow);
    assert_eq!(a.backward.valid, b.backward.valid);
    assert!(s.depth2.iter().chain(&a.depth).all(|d| d.is_finite() && *d >= 0.0));
}
