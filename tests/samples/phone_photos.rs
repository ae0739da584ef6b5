//! Photos as phones store them: a JPEG kept sideways with an EXIF orientation tag is decoded
//! upright, and depth given upright (in the orientation of the photo as displayed) lines up with
//! it in the scene; the tag moves the fingerprint only of the folders (shards, uploads) whose
//! photos carry one. Depth and masks of another aspect than their photo's are refused naming
//! both shapes and the likely cause; of the same aspect at another resolution they are resized.
//! WebP photos are read; every other file of a photo folder is counted as left out, by reason
//! (HEIC/HEIF named with the advice to convert it). A folder's photos are checked when it is
//! opened: those that cannot serve are left out of the index, so the others keep equal weight
//! and the scene window its interleaving; `serve` logs the summary, `--strict` refuses.

use std::path::{Path, PathBuf};

use image::codecs::jpeg::JpegEncoder;
use image::{ExtendedColorType, ImageEncoder};
use mpiflow::io::image::{load_rgb, orientation_of_prefix, read_header, ImageLimits, HEIC_ADVICE};
use mpiflow::sample::config::SampleConfig;
use mpiflow::sample::pipeline::Pipeline;
use mpiflow::scene::cache::SceneCache;
use mpiflow::scene::stage::SceneStage;
use mpiflow::source::dir::{DirSource, SourceOptions};
use mpiflow::source::encoded::{decode_item, DepthEncoding, Encoded, EncodedItem};
use mpiflow::source::given::same_aspect;
use mpiflow::source::{FailureKind, GivenDepth, Source, SourceError};
use std::collections::{BTreeMap, BTreeSet};
use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::sync::Arc;

/// The photo as displayed: 48 x 32, a bright block in its upper-left part on a dark ground.
const W: u32 = 48;
const H: u32 = 32;

fn bright(x: u32, y: u32) -> bool {
    (4..20).contains(&x) && (4..14).contains(&y)
}

fn upright() -> image::RgbImage {
    image::RgbImage::from_fn(
        W,
        H,
        |x, y| if bright(x, y) { image::Rgb([230, 220, 210]) } else { image::Rgb([20, 30, 40]) },
    )
}

/// The depth of the photo as displayed (H x W, row-major): near on the block, far elsewhere.
fn upright_depth() -> Vec<f32> {
    (0..H * W).map(|i| if bright(i % W, i / W) { 1.0 } else { 4.0 }).collect()
}

/// An EXIF `APP1` segment (big-endian TIFF, one IFD0 entry) with orientation `o`.
fn exif_app1(o: u16) -> Vec<u8> {
    let mut tiff = b"MM\0\x2a\0\0\0\x08".to_vec();
    tiff.extend_from_slice(&1u16.to_be_bytes()); // one entry
    tiff.extend_from_slice(&0x0112u16.to_be_bytes()); // Orientation
    tiff.extend_from_slice(&3u16.to_be_bytes()); // SHORT
    tiff.extend_from_slice(&1u32.to_be_bytes()); // one value
    tiff.extend_from_slice(&o.to_be_bytes());
    tiff.extend_from_slice(&[0, 0]);
    tiff.extend_from_slice(&0u32.to_be_bytes()); // no next IFD
    let mut body = b"Exif\0\0".to_vec();
    body.extend(tiff);
    let mut seg = vec![0xFF, 0xE1];
    seg.extend_from_slice(&((body.len() + 2) as u16).to_be_bytes());
    seg.extend(body);
    seg
}

/// A JPEG of `img` with an EXIF segment of orientation `o` right after its start marker (as a
/// phone writes it), or none.
fn jpeg(img: &image::RgbImage, o: Option<u16>) -> Vec<u8> {
    let mut plain = Vec::new();
    JpegEncoder::new_with_quality(&mut plain, 95)
        .write_image(img.as_raw(), img.width(), img.height(), ExtendedColorType::Rgb8)
        .unwrap();
    let mut out = plain[..2].to_vec();
    if let Some(o) = o {
        out.extend(exif_app1(o));
    }
    out.extend_from_slice(&plain[2..]);
    out
}

/// The photo as a phone stores it for tag `o`: 6 means "turn a quarter clockwise to show", so
/// the stored pixels are the upright ones turned a quarter anticlockwise; 8 the other way.
fn stored_for(o: u16) -> image::RgbImage {
    match o {
        6 => image::imageops::rotate270(&upright()),
        8 => image::imageops::rotate90(&upright()),
        _ => upright(),
    }
}

fn tmp(name: &str) -> PathBuf {
    let d = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("orientation-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A reference-layout folder: `images/phone.jpg` (stored for tag `o`) with upright depth.
fn phone_folder(name: &str, o: Option<u16>, stored_tag: u16) -> PathBuf {
    let dir = tmp(name);
    std::fs::create_dir_all(dir.join("images")).unwrap();
    std::fs::create_dir_all(dir.join("depths")).unwrap();
    std::fs::write(dir.join("images/phone.jpg"), jpeg(&stored_for(stored_tag), o)).unwrap();
    mpiflow::io::npy::write_f32(&dir.join("depths/phone.npy"), &[u64::from(H), u64::from(W)], &upright_depth())
        .unwrap();
    dir
}

/// Mean brightness of the image where `near` is true and where it is false.
fn means(rgb: &[f32], near: &[bool]) -> (f32, f32) {
    let (mut a, mut na, mut b, mut nb) = (0.0, 0, 0.0, 0);
    for (i, &n) in near.iter().enumerate() {
        let v = (rgb[3 * i] + rgb[3 * i + 1] + rgb[3 * i + 2]) / 3.0;
        if n {
            a += v;
            na += 1;
        } else {
            b += v;
            nb += 1;
        }
    }
    (a / na as f32, b / nb as f32)
}

#[test]
fn exif_orientation_6_and_8_decode_upright() {
    for o in [6u16, 8] {
        let dir = tmp(&format!("decode-{o}"));
        let p = dir.join("phone.jpg");
        let bytes = jpeg(&stored_for(o), Some(o));
        std::fs::write(&p, &bytes).unwrap();
        assert_eq!(orientation_of_prefix(&bytes), o as u8);
        let header = read_header(&p, &ImageLimits::default()).unwrap();
        assert_eq!((header.width, header.height, header.stored_width, header.stored_height), (W, H, H, W));
        assert_eq!(header.orientation, o as u8);
        let img = load_rgb(&p, &ImageLimits::default()).unwrap();
        assert_eq!((img.width, img.height), (W as usize, H as usize), "orientation {o}");
        // every pixel is where the upright photo has it (JPEG error aside)
        let want = upright();
        for y in 0..H {
            for x in 0..W {
                let got = img.data[3 * (y * W + x) as usize];
                let exp = f32::from(want.get_pixel(x, y)[0]) / 255.0;
                // the block's edges ring a little under JPEG; its inside and the ground do not
                let edge =
                    (3..=4).contains(&x) || (19..=20).contains(&x) || (3..=4).contains(&y) || (13..=14).contains(&y);
                if !edge {
                    assert!((got - exp).abs() < 0.1, "orientation {o}: ({x}, {y}) is {got}, upright {exp}");
                }
            }
        }
        // without the tag the same pixels stay as stored: sideways
        let plain = dir.join("plain.jpg");
        std::fs::write(&plain, jpeg(&stored_for(o), None)).unwrap();
        let img = load_rgb(&plain, &ImageLimits::default()).unwrap();
        assert_eq!((img.width, img.height), (H as usize, W as usize));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}

#[test]
fn a_rotated_phone_jpeg_with_upright_depth_gives_a_scene_whose_depth_edges_follow_the_photo() {
    for o in [6u16, 8] {
        let dir = phone_folder(&format!("scene-{o}"), Some(o), o);
        let src = DirSource::open(&dir, &SourceOptions::default()).unwrap();
        let item = src.load(0).unwrap();
        assert_eq!((item.image.width, item.image.height), (W as usize, H as usize), "orientation {o}");
        // the depth is the file's own, not stretched: its values are the two levels, in place
        let Some(GivenDepth::Depth(d)) = &item.depth else { panic!("given depth") };
        assert_eq!(d, &upright_depth(), "orientation {o}");
        let scene = SceneStage::builtin().scene(item).unwrap();
        assert_eq!((scene.disparity.width, scene.disparity.height), (W as usize, H as usize));
        // the near (high disparity) part of the scene is the bright block of the photo
        let mid = {
            let (lo, hi) = scene.disparity.data.iter().fold((f32::MAX, f32::MIN), |(l, h), &v| (l.min(v), h.max(v)));
            (lo + hi) / 2.0
        };
        let near: Vec<bool> = scene.disparity.data.iter().map(|&v| v > mid).collect();
        let (on_near, on_far) = means(&scene.image.data, &near);
        assert!(on_near > 0.75 && on_far < 0.25, "orientation {o}: brightness {on_near} near, {on_far} far");
        // the depth edges are the photo's edges: no pixel of the block is far, none of the ground near
        for (i, &n) in near.iter().enumerate() {
            let (x, y) = (i as u32 % W, i as u32 / W);
            assert_eq!(n, bright(x, y), "orientation {o}: ({x}, {y})");
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}

#[test]
fn the_orientation_tag_changes_the_fingerprint_only_of_folders_that_carry_one() {
    // the same stored pixels and the same file sizes: tag 1 (identity) and tag 6
    let plain = |name: &str, o: u16| {
        let dir = tmp(name);
        std::fs::write(dir.join("phone.jpg"), jpeg(&stored_for(6), Some(o))).unwrap();
        dir
    };
    let (a, b, c) = (plain("fp-1", 1), plain("fp-6", 6), plain("fp-1-again", 1));
    let size = |d: &Path| std::fs::metadata(d.join("phone.jpg")).unwrap().len();
    assert_eq!(size(&a), size(&b));
    let fp = |d: &Path| DirSource::open(d, &SourceOptions::default()).unwrap().fingerprint();
    assert_ne!(fp(&a), fp(&b), "a photo turned upright when loaded has other bytes: another fingerprint");
    assert_eq!(fp(&a), fp(&c), "an identity tag changes nothing");
    for d in [a, b, c] {
        std::fs::remove_dir_all(&d).unwrap();
    }
}

/// A reference-layout folder: `images/p.png` of `W` x `H` (the block photo) and
/// `depths/p.npy` of `dw` x `dh` (the block's depth scaled to it).
fn depth_folder(name: &str, dw: usize, dh: usize) -> PathBuf {
    let dir = tmp(name);
    std::fs::create_dir_all(dir.join("images")).unwrap();
    std::fs::create_dir_all(dir.join("depths")).unwrap();
    upright().save(dir.join("images/p.png")).unwrap();
    let depth: Vec<f32> = (0..dw * dh)
        .map(|i| {
            let (x, y) = ((i % dw) * W as usize / dw, (i / dw) * H as usize / dh);
            if bright(x as u32, y as u32) {
                1.0
            } else {
                4.0
            }
        })
        .collect();
    mpiflow::io::npy::write_f32(&dir.join("depths/p.npy"), &[dh as u64, dw as u64], &depth).unwrap();
    dir
}

/// The refusal of a folder whose one item cannot serve: found when the folder is opened (the
/// item left out, so no photo is left), or, for a file changed after that, when it is loaded.
fn load_err(dir: &Path) -> (FailureKind, String) {
    let e = match DirSource::open(dir, &SourceOptions::default()) {
        Ok(src) => src.load(0).err().unwrap_or_else(|| panic!("{} loads", dir.display())),
        Err(e) => e,
    };
    match e {
        SourceError::File { kind, message, path } => (kind, format!("{path}: {message}")),
        e => panic!("another error: {e}"),
    }
}

#[test]
fn depth_of_another_aspect_is_refused_naming_both_shapes_and_the_cause() {
    // a square depth for a 3:2 photo: stretched it would cut across the content
    let (kind, m) = load_err(&depth_folder("aspect-square", 10, 10));
    assert_eq!(kind, FailureKind::Depth, "{m}");
    assert!(m.contains("depths/p.npy") && m.contains("depth is 10 x 10") && m.contains("photo is 48 x 32"), "{m}");
    assert!(m.contains("a crop of the photo, or another photo's file"), "{m}");
    // a transposed depth: turned a quarter against the photo
    let (kind, m) = load_err(&depth_folder("aspect-turned", H as usize, W as usize));
    assert_eq!(kind, FailureKind::Depth, "{m}");
    assert!(m.contains("depth is 32 x 48") && m.contains("photo is 48 x 32"), "{m}");
    assert!(m.contains("turned a quarter") && m.contains("orientation"), "{m}");
    // a cropped depth (a few columns short) is another view too
    let (_, m) = load_err(&depth_folder("aspect-crop", 44, 32));
    assert!(m.contains("depth is 44 x 32"), "{m}");
    // a depth replaced after the folder was opened: refused when the item is loaded
    let dir = depth_folder("aspect-later", 24, 16);
    let src = DirSource::open(&dir, &SourceOptions::default()).unwrap();
    mpiflow::io::npy::write_f32(&dir.join("depths/p.npy"), &[16, 16], &[2.0; 256]).unwrap();
    match src.load(0) {
        Err(SourceError::File { kind, message, .. }) => {
            assert_eq!(kind, FailureKind::Depth);
            assert!(message.contains("depth is 16 x 16 but its photo is 48 x 32"), "{message}");
        }
        other => panic!("{other:?}"),
    }
    std::fs::remove_dir_all(&dir).unwrap();
    // a sideways phone photo without its orientation tag, with upright depth: the same refusal
    let dir = phone_folder("aspect-untagged", None, 6);
    let (kind, m) = load_err(&dir);
    assert_eq!(kind, FailureKind::Depth, "{m}");
    assert!(m.contains("depth is 48 x 32 but its photo is 32 x 48") && m.contains("turned a quarter"), "{m}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn depth_and_masks_of_the_photos_aspect_at_another_resolution_are_resized() {
    // half the resolution: resized to the photo, the block's edges where the photo's are
    let dir = depth_folder("half", 24, 16);
    let src = DirSource::open(&dir, &SourceOptions::default()).unwrap();
    // counted in the source's record
    assert!(src.describe().contains("; 1 with depth or masks at another resolution, resized"), "{}", src.describe());
    let item = src.load(0).unwrap();
    let Some(GivenDepth::Depth(d)) = &item.depth else { panic!("given depth") };
    assert_eq!(d.len(), (W * H) as usize);
    for (i, &v) in d.iter().enumerate() {
        let (x, y) = (i as u32 % W, i as u32 / W);
        assert_eq!(v == 1.0, bright(x, y), "({x}, {y}): {v}");
    }
    // a pixel of rounding is not another aspect: 49 x 32 and 25 x 17 are taken and resized
    assert!(same_aspect(49, 32, 48, 32) && same_aspect(25, 17, 48, 32) && same_aspect(450, 375, 225, 188));
    assert!(!same_aspect(10, 10, 128, 96) && !same_aspect(96, 128, 128, 96) && !same_aspect(44, 32, 48, 32));
    let src = DirSource::open(&depth_folder("rounding", 25, 17), &SourceOptions::default()).unwrap();
    assert!(src.load(0).is_ok());

    // masks: the same rule, by nearest neighbour
    let dir = depth_folder("masks", 48, 32);
    std::fs::create_dir_all(dir.join("masks")).unwrap();
    let ids =
        |w: u32, h: u32| image::GrayImage::from_fn(w, h, |x, y| image::Luma([u8::from(bright(x * W / w, y * H / h))]));
    ids(24, 16).save(dir.join("masks/p.png")).unwrap();
    let item = DirSource::open(&dir, &SourceOptions::default()).unwrap().load(0).unwrap();
    let m = item.masks.expect("masks");
    assert_eq!((m.width, m.height, m.masks.len()), (48, 32, 1));
    ids(32, 48).save(dir.join("masks/p.png")).unwrap();
    let (kind, msg) = load_err(&dir);
    assert_eq!(kind, FailureKind::Mask, "{msg}");
    assert!(msg.contains("masks is 32 x 48 but its photo is 48 x 32") && msg.contains("turned a quarter"), "{msg}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn encoded_items_of_uploads_and_shards_follow_the_same_rules() {
    let photo = jpeg(&stored_for(6), Some(6));
    let npy = |w: usize, h: usize| {
        let dir = tmp(&format!("npy-{w}x{h}"));
        let p = dir.join("d.npy");
        mpiflow::io::npy::write_f32(&p, &[h as u64, w as u64], &vec![2.0; w * h]).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
        bytes
    };
    let item = |depth: &[u8]| {
        decode_item(
            EncodedItem {
                id: "phone".into(),
                image: Encoded { name: "upload:d/image/phone".into(), bytes: &photo },
                depth: Some((DepthEncoding::Npy, Encoded { name: "upload:d/depth/phone".into(), bytes: depth })),
                masks: None,
                intrinsics: None,
            },
            &SourceOptions::default(),
        )
    };
    // upright depth for the sideways-stored, tagged photo: taken as it is
    let ok = item(&npy(W as usize, H as usize)).unwrap();
    assert_eq!((ok.image.width, ok.image.height), (W as usize, H as usize));
    // depth of the stored (sideways) shape: refused, naming both shapes
    match item(&npy(H as usize, W as usize)) {
        Err(SourceError::File { kind, message, path }) => {
            assert_eq!(kind, FailureKind::Depth);
            assert_eq!(path, "upload:d/depth/phone");
            assert!(message.contains("depth is 32 x 48 but its photo is 48 x 32"), "{message}");
        }
        other => panic!("{other:?}"),
    }
}

/// The block photo as a lossless WebP.
fn webp() -> Vec<u8> {
    let mut out = Vec::new();
    image::codecs::webp::WebPEncoder::new_lossless(&mut out)
        .write_image(upright().as_raw(), W, H, ExtendedColorType::Rgb8)
        .unwrap();
    out
}

/// The start of a HEIC file as an iPhone writes it (an ISO-BMFF `ftyp` box of brand `heic`).
fn heic() -> Vec<u8> {
    let mut b = vec![0, 0, 0, 24];
    b.extend_from_slice(b"ftypheic\0\0\0\0mif1heic");
    b.extend_from_slice(&[0; 64]);
    b
}

#[test]
fn a_folder_reads_webp_and_counts_every_file_it_leaves_out_by_reason() {
    let dir = tmp("formats");
    std::fs::write(dir.join("a.jpg"), jpeg(&upright(), None)).unwrap();
    std::fs::write(dir.join("b.webp"), webp()).unwrap();
    std::fs::write(dir.join("IMG_0001.HEIC"), heic()).unwrap();
    std::fs::write(dir.join("IMG_0002.heif"), heic()).unwrap();
    std::fs::write(dir.join("notes.txt"), b"my photos").unwrap();
    std::fs::write(dir.join("c.gif"), b"GIF89a\x01\x00\x01\x00\x00\x00\x00;").unwrap();
    let src = DirSource::open(&dir, &SourceOptions::default()).unwrap();
    assert_eq!((src.len(), src.id(0), src.id(1)), (2, "a".to_string(), "b".to_string()));
    // the WebP decodes losslessly, as the photo it was made from
    let b = src.load(1).unwrap();
    let want: Vec<f32> = upright().as_raw().iter().map(|&v| f32::from(v) / 255.0).collect();
    assert_eq!((b.image.width, b.image.height), (W as usize, H as usize));
    assert_eq!(b.image.data, want);
    // every other file counted, by reason, named
    let skipped = src.skipped();
    let got: Vec<(&str, &str)> = skipped.iter().map(|s| (s.item.as_str(), s.kind.as_str())).collect();
    assert_eq!(
        got,
        [
            ("IMG_0001.HEIC", "unsupported"),
            ("IMG_0002.heif", "unsupported"),
            ("c.gif", "unsupported"),
            ("notes.txt", "unsupported")
        ]
    );
    assert_eq!(skipped[0].reason, HEIC_ADVICE);
    assert!(HEIC_ADVICE.starts_with("HEIC: not supported, convert to JPEG"));
    assert_eq!(skipped[2].reason, "not a photo mpiflow reads (PNG, JPEG or WebP)");
    let d = src.describe();
    assert!(d.contains("(2 images"), "{d}");
    assert!(
        d.ends_with(
            "4 left out: 2 HEIC: not supported, convert to JPEG (IMG_0001.HEIC, IMG_0002.heif), 2 unsupported (c.gif, \
             notes.txt)"
        ),
        "{d}"
    );
    // a folder of HEIC photos only: the error says why and what to do
    let only = tmp("formats-heic");
    std::fs::write(only.join("IMG_0001.HEIC"), heic()).unwrap();
    let e = DirSource::open(&only, &SourceOptions::default()).unwrap_err().to_string();
    assert!(e.contains("1 HEIC/HEIF photos: not supported, convert them to JPEG"), "{e}");
    // one HEIC file given as the source
    let e = DirSource::open(&only.join("IMG_0001.HEIC"), &SourceOptions::default()).unwrap_err().to_string();
    assert!(e.contains(HEIC_ADVICE), "{e}");
    for d in [dir, only] {
        std::fs::remove_dir_all(&d).unwrap();
    }
}

#[test]
fn generate_makes_samples_from_a_webp_photo() {
    let dir = tmp("webp-generate");
    std::fs::create_dir_all(dir.join("src/images")).unwrap();
    std::fs::create_dir_all(dir.join("src/depths")).unwrap();
    std::fs::write(dir.join("src/images/b.webp"), webp()).unwrap();
    mpiflow::io::npy::write_f32(&dir.join("src/depths/b.npy"), &[u64::from(H), u64::from(W)], &upright_depth())
        .unwrap();
    let out = dir.join("out");
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_mpiflow"))
        .args(["generate", "--count", "2", "--source"])
        .arg(dir.join("src"))
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    assert!(!stderr.contains("warning"), "{stderr}");
    // two samples, each naming the WebP photo as its source
    for key in ["00000000", "00000001"] {
        let j: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join(format!("{key}.json"))).unwrap()).unwrap();
        assert_eq!(j["source_id"], "b", "{j}");
        let img = load_rgb(&out.join(format!("{key}_img1.png")), &ImageLimits::default()).unwrap();
        assert_eq!((img.width, img.height), (W as usize, H as usize));
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A reference-layout folder of 12 photos (64 x 48, each its own pattern, each with depth), four
/// of which cannot serve: a JPEG cut short, a file that is no image, a photo over the size
/// limit, a depth turned a quarter against its photo.
fn twelve_with_four_bad(name: &str) -> PathBuf {
    let dir = tmp(name);
    std::fs::create_dir_all(dir.join("images")).unwrap();
    std::fs::create_dir_all(dir.join("depths")).unwrap();
    let (w, h) = (64u32, 48u32);
    for k in 0..12u32 {
        let img = image::RgbImage::from_fn(w, h, |x, y| {
            let v = |c: u32| ((x * (2 + c + k) + y * (3 + k) + 40 * c + 19 * k) % 256) as u8;
            image::Rgb([v(0), v(1), v(2)])
        });
        let depth: Vec<f32> = (0..w * h).map(|i| 1.0 + ((i % w) + k) as f32 / 32.0).collect();
        let id = format!("p{k:02}");
        match k {
            3 => {
                let bytes = jpeg(&img, None);
                std::fs::write(dir.join(format!("images/{id}.jpg")), &bytes[..bytes.len() / 2]).unwrap();
            }
            6 => std::fs::write(dir.join(format!("images/{id}.png")), b"\x00\x01 not an image at all").unwrap(),
            9 => image::GrayImage::new(9000, 2).save(dir.join(format!("images/{id}.png"))).unwrap(),
            _ => img.save(dir.join(format!("images/{id}.png"))).unwrap(),
        }
        let shape = if k == 10 { [u64::from(w), u64::from(h)] } else { [u64::from(h), u64::from(w)] };
        mpiflow::io::npy::write_f32(&dir.join(format!("depths/{id}.npy")), &shape, &depth).unwrap();
    }
    dir
}

const BAD: [(&str, &str); 4] = [
    ("depths/p10.npy", "depth"),
    ("images/p03.jpg", "truncated"),
    ("images/p06.png", "decode"),
    ("images/p09.png", "too-large"),
];

#[test]
fn photos_that_cannot_serve_are_left_out_so_the_others_keep_equal_weight() {
    let dir = twelve_with_four_bad("equal-weight");
    let src = DirSource::open(&dir, &SourceOptions::default()).unwrap();
    let ids: Vec<String> = (0..src.len()).map(|i| src.id(i)).collect();
    assert_eq!(ids, ["p00", "p01", "p02", "p04", "p05", "p07", "p08", "p11"]);
    let skipped: Vec<(String, String)> =
        src.skipped().iter().map(|s| (s.item.clone(), s.kind.as_str().to_string())).collect();
    let want: Vec<(String, String)> = BAD.iter().map(|(a, b)| (a.to_string(), b.to_string())).collect();
    assert_eq!(skipped, want);
    for s in src.skipped() {
        assert!(!s.reason.is_empty() && !s.reason.contains(&dir.display().to_string()), "{s:?}");
    }
    let d = src.describe();
    assert!(
        d.contains("(8 images") && d.contains("4 left out: 1 decode (images/p06.png), 1 depth (depths/p10.npy)"),
        "{d}"
    );

    // 8 x 88 samples: each good photo exactly 88 times, and any 8 consecutive samples from at
    // least 6 photos
    let source: Arc<dyn Source> = Arc::new(src);
    let stage = Arc::new(SceneStage::builtin());
    let p = Pipeline::new(source, stage, Arc::new(SceneCache::new(1 << 30)), SampleConfig::default()).unwrap();
    let g = p.generator();
    let order: Vec<String> = (0..8 * 88).map(|i| g.sample(7, i).unwrap().source_id).collect();
    let mut counts: BTreeMap<&str, usize> = BTreeMap::new();
    for id in &order {
        *counts.entry(id.as_str()).or_default() += 1;
    }
    assert_eq!(counts.keys().copied().collect::<Vec<_>>(), ids.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(counts.values().all(|&n| n == 88), "{counts:?}");
    for (at, w) in order.windows(8).enumerate() {
        let distinct: BTreeSet<&String> = w.iter().collect();
        assert!(distinct.len() >= 6, "samples {at}..{}: {w:?}", at + 8);
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn serve_logs_what_it_left_out_at_start_up_and_strict_refuses() {
    let dir = twelve_with_four_bad("start-up");
    let bin = env!("CARGO_BIN_EXE_mpiflow");
    // --strict: no server, exit status 2, each file named by reason
    for args in [
        vec!["serve", "--strict", "--addr", "127.0.0.1:0", "--source"],
        vec!["generate", "--strict", "--count", "1", "--out", "/nonexistent/never-written", "--source"],
    ] {
        let o = Command::new(bin).args(&args).arg(&dir).output().unwrap();
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {stderr}");
        assert!(o.stdout.is_empty(), "{args:?}");
        assert!(stderr.starts_with("error: --strict: "), "{stderr}");
        for (item, kind) in BAD {
            assert!(stderr.contains(&format!("1 {kind} ({item})")), "{args:?}: {item} not named: {stderr}");
        }
    }
    // without it: serving the 8, the summary logged before the first line on stdout
    let mut child = Command::new(bin)
        .args(["serve", "--addr", "127.0.0.1:0", "--log-level", "info", "--source"])
        .arg(&dir)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    assert!(line.starts_with("mpiflow serving on "), "{line:?}");
    child.kill().unwrap();
    let out = child.wait_with_output().unwrap();
    let log = String::from_utf8_lossy(&out.stderr);
    let opened = log.lines().find(|l| l.contains("dataset opened")).unwrap_or_else(|| panic!("{log}"));
    assert!(opened.contains("8 images") && opened.contains("4 left out"), "{opened}");
    for (item, _) in BAD {
        assert!(opened.contains(item), "{item}: {opened}");
        assert!(log.lines().any(|l| l.contains("source item left out") && l.contains(item)), "{item}: {log}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `bake` and `bench quality` open the folder as `serve` does and print the same summary: what
/// they serve and what they passed over, by reason with the names.
#[test]
fn bake_and_bench_quality_print_the_folder_summary() {
    let dir = twelve_with_four_bad("summaries");
    let bin = env!("CARGO_BIN_EXE_mpiflow");
    let baked = dir.join("baked");
    let runs: [Vec<&std::ffi::OsStr>; 2] = [
        vec!["bake".as_ref(), "--quiet".as_ref(), "--out".as_ref(), baked.as_os_str()],
        vec!["bench".as_ref(), "quality".as_ref(), "--sharpness".as_ref(), "--count".as_ref(), "1".as_ref()],
    ];
    for args in runs {
        let o = Command::new(bin).args(&args).arg("--source").arg(&dir).output().unwrap();
        let (stdout, stderr) = (String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
        assert!(o.status.success(), "{args:?}: {stderr}");
        let summary = format!("{stdout}{stderr}");
        let line = summary.lines().find(|l| l.contains("left out:")).unwrap_or_else(|| panic!("{args:?}: {summary}"));
        assert!(line.contains("(8 images"), "{args:?}: {line}");
        assert!(
            line.contains(
                "4 left out: 1 decode (images/p06.png), 1 depth (depths/p10.npy), 1 too-large (images/p09.png), 1 \
                 truncated (images/p03.jpg)"
            ),
            "{args:?}: {line}"
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
