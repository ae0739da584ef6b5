//! Phone-sized photos: a 48-megapixel baseline JPEG (8064 x 6048, made here) is served by the
//! real `mpiflow` binary at the folder's working size with the server's peak resident memory
//! under 1 GiB (it is decoded at reduced scale, never whole), and shows the photo; a photo over
//! the limits even at its reduced scale is left out with a message naming the settings.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use mpiflow::service::client::client_for;
use mpiflow::service::pb;
use mpiflow::source::{open_source, FailureKind, SourceOptions};
use tonic::transport::Endpoint;

const BIN: &str = env!("CARGO_BIN_EXE_mpiflow");

/// 1 GiB, in the kB that /proc/PID/status counts.
const GIB_KB: u64 = 1 << 20;

fn tmp(name: &str) -> PathBuf {
    let d = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("phone-sizes-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A smooth photo-like pattern of `w` x `h`: waves in red and green, a ramp in blue.
fn pattern(w: u32, h: u32) -> image::RgbImage {
    image::RgbImage::from_fn(w, h, |x, y| {
        let (xf, yf) = (x as f32, y as f32);
        let r = 127.0 + 100.0 * (xf / 97.0).sin() * (yf / 131.0).cos();
        let g = 127.0 + 100.0 * ((xf + yf) / 211.0).sin();
        let b = xf * 255.0 / w as f32;
        image::Rgb([r as u8, g as u8, b as u8])
    })
}

fn baseline_jpeg(img: &image::RgbImage) -> Vec<u8> {
    let mut out = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 90).encode_image(img).unwrap();
    out
}

/// [`baseline_jpeg`] with an EXIF segment of orientation 6 after the start marker, as a phone
/// writes a portrait photo: stored sideways, shown turned a quarter clockwise.
fn sideways_jpeg(img: &image::RgbImage) -> Vec<u8> {
    let mut tiff = b"MM\0\x2a\0\0\0\x08".to_vec();
    // one entry: Orientation (0x0112), SHORT, one value, 6; then no next IFD
    for field in [&1u16.to_be_bytes()[..], &0x0112u16.to_be_bytes(), &3u16.to_be_bytes(), &1u32.to_be_bytes()] {
        tiff.extend_from_slice(field);
    }
    tiff.extend_from_slice(&[0, 6, 0, 0, 0, 0, 0, 0]);
    let mut body = b"Exif\0\0".to_vec();
    body.extend(tiff);
    let plain = baseline_jpeg(img);
    let mut out = vec![0xFF, 0xD8, 0xFF, 0xE1];
    out.extend_from_slice(&((body.len() + 2) as u16).to_be_bytes());
    out.extend(body);
    out.extend_from_slice(&plain[2..]);
    out
}

/// The peak resident memory (VmHWM) of process `pid`, in kB.
fn peak_rss_kb(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    let line = status.lines().find(|l| l.starts_with("VmHWM:")).unwrap_or_else(|| panic!("{status}"));
    line.split_whitespace().nth(1).unwrap().parse().unwrap()
}

/// A folder with one 8064 x 6048 baseline JPEG and its depth (a step: the left half nearer) at
/// a quarter of its resolution: the server renders it at the working size 640 x 480 with its peak
/// resident memory under 1 GiB, and the samples show the photo (the source image is the photo
/// brought to 640 x 480 by a plain resize, within a few levels).
#[test]
fn a_48_megapixel_jpeg_serves_at_the_working_size_with_peak_memory_under_1_gib() {
    let photo = pattern(8064, 6048);
    let expected = image::imageops::resize(&photo, 640, 480, image::imageops::FilterType::Triangle);
    serves_at_the_working_size("48mp", baseline_jpeg(&photo), expected);
}

/// The same photo stored sideways with orientation 6, as a phone stores a portrait: served
/// upright at the portrait working size 560 x 744, under 1 GiB.
#[test]
fn a_48_megapixel_portrait_stored_sideways_serves_upright_under_1_gib() {
    let photo = pattern(8064, 6048);
    let upright = image::imageops::rotate90(&photo);
    // the photo covers 560 x 744 at 560 x 747, centred: rows 1 to 744
    let covered = image::imageops::resize(&upright, 560, 747, image::imageops::FilterType::Triangle);
    let expected = image::imageops::crop_imm(&covered, 0, 1, 560, 744).to_image();
    serves_at_the_working_size("48mp-portrait", sideways_jpeg(&photo), expected);
}

/// Serves `jpeg` (an 8064 x 6048 photo, as displayed `expected`'s aspect) with a depth step at a
/// quarter of its displayed resolution; asserts the samples have `expected`'s size and show it,
/// and the server's peak resident memory stays under 1 GiB.
fn serves_at_the_working_size(name: &str, jpeg: Vec<u8>, expected: image::RgbImage) {
    let dir = tmp(name);
    std::fs::create_dir_all(dir.join("images")).unwrap();
    std::fs::create_dir_all(dir.join("depths")).unwrap();
    std::fs::write(dir.join("images/big.jpg"), jpeg).unwrap();
    let (fw, fh) = (expected.width(), expected.height());
    let (dw, dh) = if fw > fh { (2016usize, 1512usize) } else { (1512, 2016) };
    let depth: Vec<f32> = (0..dw * dh).map(|k| if k % dw < dw / 2 { 2.0 } else { 4.0 }).collect();
    mpiflow::io::npy::write_f32(&dir.join("depths/big.npy"), &[dh as u64, dw as u64], &depth).unwrap();

    let log_path = dir.join("serve.log");
    let mut child = Command::new(BIN)
        .args(["serve", "--addr", "127.0.0.1:0", "--log-level", "info", "--workers", "2", "--source"])
        .arg(&dir)
        .stdout(Stdio::piped())
        .stderr(std::fs::File::create(&log_path).unwrap())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    let addr = line.trim().strip_prefix("mpiflow serving on ").unwrap_or_else(|| {
        let _ = child.kill();
        panic!("{line:?}: {}", std::fs::read_to_string(&log_path).unwrap_or_default())
    });
    let samples = tokio::runtime::Runtime::new().unwrap().block_on(async {
        let channel = Endpoint::from_shared(format!("http://{addr}")).unwrap().connect().await.unwrap();
        let spec = pb::SampleSpec { seed: 1, ..Default::default() };
        let request = pb::StreamRequest { count: 3, ..spec.stream() };
        let mut stream = client_for(channel).stream_samples(request).await.unwrap().into_inner();
        let mut out = Vec::new();
        while let Some(b) = stream.message().await.unwrap() {
            out.extend(b.samples);
        }
        out
    });
    let peak = peak_rss_kb(child.id());
    child.kill().unwrap();
    child.wait().unwrap();
    let log = std::fs::read_to_string(&log_path).unwrap();
    let opened = log.lines().find(|l| l.contains("dataset opened")).unwrap_or_else(|| panic!("{log}"));
    assert!(opened.contains(&format!("working size {fw}x{fh}")), "{opened}");

    assert_eq!(samples.len(), 3);
    for s in &samples {
        assert_eq!((s.width, s.height), (fw, fh), "{}", s.source_id);
        let image1 = s.tensors.iter().find(|t| t.name == "image1").unwrap();
        assert_eq!(image1.shape, [fh, fw, 3]);
        assert_eq!(image1.data.len(), expected.as_raw().len(), "uncompressed u8");
        let diff = |a: &[u8], b: &[u8]| {
            a.iter().zip(b).map(|(&x, &y)| f64::from((i32::from(x) - i32::from(y)).unsigned_abs())).sum::<f64>()
                / a.len() as f64
        };
        let mirrored = image::imageops::flip_horizontal(&expected);
        let (same, other) = (diff(&image1.data, expected.as_raw()), diff(&image1.data, mirrored.as_raw()));
        assert!(same < 3.0 && other > 10.0 * same, "mean difference {same} to the photo, {other} to its mirror");
    }
    eprintln!("peak resident memory of the server: {} MiB", peak / 1024);
    assert!(peak < GIB_KB, "peak resident memory {peak} kB");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A photo larger than the limits allow is left out when the folder is opened, by reason
/// `too-large`, with a message naming the size, the limit and the settings: a PNG of 9000 pixels
/// a side (over the 8192 of `max_image_side`), and a baseline JPEG whose header promises 65000 x
/// 65000 (over 40000000 pixels even at 1/8 scale, 8125 x 8125).
#[test]
fn a_photo_over_the_limits_is_left_out_naming_the_size_and_the_settings() {
    let dir = tmp("limits");
    let save = |name: &str, img: &image::RgbImage| img.save(dir.join(name)).unwrap();
    save("good.png", &pattern(64, 48));
    save("wide.png", &pattern(9000, 16));
    let mut bomb = baseline_jpeg(&pattern(16, 16));
    let sof = bomb.windows(2).position(|w| w == [0xFF, 0xC0]).unwrap();
    // SOF0: marker, length (2), precision (1), height (2), width (2)
    bomb[sof + 5..sof + 9].copy_from_slice(&[0xFD, 0xE8, 0xFD, 0xE8]);
    std::fs::write(dir.join("bomb.jpg"), bomb).unwrap();

    let source = open_source(&dir, &SourceOptions::default()).unwrap();
    assert_eq!(source.len(), 1, "{}", source.describe());
    let skipped = source.skipped();
    assert_eq!(skipped.len(), 2, "{skipped:?}");
    for s in &skipped {
        assert_eq!(s.kind, FailureKind::TooLarge, "{s:?}");
        assert!(s.reason.contains("max_photo_pixels") && s.reason.contains("max_image_side"), "{}", s.reason);
    }
    let reason = |item: &str| &skipped.iter().find(|s| s.item == item).unwrap().reason;
    assert!(reason("wide.png").contains("9000 x 16 pixels is too large"), "{}", reason("wide.png"));
    assert!(
        reason("bomb.jpg").contains("65000 x 65000 pixels is too large even decoded at 1/8 scale, 8125 x 8125"),
        "{}",
        reason("bomb.jpg")
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The scale is the smallest of 1/8, 1/4, 1/2 that covers the size on both sides (full size when
/// none does), each side rounded up as the decoder rounds it; only sequential JPEGs of one or
/// three components are scaled.
#[test]
fn the_decoding_scale_is_the_smallest_that_covers_both_sides() {
    use mpiflow::io::scaled::{decode_scale, jpeg_scalable, scaled_side};
    assert_eq!(decode_scale((8064, 6048), (640, 480)), 1, "1008 x 756 covers 640 x 480");
    assert_eq!(decode_scale((4032, 3024), (640, 480)), 2, "504 x 378 does not: 1008 x 756");
    assert_eq!(decode_scale((4032, 3024), (1100, 480)), 4);
    assert_eq!(decode_scale((1280, 960), (640, 480)), 4, "exactly half");
    assert_eq!(decode_scale((1000, 750), (640, 480)), 8, "half is too small: full size");
    assert_eq!(decode_scale((6048, 8064), (480, 640)), 1, "portrait");
    assert_eq!(scaled_side(4033, 2), 1009, "rounded up");
    let jpg = baseline_jpeg(&pattern(32, 24));
    assert!(jpeg_scalable(&jpg));
    let sof = jpg.windows(2).position(|w| w == [0xFF, 0xC0]).unwrap();
    let mut progressive = jpg.clone();
    progressive[sof + 1] = 0xC2;
    assert!(!jpeg_scalable(&progressive), "progressive");
    assert!(!jpeg_scalable(&jpg[..sof]), "cut before its frame header");
    assert!(!jpeg_scalable(b"\x89PNG\r\n\x1a\n"));
}

/// A crop larger than the frame (Cones, 450 x 375, read as it is) names the setting that makes
/// the frame larger: `generate` says to pass `--size`, and `pull` from a server gives the
/// server's refusal without a resume hint (resuming the same request fails again).
#[test]
fn a_crop_larger_than_the_frame_names_size_and_gives_no_resume_hint() {
    let cones = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/rgbd/cones");
    let dir = tmp("crop");
    let o = Command::new(BIN)
        .args(["generate", "--count", "2", "--crop", "496x368", "--objects", "0", "--preview-every", "0", "--out"])
        .arg(dir.join("out"))
        .arg("--source")
        .arg(&cones)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{stderr}");
    assert!(
        stderr.contains(
            "--crop 496x368 is larger than the rendered frame 450x375; pass --size WxH with both sides at \
                         least 496x368"
        ),
        "{stderr}"
    );

    let mut child = Command::new(BIN)
        .args(["serve", "--addr", "127.0.0.1:0", "--log-level", "warn", "--source"])
        .arg(&cones)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    let addr = line.trim().strip_prefix("mpiflow serving on ").unwrap_or_else(|| panic!("{line:?}")).to_string();
    let o = Command::new(BIN).args(["pull", "--addr", &addr, "--count", "2", "--crop", "496x368"]).output().unwrap();
    child.kill().unwrap();
    child.wait().unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{stderr}");
    assert!(stderr.contains("InvalidArgument") && stderr.contains("450x375"), "{stderr}");
    assert!(!stderr.contains("resume"), "{stderr}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A small portrait in a landscape folder is upscaled and loses much of its area to the frame's
/// crop: the source's description (what `serve` logs at start-up) says so, with the factor and
/// the share kept.
#[test]
fn a_small_portrait_in_a_landscape_folder_is_noted_as_upscaled_and_cropped() {
    let dir = tmp("portrait-note");
    pattern(640, 480).save(dir.join("wide.png")).unwrap();
    pattern(300, 400).save(dir.join("small.png")).unwrap();
    let d = open_source(&dir, &SourceOptions::default()).unwrap().describe();
    assert!(d.contains("working size 640x480"), "{d}");
    assert!(d.contains("; 1 smaller than the frame, upscaled (small 2.1x)"), "{d}");
    assert!(d.contains("; 1 of another aspect, cropped to under two thirds of their area (small 56% kept)"), "{d}");
    // a folder of one aspect gets no note
    std::fs::remove_file(dir.join("small.png")).unwrap();
    pattern(1280, 960).save(dir.join("large.png")).unwrap();
    let d = open_source(&dir, &SourceOptions::default()).unwrap().describe();
    assert!(!d.contains("upscaled") && !d.contains("cropped"), "{d}");
    std::fs::remove_dir_all(&dir).unwrap();
}
