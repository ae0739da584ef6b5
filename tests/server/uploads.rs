//! Upload datasets: chunked files, names, kinds and limits, rejected files reported as
//! `name: reason`, atomic commits, snapshots with content fingerprints and a deterministic order.

use mpiflow::io::image::ImageLimits;
use mpiflow::io::npy::write_f32_to;
use mpiflow::source::upload::{validate_name, UploadLimits, UploadStore};
use mpiflow::source::{GivenDepth, Source, SourceError, SourceOptions};

fn png(w: u32, h: u32, seed: u32) -> Vec<u8> {
    let img = image::RgbImage::from_fn(w, h, |x, y| image::Rgb([(x * 9 + seed) as u8, (y * 11) as u8, seed as u8]));
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).unwrap();
    out.into_inner()
}

fn gray_png(w: u32, h: u32, v: u8) -> Vec<u8> {
    let img = image::GrayImage::from_fn(w, h, |x, _| image::Luma([if x < w / 2 { 0 } else { v }]));
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).unwrap();
    out.into_inner()
}

fn npy(h: usize, w: usize, v: f32) -> Vec<u8> {
    let mut out = Vec::new();
    write_f32_to(&mut out, &[h as u64, w as u64], &vec![v; h * w]).unwrap();
    out
}

fn store() -> std::sync::Arc<UploadStore> {
    UploadStore::new(SourceOptions::default(), UploadLimits::default())
}

#[test]
fn names_are_stems_only() {
    for ok in ["a", "IMG_0001", "photo-2.v3", "a.b_c-d"] {
        assert!(validate_name(ok).is_ok(), "{ok}");
    }
    for bad in ["", "a/b", "../x", "..", ".", ".hidden", "a..b", "a b", "a\\b", "é", "x\0", &"n".repeat(129)] {
        assert!(validate_name(bad).is_err(), "{bad:?}");
    }
}

#[test]
fn chunked_files_make_a_sorted_snapshot_whose_fingerprint_follows_content() {
    let st = store();
    let mut up = st.session().unwrap();
    // b's image in three chunks, then its depth; a's image and mask; order of arrival is not the order
    let b = png(16, 8, 2);
    up.push("photos", "b", "image", &b[..10]).unwrap();
    up.push("ignored", "", "", &b[10..30]).unwrap();
    up.push("", "", "", &b[30..]).unwrap();
    up.push("", "b", "depth", &npy(8, 16, 3.0)).unwrap();
    up.push("", "a", "image", &png(16, 8, 1)).unwrap();
    up.push("", "a", "mask", &gray_png(16, 8, 5)).unwrap();
    let sum = up.finish().unwrap();
    assert_eq!((sum.dataset.as_str(), sum.accepted, sum.sources), ("photos", 4, 2));
    assert!(sum.rejected.is_empty(), "{:?}", sum.rejected);
    let src = st.source("photos").unwrap();
    assert_eq!(src.fingerprint(), sum.fingerprint);
    assert_eq!((src.len(), src.id(0), src.id(1)), (2, "a".to_string(), "b".to_string()));
    let a = src.load(0).unwrap();
    assert_eq!(a.masks.unwrap().masks.len(), 1);
    assert_eq!(src.load(1).unwrap().depth, Some(GivenDepth::Depth(vec![3.0; 128])));
    assert!(st.dyn_source("photos").unwrap().describe().contains("upload:photos (2 images)"));

    // the same content uploaded in another order to another dataset: same fingerprint
    let mut up = st.session().unwrap();
    up.push("copy", "a", "image", &png(16, 8, 1)).unwrap();
    up.push("", "a", "mask", &gray_png(16, 8, 5)).unwrap();
    up.push("", "b", "depth", &npy(8, 16, 3.0)).unwrap();
    up.push("", "b", "image", &b).unwrap();
    assert_eq!(up.finish().unwrap().fingerprint, sum.fingerprint);

    // new content changes it; the old snapshot stays as it was
    let old = st.source("photos").unwrap();
    let mut up = st.session().unwrap();
    up.push("photos", "b", "depth", &npy(8, 16, 4.0)).unwrap();
    let s2 = up.finish().unwrap();
    assert_eq!((s2.accepted, s2.sources), (1, 2));
    assert_ne!(s2.fingerprint, sum.fingerprint);
    assert_eq!(old.fingerprint(), sum.fingerprint);
    assert_eq!(old.load(1).unwrap().depth, Some(GivenDepth::Depth(vec![3.0; 128])));
    assert_eq!(st.source("photos").unwrap().load(1).unwrap().depth, Some(GivenDepth::Depth(vec![4.0; 128])));
    let infos = st.datasets();
    assert_eq!(infos.iter().map(|d| d.name.as_str()).collect::<Vec<_>>(), ["copy", "photos"]);
    assert_eq!(st.total_bytes(), infos.iter().map(|d| d.bytes).sum::<u64>());
    assert!(st.remove("copy") && !st.remove("copy"));
    assert_eq!(st.total_bytes(), st.datasets()[0].bytes);
}

#[test]
fn bad_files_are_rejected_by_name_and_the_rest_is_kept() {
    let limits = ImageLimits { max_width: 64, max_bytes: 4000, ..ImageLimits::default() };
    let st = UploadStore::new(SourceOptions { limits, ..SourceOptions::default() }, UploadLimits::default());
    let mut up = st.session().unwrap();
    let good = png(16, 8, 1);
    up.push("ds", "good", "image", &good).unwrap();
    up.push("", "../etc/passwd", "image", &good).unwrap();
    up.push("", "odd", "video", &good).unwrap();
    up.push("", "corrupt", "image", b"\x89PNG\r\n\x1a\nnope").unwrap();
    let cut = png(16, 8, 3);
    up.push("", "cut", "image", &cut[..cut.len() / 2]).unwrap();
    up.push("", "wide", "image", &png(100, 4, 4)).unwrap();
    let big: Vec<u8> = (0..5000u32).map(|i| (i * 7919 % 251) as u8).collect();
    up.push("", "big", "image", &big[..3000]).unwrap();
    up.push("", "", "", &big[3000..]).unwrap();
    up.push("", "lonely", "depth", &npy(8, 16, 1.0)).unwrap();
    up.push("", "withbaddepth", "image", &good).unwrap();
    up.push("", "withbaddepth", "depth", b"neither npy nor png").unwrap();
    up.push("", "twice", "image", &good).unwrap();
    up.push("", "twice", "mask", &gray_png(16, 8, 1)).unwrap();
    up.push("", "twice", "image", &good).unwrap();
    let sum = up.finish().unwrap();
    assert_eq!(sum.sources, 1, "{:?}", sum.rejected);
    assert_eq!(sum.accepted, 1);
    let find = |name: &str| sum.rejected.iter().find(|r| r.starts_with(&format!("{name}: "))).cloned();
    for (name, needle) in [
        ("../etc/passwd", "invalid character '/'"),
        ("odd", "unknown kind \"video\""),
        ("corrupt", "corrupt"),
        ("cut", "unexpected end"),
        ("wide", "too large"),
        ("big", "per-file limit"),
        ("lonely", "without an image"),
        ("withbaddepth", "neither a .npy array nor a PNG"),
        ("twice", "sent twice as image"),
    ] {
        let r = find(name).unwrap_or_else(|| panic!("{name} not rejected: {:?}", sum.rejected));
        assert!(r.contains(needle), "{r}");
    }
    let src = st.source("ds").unwrap();
    assert_eq!((src.len(), src.id(0)), (1, "good".to_string()));
}

#[test]
fn limits_and_malformed_streams_fail_the_whole_upload() {
    let limits = UploadLimits {
        max_upload_bytes: 3000,
        max_total_bytes: 5000,
        max_datasets: 2,
        max_items: 2,
        ..UploadLimits::default()
    };
    let st = UploadStore::new(SourceOptions::default(), limits);
    let mut up = st.session().unwrap();
    let e = up.push("", "a", "image", b"x").unwrap_err();
    assert!(matches!(&e, SourceError::Upload { field: "dataset", .. }), "{e}");
    assert!(e.to_string().starts_with("dataset: "), "{e}");
    drop(up);
    let mut up = st.session().unwrap();
    let e = up.push("bad/name", "a", "image", b"x").unwrap_err();
    assert!(matches!(&e, SourceError::Upload { field: "dataset", message } if message.contains("no paths")), "{e}");
    drop(up);
    let mut up = st.session().unwrap();
    let e = up.push("ds", "", "", b"x").unwrap_err();
    assert!(matches!(&e, SourceError::Upload { field: "name", message } if message.contains("must name it")), "{e}");
    drop(up);
    let e = st.session().unwrap().finish().unwrap_err();
    assert!(matches!(&e, SourceError::Upload { field: "dataset", message } if message.contains("no chunks")), "{e}");

    let img = png(16, 8, 1);
    assert!(img.len() < 1000, "{}", img.len());
    let mut up = st.session().unwrap();
    up.push("ds", "a", "image", &img).unwrap();
    let e = up.push("", "b", "image", &vec![0u8; 3000]).unwrap_err();
    assert!(matches!(&e, SourceError::Limit(m) if m.contains("per-upload")), "{e}");
    assert!(st.source("ds").is_none(), "nothing of a failed upload is stored");

    // items per dataset
    drop(up);
    let mut up = st.session().unwrap();
    for name in ["a", "b", "c"] {
        up.push("ds", name, "image", &img).unwrap();
    }
    assert!(matches!(up.finish(), Err(SourceError::Limit(m)) if m.contains("per dataset")));
    assert!(st.source("ds").is_none());
    // datasets
    for ds in ["d1", "d2"] {
        let mut up = st.session().unwrap();
        up.push(ds, "a", "image", &img).unwrap();
        up.finish().unwrap();
    }
    let mut up = st.session().unwrap();
    up.push("d3", "a", "image", &img).unwrap();
    assert!(matches!(up.finish(), Err(SourceError::Limit(m)) if m.contains("datasets")));
    // the total: checked at the commit, items replaced by the upload not counted twice
    let limits = UploadLimits { max_total_bytes: 2 * img.len() as u64 + 10, ..UploadLimits::default() };
    let st = UploadStore::new(SourceOptions::default(), limits);
    for name in ["a", "b"] {
        let mut up = st.session().unwrap();
        up.push("ds", name, "image", &img).unwrap();
        up.finish().unwrap();
    }
    assert_eq!(st.total_bytes(), 2 * img.len() as u64);
    let mut up = st.session().unwrap();
    up.push("ds", "c", "image", &img).unwrap();
    let e = up.finish().unwrap_err();
    assert!(matches!(&e, SourceError::Limit(m) if m.contains("store")), "{e}");
    assert_eq!(st.source("ds").unwrap().len(), 2);
    // replacing an item by one of the same size fits
    let mut up = st.session().unwrap();
    up.push("ds", "a", "image", &img[..10]).unwrap();
    up.push("", "", "", &img[10..]).unwrap();
    assert_eq!(up.finish().unwrap().sources, 2);
}

/// A file sent twice back to back (same name and kind) is not appended to the first: the name is
/// rejected whole, as anywhere else in the upload; bytes after a complete PNG, JPEG or `.npy`
/// are rejected, never silently dropped.
#[test]
fn a_file_sent_twice_or_with_trailing_bytes_is_rejected() {
    let st = store();
    let mut up = st.session().unwrap();
    let mut jpeg = std::io::Cursor::new(Vec::new());
    image::RgbImage::from_fn(16, 8, |x, y| image::Rgb([(x * 13) as u8, (y * 29) as u8, 40]))
        .write_to(&mut jpeg, image::ImageFormat::Jpeg)
        .unwrap();
    let jpeg = jpeg.into_inner();
    up.push("twice", "a", "image", &png(16, 8, 1)).unwrap();
    up.push("", "a", "image", &jpeg).unwrap(); // back to back: the same file again
    let mut junk_png = png(16, 8, 2);
    junk_png.extend_from_slice(b"junk");
    up.push("", "b", "image", &junk_png).unwrap();
    let mut junk_jpeg = jpeg.clone();
    junk_jpeg.extend_from_slice(&[0u8; 7]);
    up.push("", "c", "image", &junk_jpeg).unwrap();
    up.push("", "d", "image", &png(16, 8, 3)).unwrap();
    let mut junk_npy = npy(8, 16, 2.0);
    junk_npy.push(1);
    up.push("", "d", "depth", &junk_npy).unwrap();
    up.push("", "e", "image", &jpeg).unwrap(); // a clean JPEG is accepted
    let sum = up.finish().unwrap();
    let has = |prefix: &str, needle: &str| sum.rejected.iter().any(|r| r.starts_with(prefix) && r.contains(needle));
    assert!(has("a:", "sent twice"), "{:?}", sum.rejected);
    assert!(has("b:", "4 bytes after the end"), "{:?}", sum.rejected);
    assert!(has("c:", "7 bytes after the end"), "{:?}", sum.rejected);
    assert!(has("d:", "1 bytes after the end"), "{:?}", sum.rejected);
    let src = st.source("twice").unwrap();
    assert_eq!((src.len(), src.id(0)), (1, "e".to_string()), "only the clean file is stored: {:?}", sum.rejected);
}

/// The budgets of uploads in progress: at most `max_concurrent` sessions at once and at most
/// `max_buffer_bytes` held by all of them together; over either the upload fails with a limit
/// (RESOURCE_EXHAUSTED on the wire) and nothing of it is kept; a finished or dropped session
/// gives its slot and bytes back.
#[test]
fn uploads_in_progress_are_bounded_in_number_and_bytes() {
    let limits = UploadLimits { max_concurrent: 2, max_buffer_bytes: 3000, ..UploadLimits::default() };
    let st = UploadStore::new(SourceOptions::default(), limits);
    let a = st.session().unwrap();
    let mut b = st.session().unwrap();
    let e = st.session().unwrap_err();
    assert!(matches!(e, SourceError::Limit(ref m) if m.contains("max_concurrent_uploads")), "{e}");
    assert_eq!(st.in_progress(), (2, 0));
    drop(a);
    let mut c = st.session().unwrap();
    // bytes: b holds 2000, c may add 1000 but not 1001
    b.push("one", "x", "image", &vec![7u8; 2000]).unwrap();
    c.push("two", "y", "image", &vec![7u8; 1000]).unwrap();
    assert_eq!(st.in_progress(), (2, 3000));
    let e = c.push("", "", "", &[1]).unwrap_err();
    assert!(matches!(e, SourceError::Limit(ref m) if m.contains("max_upload_buffer_mb")), "{e}");
    drop(c);
    assert_eq!(st.in_progress(), (1, 2000), "a dropped session gives its bytes back");
    // b's file is not an image: rejected, and finishing gives everything back
    let sum = b.finish().unwrap();
    assert_eq!(sum.sources, 0);
    assert_eq!(st.in_progress(), (0, 0));
    assert!(st.source("two").is_none(), "nothing of the refused upload is kept");
    let mut d = st.session().unwrap();
    d.push("three", "z", "image", &png(16, 8, 1)).unwrap();
    assert_eq!(d.finish().unwrap().sources, 1);
}
