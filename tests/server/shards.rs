//! WebDataset shard sources: the shared vector written by the `webdataset` library, shards written
//! with the `tar` crate (every field, directories of shards, duplicates, members over the
//! limits), truncation at every cut, fingerprints, `open_source`'s dispatch, and a shard written by
//! Python's `webdataset.TarWriter` read back.
//!
//! The Python test runs under `$MPIFLOW_PYTHON` (set by `eval "$(bash tools/setup_python.sh)"`,
//! which `bash tools/test.sh` does).

use std::path::{Path, PathBuf};
use std::process::Command;

use mpiflow::geometry::Intrinsics;
use mpiflow::io::image::{load_rgb_from_bytes, ImageLimits};
use mpiflow::io::npy::write_f32_to;
use mpiflow::source::shard::{index_shard, split_key, ShardSource};
use mpiflow::source::{open_source, FailureKind, GivenDepth, IntrinsicsSpec, Source, SourceError, SourceOptions};

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("mpiflow-shards-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn vector() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/webdataset/webdataset-flow-000000.tar")
}

/// Writes a tar with the `tar` crate (GNU headers, end-of-archive blocks).
fn write_tar(path: &Path, members: &[(&str, Vec<u8>)]) {
    let mut b = tar::Builder::new(std::fs::File::create(path).unwrap());
    for (name, data) in members {
        let mut h = tar::Header::new_gnu();
        h.set_size(data.len() as u64);
        h.set_mode(0o644);
        h.set_cksum();
        b.append_data(&mut h, name, data.as_slice()).unwrap();
    }
    b.finish().unwrap();
}

fn photo(w: u32, h: u32, seed: u32) -> image::RgbImage {
    image::RgbImage::from_fn(w, h, |x, y| image::Rgb([(x * 9 + seed) as u8, (y * 11) as u8, ((x + y) * 5) as u8]))
}

fn encode<P: image::Pixel<Subpixel = S> + image::PixelWithColorType, S: image::Primitive>(
    img: &image::ImageBuffer<P, Vec<S>>,
    format: image::ImageFormat,
) -> Vec<u8>
where
    [S]: image::EncodableLayout,
{
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, format).unwrap();
    out.into_inner()
}

fn npy(h: usize, w: usize, data: &[f32]) -> Vec<u8> {
    let mut out = Vec::new();
    write_f32_to(&mut out, &[h as u64, w as u64], data).unwrap();
    out
}

/// A shard with every field: s0 (jpg, depth.npy, json), s1 (png, 16-bit disp.png, mask.png),
/// s2 (PNG, 8-bit depth.png, a json without intrinsics), s3 (no image), and a member without a
/// field.
fn full_shard(path: &Path) -> Vec<f32> {
    let (w, h) = (12u32, 8u32);
    let depth: Vec<f32> = (0..w * h).map(|i| 2.0 + i as f32 * 0.125).collect();
    let disp16 =
        image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_fn(w, h, |x, y| image::Luma([(x * 1000 + y) as u16]));
    let mask = image::GrayImage::from_fn(w, h, |x, _| {
        image::Luma([if x < 4 {
            0
        } else if x < 8 {
            3
        } else {
            7
        }])
    });
    let disp8 = image::GrayImage::from_fn(w / 2, h / 2, |x, _| image::Luma([(x * 40) as u8]));
    write_tar(
        path,
        &[
            ("s0.jpg", encode(&photo(w, h, 0), image::ImageFormat::Jpeg)),
            ("s0.depth.npy", npy(h as usize, w as usize, &depth)),
            ("s0.json", br#"{"fx": 10.0, "fy": 11.0, "cx": 6.0, "cy": 4.0, "note": "ignored"}"#.to_vec()),
            ("s1.png", encode(&photo(w, h, 1), image::ImageFormat::Png)),
            ("s1.disp.png", encode(&disp16, image::ImageFormat::Png)),
            ("s1.mask.png", encode(&mask, image::ImageFormat::Png)),
            ("README", b"no field".to_vec()),
            ("sub/s2.PNG", encode(&photo(w, h, 2), image::ImageFormat::Png)),
            ("sub/s2.depth.png", encode(&disp8, image::ImageFormat::Png)),
            ("sub/s2.json", br#"{"caption": "a photo"}"#.to_vec()),
            ("s3.txt", b"text only".to_vec()),
        ],
    );
    depth
}

#[test]
fn keys_and_fields_follow_the_webdataset_rule() {
    assert_eq!(split_key("a/b/0001.depth.npy"), Some(("a/b/0001".into(), "depth.npy".into())));
    assert_eq!(split_key("x.y.z/0001.jpg"), Some(("x.y.z/0001".into(), "jpg".into())));
    assert_eq!(split_key("0001"), None);
    assert_eq!(split_key(".hidden"), None);
    assert_eq!(split_key("k."), None);
}

#[test]
fn the_shared_vector_is_indexed_as_webdataset_reads_it() {
    let index = index_shard(&vector()).unwrap();
    assert_eq!(index.truncated, None);
    let keys: Vec<&str> = index.samples.iter().map(|s| s.key.as_str()).collect();
    assert_eq!(keys, ["chairs/000000", "chairs/000001"]);
    for s in &index.samples {
        let fields: Vec<(&str, u64)> = s.members.iter().map(|m| (m.field.as_str(), m.size)).collect();
        assert_eq!(
            fields,
            [
                ("flow.flo", 20012),
                ("flow.npy", 20128),
                ("img1.ppm", 7513),
                ("img2.ppm", 7513),
                ("json", 47),
                ("valid.png", 94)
            ]
        );
    }
    // members are read by offset: the .flo magic and the PNG signature are where the index says
    let bytes = std::fs::read(vector()).unwrap();
    let m = &index.samples[1].members[0];
    assert_eq!(&bytes[m.offset as usize..m.offset as usize + 4], &202021.25f32.to_le_bytes());
    let m = &index.samples[1].members[5];
    assert_eq!(&bytes[m.offset as usize..m.offset as usize + 8], b"\x89PNG\r\n\x1a\n");
    // no jpg/png image field: nothing to make scenes from, and the error says why
    let e = ShardSource::open(&vector(), &SourceOptions::default()).unwrap_err().to_string();
    assert!(e.contains("no usable samples") && e.contains("chairs/000000") && e.contains("no image"), "{e}");

    // cut inside chairs/000001's members: chairs/000000 stays, the cut sample is reported
    let dir = tmp("vector-cut");
    let cut = dir.join("cut.tar");
    let at = index.samples[1].members[2].offset as usize + 100;
    std::fs::write(&cut, &bytes[..at]).unwrap();
    let index = index_shard(&cut).unwrap();
    assert_eq!(index.samples.len(), 1);
    assert_eq!(index.incomplete_key.as_deref(), Some("chairs/000001"));
    assert!(index.truncated.as_deref().unwrap().contains("chairs/000001.img1.ppm"), "{:?}", index.truncated);
}

#[test]
fn a_shard_with_every_field_loads_like_a_directory() {
    let dir = tmp("full");
    let path = dir.join("train-000.tar");
    let depth = full_shard(&path);
    let src = ShardSource::open(&path, &SourceOptions::default()).unwrap();
    assert_eq!(src.len(), 3);
    assert_eq!((0..3).map(|i| src.id(i)).collect::<Vec<_>>(), ["s0", "s1", "sub/s2"]);
    let classes: Vec<(&str, &str)> = src.skipped().iter().map(|s| (s.item.as_str(), s.kind.as_str())).collect();
    assert_eq!(classes, [("train-000.tar:README", "unnamed"), ("train-000.tar:s3", "no-image")]);
    assert!(src.describe().contains("3 samples, 2 skipped"), "{}", src.describe());

    let s0 = src.load(0).unwrap();
    assert_eq!((s0.image.width, s0.image.height), (12, 8));
    assert_eq!(s0.depth, Some(GivenDepth::Depth(depth)));
    assert_eq!(s0.intrinsics, Some(Intrinsics::new(10.0, 11.0, 6.0, 4.0)));
    let s1 = src.load(1).unwrap();
    let expect =
        load_rgb_from_bytes(&encode(&photo(12, 8, 1), image::ImageFormat::Png), &ImageLimits::default()).unwrap();
    assert_eq!(s1.image, expect);
    match &s1.depth {
        Some(GivenDepth::Disparity(d)) => assert_eq!(d[12 + 5], (5 * 1000 + 1) as f32 / 65535.0),
        other => panic!("expected a disparity, got {other:?}"),
    }
    let ids: Vec<u32> = s1.masks.as_ref().unwrap().masks.iter().map(|m| m.id).collect();
    assert_eq!(ids, [3, 7]);
    assert_eq!(s1.intrinsics, None);
    let s2 = src.load(2).unwrap();
    match &s2.depth {
        // 6 x 4 resized to 12 x 8 by nearest neighbour
        Some(GivenDepth::Disparity(d)) => assert_eq!((d.len(), d[3]), (96, 40.0 / 255.0)),
        other => panic!("expected a disparity, got {other:?}"),
    }

    // resizing scales the json intrinsics; the run's intrinsics win over them
    let resized =
        ShardSource::open(&path, &SourceOptions { resize: Some((24, 4)), ..SourceOptions::default() }).unwrap();
    assert_eq!(resized.load(0).unwrap().intrinsics, Some(Intrinsics::new(20.0, 5.5, 12.0, 2.0)));
    let k = Intrinsics::new(1.0, 1.0, 0.5, 0.5);
    let fixed = SourceOptions { intrinsics: Some(IntrinsicsSpec::Relative(k)), ..SourceOptions::default() };
    let fixed = ShardSource::open(&path, &fixed).unwrap();
    assert_eq!(fixed.load(0).unwrap().intrinsics, Some(Intrinsics::new(12.0, 8.0, 6.0, 4.0)));
    assert_ne!(fixed.fingerprint(), src.fingerprint());
}

#[test]
fn truncated_shards_keep_their_complete_samples_at_every_cut() {
    let dir = tmp("cuts");
    let path = dir.join("full.tar");
    full_shard(&path);
    let bytes = std::fs::read(&path).unwrap();
    let full = ShardSource::open(&path, &SourceOptions::default()).unwrap();
    let full_ids: Vec<String> = (0..full.len()).map(|i| full.id(i)).collect();
    let cut_path = dir.join("cut.tar");
    let idx = index_shard(&path).unwrap();
    let last = idx.samples.last().unwrap().members.last().unwrap();
    let end_block = (last.offset + last.size).div_ceil(512) * 512 + 512;
    let mut seen_lens = std::collections::BTreeSet::new();
    // every 512-byte block boundary and a few bytes around each
    let cuts: Vec<usize> = (0..bytes.len()).filter(|c| matches!(c % 512, 0 | 1 | 100 | 511)).collect();
    for cut in cuts {
        std::fs::write(&cut_path, &bytes[..cut]).unwrap();
        // complete: every member and the first end-of-archive block are there
        let complete = cut as u64 >= end_block;
        match ShardSource::open(&cut_path, &SourceOptions::default()) {
            Ok(src) => {
                let ids: Vec<String> = (0..src.len()).map(|i| src.id(i)).collect();
                assert_eq!(ids[..], full_ids[..ids.len()], "cut {cut}: a prefix of the samples");
                let truncated = src.skipped().iter().any(|s| s.kind == FailureKind::Truncated);
                assert_eq!(truncated, !complete, "cut {cut}: {:?}", src.skipped());
                for i in 0..src.len() {
                    src.load(i).unwrap_or_else(|e| panic!("cut {cut}, item {i}: {e}"));
                }
                seen_lens.insert(src.len());
            }
            Err(e) => {
                let m = e.to_string();
                assert!(m.contains("no usable samples") || m.contains("truncated"), "cut {cut}: {m}");
                seen_lens.insert(0);
            }
        }
    }
    assert_eq!(seen_lens.into_iter().collect::<Vec<_>>(), [0, 1, 2, 3], "cuts inside every sample");
}

#[test]
fn directories_duplicates_limits_and_dispatch() {
    let dir = tmp("dir");
    let png = |seed| encode(&photo(8, 8, seed), image::ImageFormat::Png);
    write_tar(&dir.join("b.tar"), &[("k.png", png(1)), ("other.png", png(2)), ("k.png", png(3))]);
    write_tar(&dir.join("a.tar"), &[("k.png", png(4)), ("k.mask.png", png(5))]);
    std::fs::write(dir.join("notes.txt"), "ignored").unwrap();
    let src = ShardSource::open(&dir, &SourceOptions::default()).unwrap();
    assert_eq!((0..src.len()).map(|i| src.id(i)).collect::<Vec<_>>(), ["a/k", "b/k", "b/other"]);
    assert_eq!(src.skipped().len(), 1);
    assert_eq!((src.skipped()[0].item.as_str(), src.skipped()[0].kind), ("b.tar:k", FailureKind::Duplicate));
    assert!(src.describe().starts_with("shards:") && src.describe().contains("2 shards, 3 samples"));
    // a colour PNG as instance ids: each colour one instance
    assert!(src.load(0).unwrap().masks.is_some());

    // open_source: a .tar, a directory of shards, a directory of images, an ambiguous one
    let one = open_source(&dir.join("a.tar"), &SourceOptions::default()).unwrap();
    assert!(one.describe().starts_with("shard:"), "{}", one.describe());
    assert_eq!(one.id(0), "k");
    assert_eq!(open_source(&dir, &SourceOptions::default()).unwrap().fingerprint(), src.fingerprint());
    let imgs = tmp("dir-images");
    std::fs::write(imgs.join("p.png"), png(1)).unwrap();
    assert!(open_source(&imgs, &SourceOptions::default()).unwrap().describe().starts_with("dir:"));
    std::fs::copy(dir.join("a.tar"), imgs.join("a.tar")).unwrap();
    let e = open_source(&imgs, &SourceOptions::default()).err().unwrap().to_string();
    assert!(e.contains("both images and .tar shards"), "{e}");
    assert!(matches!(open_source(&dir.join("missing.tar"), &SourceOptions::default()), Err(SourceError::File { .. })));

    // a member over the byte limit fails its item only, as too-large
    let small =
        SourceOptions { limits: ImageLimits { max_bytes: 60, ..ImageLimits::default() }, ..SourceOptions::default() };
    let src = ShardSource::open(&dir, &small).unwrap();
    match src.load(1).unwrap_err() {
        SourceError::File { path, kind, message } => {
            assert_eq!(path, "b.tar:k.png");
            assert_eq!(kind, FailureKind::TooLarge, "{message}");
        }
        other => panic!("{other}"),
    }
    // a corrupt member fails its item only
    write_tar(&dir.join("c.tar"), &[("bad.jpg", b"\xff\xd8\xff\xe0\x00\x10JFIF".to_vec()), ("good.png", png(6))]);
    let src = ShardSource::open(&dir.join("c.tar"), &SourceOptions::default()).unwrap();
    let e = src.load(0).unwrap_err();
    assert_eq!(e.failure_kind(), Some(FailureKind::Truncated), "{e}");
    let e = e.to_string();
    assert!(e.starts_with("c.tar:bad.jpg: ") && e.contains("truncated JPEG"), "{e}");
    src.load(1).unwrap();
}

#[test]
fn fingerprints_follow_names_keys_and_sizes_not_folders() {
    let (d1, d2) = (tmp("fp1"), tmp("fp2"));
    let png = |seed| encode(&photo(8, 8, seed), image::ImageFormat::Png);
    let members = vec![("k0.png", png(1)), ("k1.png", png(2))];
    write_tar(&d1.join("s.tar"), &members);
    write_tar(&d2.join("s.tar"), &members);
    let fp = |p: &Path, hash: bool| {
        ShardSource::open(p, &SourceOptions { hash_contents: hash, ..SourceOptions::default() }).unwrap().fingerprint()
    };
    let base = fp(&d1.join("s.tar"), false);
    assert_eq!(base, fp(&d2.join("s.tar"), false), "same shard elsewhere, same fingerprint");
    std::fs::rename(d2.join("s.tar"), d2.join("t.tar")).unwrap();
    assert_ne!(base, fp(&d2.join("t.tar"), false), "shard name");
    write_tar(&d2.join("s.tar"), &[("k0.png", png(1)), ("k2.png", png(2))]);
    assert_ne!(base, fp(&d2.join("s.tar"), false), "key");
    write_tar(&d2.join("s.tar"), &[("k0.png", png(1)), ("k1.png", encode(&photo(9, 8, 2), image::ImageFormat::Png))]);
    assert_ne!(base, fp(&d2.join("s.tar"), false), "member size");
    // a same-size edit is seen with hash_contents only
    let mut edited = png(2);
    let n = edited.len();
    edited[n - 20] ^= 1;
    write_tar(&d2.join("s.tar"), &[("k0.png", png(1)), ("k1.png", edited)]);
    assert_eq!(base, fp(&d2.join("s.tar"), false));
    assert_ne!(fp(&d1.join("s.tar"), true), fp(&d2.join("s.tar"), true));
}

fn python() -> PathBuf {
    match std::env::var_os("MPIFLOW_PYTHON") {
        Some(p) if !p.is_empty() => PathBuf::from(p),
        _ => panic!(
            "MPIFLOW_PYTHON is not set: this test writes a shard with the webdataset library from the \
             project's Python environment; run `bash tools/test.sh` (or `eval \"$(bash tools/setup_python.sh)\"` first)"
        ),
    }
}

#[test]
fn a_shard_written_by_python_webdataset_reads_back() {
    let dir = tmp("python");
    let png_path = dir.join("photo.png");
    std::fs::write(&png_path, encode(&photo(20, 10, 3), image::ImageFormat::Png)).unwrap();
    let script = r#"
import sys, numpy as np, webdataset as wds
out, png = sys.argv[1], open(sys.argv[2], "rb").read()
h, w = 10, 20
depth = (1.5 + np.arange(h * w, dtype=np.float32).reshape(h, w) / 64).astype(np.float32)
rgb = np.zeros((h, w, 3), np.uint8); rgb[..., 0] = np.arange(w) * 10; rgb[..., 1] = 128
with wds.TarWriter(out) as sink:
    sink.write({"__key__": "scene/a001", "png": png, "depth.npy": depth,
                "json": {"fx": 12.0, "fy": 12.5, "cx": 10.0, "cy": 5.0, "source": "test"}})
    sink.write({"__key__": "scene/a002", "jpg": rgb, "mask.png": (np.arange(h * w).reshape(h, w) % 3).astype(np.uint8)})
    sink.write({"__key__": "scene/a003", "txt": "no image"})
"#;
    let script_path = dir.join("write.py");
    std::fs::write(&script_path, script).unwrap();
    let shard = dir.join("py-000000.tar");
    let out =
        Command::new(python()).arg(&script_path).arg(&shard).arg(&png_path).output().expect("cannot start python");
    assert!(out.status.success(), "{}\n{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));

    let src = open_source(&shard, &SourceOptions::default()).unwrap();
    assert_eq!((0..src.len()).map(|i| src.id(i)).collect::<Vec<_>>(), ["scene/a001", "scene/a002"]);
    assert_eq!(src.skipped().len(), 1);
    let a = src.load(0).unwrap();
    assert_eq!((a.image.width, a.image.height), (20, 10));
    let depth: Vec<f32> = (0..200).map(|i| 1.5 + i as f32 / 64.0).collect();
    assert_eq!(a.depth, Some(GivenDepth::Depth(depth)));
    assert_eq!(a.intrinsics, Some(Intrinsics::new(12.0, 12.5, 10.0, 5.0)));
    let b = src.load(1).unwrap();
    assert_eq!((b.image.width, b.image.height), (20, 10));
    // a JPEG of (10 x, 128, 0): within JPEG error
    let px = |x: usize| &b.image.data[3 * (5 * 20 + x)..3 * (5 * 20 + x) + 3];
    assert!((px(10)[0] - 100.0 / 255.0).abs() < 0.05 && (px(10)[1] - 128.0 / 255.0).abs() < 0.05, "{:?}", px(10));
    let ids: Vec<u32> = b.masks.as_ref().unwrap().masks.iter().map(|m| m.id).collect();
    assert_eq!(ids, [1, 2]);
}
