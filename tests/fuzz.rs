//! Fuzzing harnesses for every decoder of untrusted bytes: PNG/JPEG photos (with the limit
//! checks), instance-mask and disparity PNGs, `.npy` depth, `.npz` MPIs, PFM, WebDataset tar
//! shards and their members, upload chunk sequences ([`UploadStore`]) and requests (protobuf
//! bytes decoded as the server does, then `service::validate`).
//!
//! # How
//!
//! No coverage-guided fuzzer builds here without downloading a toolchain of its own (`cargo afl`
//! needs AFL++ built from source, `cargo fuzz` a nightly compiler), so these are random-input
//! harnesses: each case is either a stack of 1 to 8 mutations (bit flips, interesting values in
//! length and size fields, inserted, deleted, duplicated and spliced ranges, truncation, decimal
//! numbers written into text headers) of a valid seed (the repo's own photos and shard, and small
//! files written here), or a structured input made to reach the limit checks (headers that
//! promise huge sizes, arrays of any dtype and shape, tars with lying size fields, chunk
//! programs). Case `i` of a target comes from a ChaCha8 stream seeded by the target's name and
//! `i` only, so every failure replays with `MPIFLOW_FUZZ_CASE=i`.
//!
//! # Laws checked on every input
//!
//! - **never panic** (each case runs under `catch_unwind`);
//! - **allocation stays within the stated limits**: this binary's global allocator counts the
//!   bytes held (`peak_alloc`), and the peak during one case, above what was held before it,
//!   must stay under the target's bound, a formula of the limits in force (e.g. for a photo:
//!   the `image` crate's budget of 8 bytes per allowed pixel plus its 64 MiB working memory, and
//!   the f32 result), so a size bomb must be refused by a limit check before it allocates; a
//!   hard cap (`cap`, 1.5 GiB) turns a runaway allocation into an abort instead of swapping;
//! - **errors are typed and printable**: the error's kind is one of the target's kinds, and its
//!   message is non-empty, at most [`MAX_ERROR_CHARS`] characters and free of control characters;
//! - **what decodes is sane**: sizes within the limits, lengths that match them, photo values
//!   finite in [0, 1]; an accepted upload item loads; a validated request obeys its limits.
//!
//! # Budget
//!
//! `cargo test --release --test fuzz` runs a fixed number of cases per target (a few seconds in
//! all, the CI run). `MPIFLOW_FUZZ_CASES=N` runs N per target, `MPIFLOW_FUZZ_SECONDS=S` runs
//! each target for S seconds, `MPIFLOW_FUZZ_CASE=i` only case i; `tools/fuzz.sh --minutes M`
//! wraps the long run. A failing input is written to `CARGO_TARGET_TMPDIR/fuzz-failures/`.
//! Crashes found are regression tests named `regression_*` below.

use std::io::Write;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::sync::{Mutex, PoisonError};
use std::time::{Duration, Instant};

use cap::Cap;
use mpiflow::failure::FailureKind;
use mpiflow::io::image::{load_rgb_from_bytes, ImageError, ImageLimits};
use mpiflow::raster::InstanceMasks;
use mpiflow::service::pb;
use mpiflow::source::given::{depth_npy_from_bytes, disparity_png_from_bytes};
use mpiflow::source::pfm::{encode_pfm, parse_pfm};
use mpiflow::source::shard::index_shard;
use mpiflow::source::upload::{UploadLimits, UploadSession, UploadStore};
use mpiflow::source::{ShardSource, Source, SourceError, SourceOptions};
use peak_alloc::PeakAlloc;
use prost::Message;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

#[global_allocator]
static ALLOC: Cap<PeakAlloc> = Cap::new(PeakAlloc, 1536 << 20);

/// The longest error message accepted (errors name a file, say what is wrong, and echo at most
/// `failure::ECHO_CHARS` characters of input).
const MAX_ERROR_CHARS: usize = 600;

/// Allocation peaks are global: every test of this file runs alone (its first line takes this
/// lock), so that no other test's allocations land in a peak it measures.
static SERIAL: Mutex<()> = Mutex::new(());

fn serial() -> std::sync::MutexGuard<'static, ()> {
    SERIAL.lock().unwrap_or_else(PoisonError::into_inner)
}

const MIB: usize = 1 << 20;

// ---------------------------------------------------------------------------------------------
// the engine

fn env_u64(name: &str) -> Option<u64> {
    std::env::var(name).ok().and_then(|v| v.trim().parse().ok())
}

fn fnv(s: &str) -> u64 {
    s.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| (h ^ u64::from(b)).wrapping_mul(0x100_0000_01b3))
}

fn panic_text(p: &(dyn std::any::Any + Send)) -> String {
    p.downcast_ref::<&str>()
        .map(|s| (*s).to_string())
        .or_else(|| p.downcast_ref::<String>().cloned())
        .unwrap_or_default()
}

fn failure_dir() -> PathBuf {
    Path::new(env!("CARGO_TARGET_TMPDIR")).join("fuzz-failures")
}

/// Runs `cases` inputs of `gen` through `check`, each under `catch_unwind` and the allocation
/// bound; panics with every failure (inputs saved) at the end.
fn fuzz(
    name: &str,
    default_cases: u64,
    gen: impl Fn(&mut ChaCha8Rng) -> Vec<u8>,
    bound: impl Fn(&[u8]) -> usize,
    check: impl Fn(&[u8]) -> Result<(), String>,
) {
    let seconds = env_u64("MPIFLOW_FUZZ_SECONDS");
    let (first, cases) = match env_u64("MPIFLOW_FUZZ_CASE") {
        Some(i) => (i, 1),
        None => (0, env_u64("MPIFLOW_FUZZ_CASES").unwrap_or(if seconds.is_some() { u64::MAX } else { default_cases })),
    };
    let deadline = seconds.map(|s| Instant::now() + Duration::from_secs(s));
    let start = Instant::now();
    let mut failures: Vec<String> = Vec::new();
    let (mut done, mut max_peak, mut bytes) = (0u64, 0usize, 0u64);
    let key = fnv(name);
    for i in first..first.saturating_add(cases) {
        if deadline.is_some_and(|d| Instant::now() >= d) {
            break;
        }
        let mut rng = ChaCha8Rng::seed_from_u64(key ^ i.wrapping_mul(0x9e37_79b9_7f4a_7c15));
        let input = gen(&mut rng);
        let base = PeakAlloc.current_usage();
        PeakAlloc.reset_peak_usage();
        let outcome = catch_unwind(AssertUnwindSafe(|| check(&input)));
        let peak = PeakAlloc.peak_usage().saturating_sub(base);
        max_peak = max_peak.max(peak);
        done += 1;
        bytes += input.len() as u64;
        let limit = bound(&input);
        let problem = match outcome {
            Err(p) => Some(format!("panic: {}", panic_text(p.as_ref()))),
            Ok(Err(m)) => Some(m),
            Ok(Ok(())) if peak > limit => Some(format!("allocated {peak} bytes, over the bound of {limit} bytes")),
            Ok(Ok(())) => None,
        };
        if let Some(p) = problem {
            let dir = failure_dir();
            let file = dir.join(format!("{name}-case-{i}.bin"));
            let _ = std::fs::create_dir_all(&dir).and_then(|()| std::fs::write(&file, &input));
            failures.push(format!("{name} case {i} ({} bytes, saved as {}): {p}", input.len(), file.display()));
            if failures.len() >= 8 {
                break;
            }
        }
    }
    eprintln!(
        "fuzz {name}: {done} inputs ({:.1} MB) in {:.1} s, {} failures, largest allocation peak {:.1} MiB",
        bytes as f64 / 1e6,
        start.elapsed().as_secs_f64(),
        failures.len(),
        max_peak as f64 / MIB as f64
    );
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// An error message as the laws want it: non-empty, short, no control characters.
fn printable_error(what: &str, msg: &str) -> Result<(), String> {
    let n = msg.chars().count();
    let cut: String = msg.chars().take(400).collect();
    if n == 0 {
        Err(format!("{what}: empty error message"))
    } else if n > MAX_ERROR_CHARS {
        Err(format!("{what}: error message of {n} characters (at most {MAX_ERROR_CHARS}): {cut:?}..."))
    } else if msg.chars().any(char::is_control) {
        Err(format!("{what}: error message with control characters: {cut:?}"))
    } else {
        Ok(())
    }
}

// ---------------------------------------------------------------------------------------------
// mutations

const INTERESTING_32: [u32; 10] = [0, 1, 0x7f, 0xff, 0xffff, 0x1_0000, 0x7fff_ffff, 0x8000_0000, 0xffff_ffff, 0xfffe];

/// A random decimal number as text (headers of `.npy` and PFM), sometimes huge or negative.
fn number_text(rng: &mut ChaCha8Rng) -> String {
    match rng.random_range(0..6) {
        0 => rng.random_range(0..16u32).to_string(),
        1 => rng.random_range(0..100_000u32).to_string(),
        2 => u64::MAX.to_string(),
        3 => format!("-{}", rng.random_range(0..1000u32)),
        4 => "1e9".into(),
        _ => rng.random::<u64>().to_string(),
    }
}

/// 1 to 8 random mutations of one of `seeds`, at most `max_len` bytes.
fn mutate(rng: &mut ChaCha8Rng, seeds: &[Vec<u8>], max_len: usize) -> Vec<u8> {
    let mut d = seeds[rng.random_range(0..seeds.len())].clone();
    let ops = 1 + rng.random_range(0..8usize).min(rng.random_range(0..8usize));
    for _ in 0..ops {
        let n = d.len();
        let pos = if n == 0 { 0 } else { rng.random_range(0..n) };
        match rng.random_range(0..11) {
            0 if n > 0 => d[pos] ^= 1 << rng.random_range(0..8),
            1 if n > 0 => d[pos] = rng.random(),
            2 if n > 0 => d[pos] = [0u8, 1, 0x7f, 0x80, 0xff][rng.random_range(0..5)],
            3 if n >= 4 => {
                let v = INTERESTING_32[rng.random_range(0..INTERESTING_32.len())];
                let b = if rng.random() { v.to_be_bytes() } else { v.to_le_bytes() };
                let at = pos.min(n - 4);
                d[at..at + 4].copy_from_slice(&b);
            }
            4 if n > 0 => {
                let len = rng.random_range(1..=64usize).min(n - pos);
                d.drain(pos..pos + len);
            }
            5 => {
                let len = rng.random_range(1..=64usize);
                let ins: Vec<u8> = (0..len).map(|_| rng.random()).collect();
                d.splice(pos..pos, ins);
            }
            6 if n > 0 => {
                let len = rng.random_range(1..=256usize).min(n - pos);
                let chunk = d[pos..pos + len].to_vec();
                let at = rng.random_range(0..=n);
                d.splice(at..at, chunk);
            }
            7 if n > 0 => d.truncate(pos),
            8 => {
                let other = &seeds[rng.random_range(0..seeds.len())];
                let from = if other.is_empty() { 0 } else { rng.random_range(0..other.len()) };
                d.truncate(pos);
                d.extend_from_slice(&other[from..]);
            }
            9 => {
                let t = number_text(rng).into_bytes();
                let end = (pos + t.len()).min(n);
                d.splice(pos..end, t);
            }
            _ if n > 0 => {
                let len = rng.random_range(1..=16usize).min(n - pos);
                let v: u8 = rng.random();
                d[pos..pos + len].fill(v);
            }
            _ => {}
        }
    }
    d.truncate(max_len);
    d
}

// ---------------------------------------------------------------------------------------------
// seeds

fn repo(p: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(p)
}

fn encode(img: image::DynamicImage, format: image::ImageFormat) -> Vec<u8> {
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, format).expect("encode a seed image");
    out.into_inner()
}

fn png_rgb(w: u32, h: u32) -> Vec<u8> {
    let img = image::RgbImage::from_fn(w, h, |x, y| image::Rgb([(x * 9) as u8, (y * 11) as u8, ((x * y) % 251) as u8]));
    encode(img.into(), image::ImageFormat::Png)
}

fn jpeg_rgb(w: u32, h: u32) -> Vec<u8> {
    let img = image::RgbImage::from_fn(w, h, |x, y| image::Rgb([(x * 7) as u8, (y * 13) as u8, ((x ^ y) * 5) as u8]));
    encode(img.into(), image::ImageFormat::Jpeg)
}

fn png_gray8(w: u32, h: u32, ids: u32) -> Vec<u8> {
    let img = image::GrayImage::from_fn(w, h, |x, y| image::Luma([((x / 4 + y / 4) % (ids + 1)) as u8]));
    encode(img.into(), image::ImageFormat::Png)
}

/// A 16-bit grey PNG whose first `ids` pixels hold ids 1..=ids (the rest 0).
fn png_gray16_ids(w: u32, h: u32, ids: u32) -> Vec<u8> {
    let img = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_fn(w, h, |x, y| {
        let i = y * w + x;
        image::Luma([if i < ids { (i + 1) as u16 } else { 0 }])
    });
    encode(image::DynamicImage::ImageLuma16(img), image::ImageFormat::Png)
}

fn image_seeds() -> Vec<Vec<u8>> {
    let rgba = image::RgbaImage::from_fn(12, 9, |x, y| image::Rgba([x as u8 * 20, y as u8 * 20, 7, (x * y) as u8]));
    let la = image::GrayAlphaImage::from_fn(10, 6, |x, y| image::LumaA([x as u8 * 25, if y > 2 { 255 } else { 0 }]));
    let gray_jpeg = encode(
        image::DynamicImage::ImageLuma8(image::GrayImage::from_fn(24, 16, |x, _| image::Luma([x as u8 * 10]))),
        image::ImageFormat::Jpeg,
    );
    vec![
        png_rgb(24, 16),
        png_gray8(20, 12, 3),
        png_gray16_ids(16, 8, 40),
        encode(rgba.into(), image::ImageFormat::Png),
        encode(la.into(), image::ImageFormat::Png),
        jpeg_rgb(33, 17),
        gray_jpeg,
        std::fs::read(repo("examples/photos/rocket.jpg")).expect("the bundled photo"),
        bomb_png(8000, 8000),
        bomb_png(600, 400),
    ]
}

fn crc32(bytes: &[u8]) -> u32 {
    let mut c = 0xffff_ffffu32;
    for &b in bytes {
        c ^= u32::from(b);
        for _ in 0..8 {
            c = if c & 1 != 0 { (c >> 1) ^ 0xedb8_8320 } else { c >> 1 };
        }
    }
    !c
}

/// A PNG header (signature and IHDR with a valid CRC) promising `w x h` RGB pixels, an empty
/// IDAT and IEND: a decompression-bomb header with no data behind it.
fn bomb_png(w: u32, h: u32) -> Vec<u8> {
    let mut out = vec![0x89, b'P', b'N', b'G', 0x0d, 0x0a, 0x1a, 0x0a];
    let mut chunk = |kind: &[u8], data: &[u8]| {
        out.extend_from_slice(&(data.len() as u32).to_be_bytes());
        let mut body = kind.to_vec();
        body.extend_from_slice(data);
        out.extend_from_slice(&body);
        out.extend_from_slice(&crc32(&body).to_be_bytes());
    };
    let mut ihdr = Vec::new();
    ihdr.extend_from_slice(&w.to_be_bytes());
    ihdr.extend_from_slice(&h.to_be_bytes());
    ihdr.extend_from_slice(&[8, 2, 0, 0, 0]);
    chunk(b"IHDR", &ihdr);
    chunk(b"IDAT", &[0x78, 0x9c, 0x03, 0x00, 0x00, 0x00, 0x00, 0x01]);
    chunk(b"IEND", &[]);
    out
}

/// A PNG or JPEG seed with its header's dimensions replaced (and the PNG's IHDR CRC fixed).
fn with_dimensions(rng: &mut ChaCha8Rng, seed: &[u8]) -> Vec<u8> {
    let pick = |rng: &mut ChaCha8Rng| -> u32 {
        match rng.random_range(0..5) {
            0 => rng.random_range(0..4),
            1 => rng.random_range(1..2048),
            2 => rng.random_range(8000..70_000),
            3 => INTERESTING_32[rng.random_range(0..INTERESTING_32.len())],
            _ => rng.random(),
        }
    };
    let mut d = seed.to_vec();
    if d.starts_with(&[0x89, b'P', b'N', b'G']) && d.len() >= 33 {
        let (w, h) = (pick(rng), pick(rng));
        d[16..20].copy_from_slice(&w.to_be_bytes());
        d[20..24].copy_from_slice(&h.to_be_bytes());
        let crc = crc32(&d[12..29]);
        d[29..33].copy_from_slice(&crc.to_be_bytes());
    } else if let Some(p) = d.windows(2).position(|m| m[0] == 0xff && (0xc0..=0xc2).contains(&m[1])) {
        if p + 9 <= d.len() {
            let (w, h) = (pick(rng) as u16, pick(rng) as u16);
            d[p + 5..p + 7].copy_from_slice(&h.to_be_bytes());
            d[p + 7..p + 9].copy_from_slice(&w.to_be_bytes());
        }
    }
    d
}

fn npy_f32(shape: &[u64]) -> Vec<u8> {
    let n: u64 = shape.iter().product();
    let data: Vec<f32> = (0..n).map(|i| 0.5 + (i % 17) as f32).collect();
    let mut out = Vec::new();
    mpiflow::io::npy::write_f32_to(&mut out, shape, &data).expect("write a seed npy");
    out
}

/// A version-1 `.npy` with any header text and data (no checks: made to be wrong).
fn npy_raw(descr: &str, fortran: bool, shape: &str, data: &[u8]) -> Vec<u8> {
    let mut header = format!(
        "{{'descr': '{descr}', 'fortran_order': {}, 'shape': {shape}, }}",
        if fortran { "True" } else { "False" }
    );
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    out.extend_from_slice(data);
    out
}

const DESCRS: [&str; 16] =
    ["<f4", ">f4", "<f8", "|u1", "<u2", "<u4", "|i1", "<i2", "<i4", "<i8", "|b1", "<c8", "<U4", "|O", "<f2", "x"];

fn item_size(descr: &str) -> usize {
    descr.chars().filter(char::is_ascii_digit).collect::<String>().parse().unwrap_or(1)
}

/// A random `.npy`: dtype, order, a shape of 0 to 5 dimensions (small, at the limits or huge),
/// and data that fits it, falls short or runs over, up to `max_bytes`.
fn random_npy(rng: &mut ChaCha8Rng, max_bytes: usize) -> Vec<u8> {
    let descr = DESCRS[rng.random_range(0..DESCRS.len())];
    let rank = rng.random_range(0..=5usize);
    let dims: Vec<u64> = (0..rank)
        .map(|_| match rng.random_range(0..6) {
            0 => 1,
            1 => rng.random_range(0..32),
            2 => rng.random_range(100..1200),
            3 => rng.random_range(1 << 16..1 << 20),
            4 => u64::from(INTERESTING_32[rng.random_range(0..INTERESTING_32.len())]),
            _ => rng.random_range(1..8),
        })
        .collect();
    let shape = match dims.len() {
        0 => "()".to_string(),
        1 => format!("({},)", dims[0]),
        _ => format!("({})", dims.iter().map(u64::to_string).collect::<Vec<_>>().join(", ")),
    };
    let count = dims.iter().try_fold(1u64, |a, &d| a.checked_mul(d)).unwrap_or(u64::MAX);
    let exact = count.saturating_mul(item_size(descr) as u64);
    let len = match rng.random_range(0..4) {
        0 => exact,
        1 => exact.saturating_sub(rng.random_range(1..64)),
        2 => exact.saturating_add(rng.random_range(1..64)),
        _ => rng.random_range(0..max_bytes as u64),
    }
    .min(max_bytes as u64) as usize;
    let fill: u8 = if rng.random() { 0 } else { rng.random() };
    let mut data = vec![fill; len];
    if rng.random_bool(0.3) {
        data.iter_mut().for_each(|b| *b = rng.random());
    }
    npy_raw(descr, rng.random_bool(0.2), &shape, &data)
}

// ---------------------------------------------------------------------------------------------
// photos, masks and disparity PNGs

/// The limits of the image targets: small enough that a bomb stands out, large enough for the
/// bundled photo.
const PHOTO_LIMITS: ImageLimits =
    ImageLimits { max_width: 1024, max_height: 1024, max_pixels: 1 << 19, max_bytes: 1 << 20 };
const MASK_LIMITS: ImageLimits =
    ImageLimits { max_width: 512, max_height: 512, max_pixels: 1 << 16, max_bytes: 1 << 20 };

/// The `image` crate's stated budget at these limits (`ImageLimits::to_image_limits`: 8 bytes
/// per allowed pixel plus 64 MiB of decoder working memory).
fn image_budget(l: &ImageLimits) -> usize {
    8 * l.max_pixels as usize + 64 * MIB
}

fn check_image_error(what: &str, e: &ImageError) -> Result<(), String> {
    if !matches!(e.failure_kind(), FailureKind::Decode | FailureKind::Truncated | FailureKind::TooLarge) {
        return Err(format!("{what}: unexpected kind {:?}", e.failure_kind()));
    }
    printable_error(what, &e.to_string())
}

#[test]
fn fuzz_png_jpeg_photos() {
    let _serial = serial();
    let seeds = image_seeds();
    let l = PHOTO_LIMITS;
    fuzz(
        "png_jpeg",
        500,
        |rng| {
            if rng.random_bool(0.25) {
                let s = &seeds[rng.random_range(0..seeds.len())];
                with_dimensions(rng, s)
            } else {
                mutate(rng, &seeds, l.max_bytes as usize + 64)
            }
        },
        // decoded image + its f32 RGB copy (12 bytes per pixel) + the input
        |input| image_budget(&l) + 12 * l.max_pixels as usize + 2 * input.len(),
        |input| match load_rgb_from_bytes(input, &l) {
            Ok(img) => {
                let (w, h) = (img.width, img.height);
                if !l.check_dimensions(w as u32, h as u32) || img.data.len() != w * h * 3 || w == 0 || h == 0 {
                    return Err(format!("decoded {w} x {h} with {} values under {l}", img.data.len()));
                }
                match img.data.iter().find(|v| !(0.0..=1.0).contains(*v)) {
                    Some(v) => Err(format!("decoded value {v} outside [0, 1]")),
                    None => Ok(()),
                }
            }
            Err(e) => check_image_error("photo", &e),
        },
    );
}

#[test]
fn fuzz_mask_and_disparity_pngs() {
    let _serial = serial();
    let mut seeds = image_seeds();
    seeds.extend([png_gray16_ids(64, 64, 900), png_gray8(64, 32, 200)]);
    let l = MASK_LIMITS;
    let p = l.max_pixels as usize;
    fuzz(
        "mask_disparity_png",
        400,
        |rng| match rng.random_range(0..8) {
            // an index map of many instances (up to over MAX_INSTANCES)
            0 => {
                let (w, h) = (rng.random_range(1..=256u32), rng.random_range(1..=256u32));
                png_gray16_ids(w, h, rng.random_range(0..1100))
            }
            1 => {
                let s = &seeds[rng.random_range(0..seeds.len())];
                with_dimensions(rng, s)
            }
            _ => mutate(rng, &seeds, l.max_bytes as usize + 64),
        },
        // decoded image, the id map (4 B/px), instance masks up to the stated mask budget
        // (`raster::MAX_MASK_FRAMES` frames of f32 at the pixel limit), disparity (4 B/px)
        |input| image_budget(&l) + (8 + 4 * mpiflow::raster::MAX_MASK_FRAMES) * p + 2 * input.len(),
        |input| {
            match InstanceMasks::from_index_png_bytes(input, "fuzz.mask.png", &l) {
                Ok(m) => {
                    if !l.check_dimensions(m.width as u32, m.height as u32)
                        || m.masks.iter().any(|i| i.mask.len() != m.width * m.height)
                    {
                        return Err(format!("masks of {} x {} do not fit the limits or their size", m.width, m.height));
                    }
                }
                Err(e) => printable_error("mask", &e.to_string())?,
            }
            match disparity_png_from_bytes(input, "fuzz.disp.png", &l) {
                Ok((w, h, d)) => {
                    if d.len() != w * h || d.iter().any(|v| !(0.0..=1.0).contains(v)) {
                        return Err(format!("disparity of {w} x {h} with {} values outside [0, 1]", d.len()));
                    }
                    Ok(())
                }
                Err(e) => {
                    let kind = e.failure_kind();
                    if !matches!(kind, Some(FailureKind::Depth | FailureKind::Truncated | FailureKind::TooLarge)) {
                        return Err(format!("disparity: unexpected kind {kind:?}"));
                    }
                    printable_error("disparity", &e.to_string())
                }
            }
        },
    );
}

// ---------------------------------------------------------------------------------------------
// .npy depth, .npz MPIs, PFM

const DEPTH_LIMITS: ImageLimits =
    ImageLimits { max_width: 1024, max_height: 1024, max_pixels: 1 << 16, max_bytes: 1 << 20 };

fn npy_seeds() -> Vec<Vec<u8>> {
    vec![
        npy_f32(&[8, 12]),
        npy_f32(&[1, 8, 12]),
        npy_f32(&[8, 12, 1]),
        npy_f32(&[1, 1, 8, 12]),
        npy_raw("|u1", false, "(4, 6)", &[7; 24]),
        npy_raw(">f4", false, "(2, 3)", &[0x3f, 0x80, 0, 0].repeat(6)),
        npy_raw("<f8", false, "(3, 2)", &1.5f64.to_le_bytes().repeat(6)),
        npy_raw("<i2", true, "(3, 2)", &[1, 0].repeat(6)),
    ]
}

#[test]
fn fuzz_npy_depth() {
    let _serial = serial();
    let seeds = npy_seeds();
    let l = DEPTH_LIMITS;
    let p = l.max_pixels as usize;
    fuzz(
        "npy_depth",
        800,
        |rng| if rng.random_bool(0.4) { random_npy(rng, l.max_bytes as usize) } else { mutate(rng, &seeds, 1 << 16) },
        // the f64 array while it grows (up to 3 x 8 B per allowed pixel) and the f32 depth
        |input| 32 * p + 2 * input.len() + 64 * 1024,
        |input| match depth_npy_from_bytes(input, &l) {
            Ok((w, h, d)) => {
                if w == 0 || h == 0 || !l.check_dimensions(w as u32, h as u32) || d.len() != w * h {
                    return Err(format!("depth of {w} x {h} with {} values under {l}", d.len()));
                }
                Ok(())
            }
            Err((kind, m)) => {
                if !matches!(kind, FailureKind::Depth | FailureKind::TooLarge) {
                    return Err(format!("depth: unexpected kind {kind:?}"));
                }
                printable_error("depth", &m)
            }
        },
    );
}

/// An `.npz` of the given members (raw bytes, written deflated as NumPy does).
fn npz(members: &[(&str, Vec<u8>)]) -> Vec<u8> {
    let mut w = npyz::npz::NpzWriter::new(std::io::Cursor::new(Vec::new()));
    for (name, bytes) in members {
        let z = w.zip_writer();
        z.start_file(format!("{name}.npy"), Default::default()).expect("zip member");
        z.write_all(bytes).expect("zip data");
    }
    w.zip_writer().finish().expect("zip end").into_inner()
}

fn mpi_members(n: u64, h: u64, w: u64) -> Vec<(&'static str, Vec<u8>)> {
    vec![
        ("mpi_rgb", npy_f32(&[1, n, 3, h, w])),
        ("mpi_sigma", npy_f32(&[1, n, 1, h, w])),
        ("disparity", npy_raw("<f4", false, &format!("(1, {n})"), &0.5f32.to_le_bytes().repeat(n as usize))),
        (
            "K",
            npy_raw(
                "<f8",
                false,
                "(1, 3, 3)",
                &[4.0f64, 0.0, 2.0, 0.0, 4.0, 1.5, 0.0, 0.0, 1.0]
                    .iter()
                    .flat_map(|v| v.to_le_bytes())
                    .collect::<Vec<_>>(),
            ),
        ),
        ("mask_in", npy_f32(&[1, 1, h, w])),
    ]
}

/// Largest `.npz` MPI the fuzz run accepts (bytes of f32 values decoded).
const NPZ_MAX_VALUES: u64 = 1 << 20;

#[test]
fn fuzz_npz_mpi() {
    let _serial = serial();
    let seeds = vec![npz(&mpi_members(2, 3, 4)), npz(&mpi_members(3, 5, 2))];
    let dir = failure_dir().join("npz-work");
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("fuzz.npz");
    fuzz(
        "npz_mpi",
        300,
        |rng| match rng.random_range(0..3) {
            0 => {
                let keys = ["mpi_rgb", "mpi_sigma", "disparity", "K", "G", "mask_in", "junk"];
                let mut members: Vec<(&str, Vec<u8>)> = Vec::new();
                for k in keys {
                    if rng.random_bool(0.7) {
                        members.push((k, random_npy(rng, 1 << 16)));
                    }
                }
                npz(&members)
            }
            1 => {
                let mut m = mpi_members(rng.random_range(1..4), rng.random_range(1..6), rng.random_range(1..6));
                let i = rng.random_range(0..m.len());
                m[i].1 = random_npy(rng, 1 << 16);
                npz(&m)
            }
            _ => mutate(rng, &seeds, 1 << 18),
        },
        // the arrays as f64 while they grow (3 x 8 B per value) and the MPI's f32 planes
        |input| 40 * NPZ_MAX_VALUES as usize + 4 * input.len() + 4 * MIB,
        |input| {
            std::fs::write(&path, input).map_err(|e| format!("write the case: {e}"))?;
            match mpiflow::mpi::npz::load_npz_limited(&path, NPZ_MAX_VALUES) {
                Ok(mpi) => {
                    let planes = mpi.planes();
                    if planes == 0 || mpi.width == 0 || mpi.height == 0 {
                        return Err(format!("an MPI of {planes} planes of {} x {}", mpi.width, mpi.height));
                    }
                    Ok(())
                }
                Err(e) => printable_error("npz", &e.to_string()),
            }
        },
    );
}

#[test]
fn fuzz_pfm() {
    let _serial = serial();
    let seeds = vec![
        encode_pfm(5, 3, 1, &[1.5; 15], true),
        encode_pfm(2, 2, 3, &[0.25; 12], false),
        b"PF 1 1 2.5\n\0\0\0\0\0\0\0\0\0\0\0\0".to_vec(),
        b"Pf\n100000 100000\n-1\n".to_vec(),
    ];
    let l = DEPTH_LIMITS;
    fuzz(
        "pfm",
        2000,
        |rng| {
            if rng.random_bool(0.4) {
                let magic = ["Pf", "PF", "P6", "pf", "", "PFF"][rng.random_range(0..6)];
                let scale = ["-1", "1", "0", "-0.0", "nan", "inf", "-1e40", "2.5"][rng.random_range(0..8)];
                let sep = [" ", "\n", "\t", "\r\n", "  \n "][rng.random_range(0..5)];
                let (w, h) = (number_text(rng), number_text(rng));
                let mut d = format!("{magic}{sep}{w}{sep}{h}{sep}{scale}").into_bytes();
                d.push(b'\n');
                let len = rng.random_range(0..4096);
                d.extend((0..len).map(|_| rng.random::<u8>()));
                d
            } else {
                mutate(rng, &seeds, 1 << 16)
            }
        },
        |input| 12 * l.max_pixels as usize + 2 * input.len() + 64 * 1024,
        |input| match parse_pfm(input, &l) {
            Ok(p) => {
                let ok = (p.channels == 1 || p.channels == 3)
                    && l.check_dimensions(p.width as u32, p.height as u32)
                    && p.data.len() == p.width * p.height * p.channels
                    && p.scale.is_finite()
                    && p.scale > 0.0;
                if ok {
                    Ok(())
                } else {
                    Err(format!("PFM {} x {} x {} with {} values", p.width, p.height, p.channels, p.data.len()))
                }
            }
            Err(e) => {
                if !matches!(e.kind, FailureKind::Decode | FailureKind::Truncated | FailureKind::TooLarge) {
                    return Err(format!("pfm: unexpected kind {:?}", e.kind));
                }
                printable_error("pfm", &e.message)
            }
        },
    );
}

// ---------------------------------------------------------------------------------------------
// WebDataset shards and their members

fn tar_of(members: &[(String, Vec<u8>)]) -> Vec<u8> {
    let mut b = tar::Builder::new(Vec::new());
    for (name, data) in members {
        let mut h = tar::Header::new_gnu();
        h.set_size(data.len() as u64);
        h.set_mode(0o644);
        h.set_cksum();
        b.append_data(&mut h, name, data.as_slice()).expect("tar member");
    }
    b.into_inner().expect("tar end")
}

fn member_payloads() -> Vec<(&'static str, Vec<u8>)> {
    vec![
        ("jpg", jpeg_rgb(16, 8)),
        ("png", png_rgb(16, 8)),
        ("depth.npy", npy_f32(&[8, 16])),
        ("depth.png", png_gray8(16, 8, 200)),
        ("disp.png", png_gray8(16, 8, 100)),
        ("mask.png", png_gray8(16, 8, 3)),
        ("json", br#"{"fx": 9.0, "fy": 9.0, "cx": 8.0, "cy": 4.0}"#.to_vec()),
        ("json", br#"{"fx": -1, "fy": "x", "cx": 1e999}"#.to_vec()),
        ("txt", b"caption".to_vec()),
    ]
}

fn shard_options() -> SourceOptions {
    SourceOptions { limits: MASK_LIMITS, ..SourceOptions::default() }
}

#[test]
fn fuzz_webdataset_shards() {
    let _serial = serial();
    let payloads = member_payloads();
    let keyed = |keys: &[&str]| -> Vec<(String, Vec<u8>)> {
        keys.iter().flat_map(|k| payloads.iter().take(7).map(move |(f, d)| (format!("{k}.{f}"), d.clone()))).collect()
    };
    let seeds = vec![
        std::fs::read(repo("tests/data/webdataset/webdataset-flow-000000.tar")).expect("the test shard"),
        tar_of(&keyed(&["a", "dir/b"])),
        tar_of(&keyed(&["c"])),
    ];
    let dir = failure_dir().join("shard-work");
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("fuzz.tar");
    let options = shard_options();
    let l = options.limits;
    fuzz(
        "webdataset_shard",
        300,
        |rng| {
            if rng.random_bool(0.4) {
                let keys = ["a", "b", "x/c", ".d", "e.f", "", "a"];
                let n = rng.random_range(0..10);
                let members: Vec<(String, Vec<u8>)> = (0..n)
                    .map(|_| {
                        let key = keys[rng.random_range(0..keys.len())];
                        let (field, data) = &payloads[rng.random_range(0..payloads.len())];
                        let data = if rng.random_bool(0.3) {
                            mutate(rng, std::slice::from_ref(data), 1 << 16)
                        } else {
                            data.clone()
                        };
                        (format!("{key}.{field}"), data)
                    })
                    .collect();
                let mut t = tar_of(&members);
                if rng.random_bool(0.3) && !t.is_empty() {
                    let cut = rng.random_range(0..t.len());
                    t.truncate(cut);
                }
                t
            } else {
                mutate(rng, &seeds, 1 << 18)
            }
        },
        // per item: the photo, depth and mask decoders' bounds, every member's bytes
        |input| {
            image_budget(&l)
                + (40 + 4 * mpiflow::raster::MAX_MASK_FRAMES) * l.max_pixels as usize
                + 6 * input.len()
                + 4 * MIB
        },
        |input| {
            std::fs::write(&path, input).map_err(|e| format!("write the case: {e}"))?;
            if let Err(e) = index_shard(&path) {
                printable_error("index", &e.to_string())?;
            }
            let src = match ShardSource::open(&path, &options) {
                Ok(s) => s,
                Err(e) => return printable_error("open", &e.to_string()),
            };
            for s in src.skipped() {
                printable_error("skip reason", &s.reason)?;
            }
            for i in 0..src.len().min(16) {
                match src.load(i) {
                    Ok(item) => {
                        let (w, h) = (item.image.width, item.image.height);
                        if !l.check_dimensions(w as u32, h as u32) {
                            return Err(format!("item {i} of {w} x {h} over {l}"));
                        }
                    }
                    Err(e) => printable_error("load", &e.to_string())?,
                }
            }
            Ok(())
        },
    );
}

// ---------------------------------------------------------------------------------------------
// upload chunk sequences

const UPLOAD_LIMITS: UploadLimits = UploadLimits {
    max_upload_bytes: 256 << 10,
    max_total_bytes: 512 << 10,
    max_datasets: 3,
    max_items: 6,
    max_concurrent: 2,
    max_buffer_bytes: 384 << 10,
};

fn upload_options() -> SourceOptions {
    SourceOptions {
        limits: ImageLimits { max_width: 256, max_height: 256, max_pixels: 1 << 14, max_bytes: 96 << 10 },
        ..SourceOptions::default()
    }
}

/// The payloads an upload program picks from.
fn upload_payloads() -> Vec<Vec<u8>> {
    let nan = npy_raw("<f4", false, "(8, 16)", &f32::NAN.to_le_bytes().repeat(128));
    let mut junk_after = png_rgb(16, 8);
    junk_after.extend_from_slice(b"junk");
    vec![
        png_rgb(16, 8),
        png_rgb(24, 12),
        jpeg_rgb(16, 8),
        npy_f32(&[8, 16]),
        npy_f32(&[3, 5]),
        nan,
        png_gray8(16, 8, 4),
        png_gray16_ids(16, 8, 30),
        bomb_png(8000, 8000),
        junk_after,
        Vec::new(),
        vec![0xab; 100 << 10],
    ]
}

const DATASETS: [&str; 6] = ["photos", "b", "", "../x", "a\u{1b}[2Jb", "ddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddddd"];
const NAMES: [&str; 9] = ["a", "b", "c", "a.b", "", ".h", "x/y", "n\u{0}\u{7}", "long-name-long-name-long-name-long-name-long-name-long-name-long-name-long-name-long-name-long-name-long-name-long-name-long-name"];
const KINDS: [&str; 6] = ["image", "depth", "mask", "", "jpg", "IMAGE"];

/// Interprets fuzz bytes as an upload program over one store: open (at most two sessions at
/// once), push chunks (dataset, name, kind from the tables above, data a slice of a payload,
/// sometimes mutated), finish, drop; then checks the store's laws. The outcome as text, for the
/// determinism check.
fn run_upload_program(program: &[u8], payloads: &[Vec<u8>]) -> Result<String, String> {
    let store = UploadStore::new(upload_options(), UPLOAD_LIMITS);
    let mut sessions: Vec<Option<UploadSession>> = vec![None, None];
    let mut log = String::new();
    let mut bytes = program.iter().copied();
    let mut next = move || bytes.next();
    let check_source_error = |what: &str, e: &SourceError| -> Result<(), String> {
        if !matches!(e, SourceError::Limit(_) | SourceError::Upload { .. }) {
            return Err(format!("{what}: unexpected error kind {e:?}"));
        }
        printable_error(what, &e.to_string())
    };
    while let Some(op) = next() {
        let s = usize::from(op >> 7);
        match op % 6 {
            0 | 1 => {
                if sessions[s].is_none() {
                    match store.session() {
                        Ok(x) => sessions[s] = Some(x),
                        Err(e) => {
                            check_source_error("session", &e)?;
                            log.push_str("busy;");
                            continue;
                        }
                    }
                }
                let (d, n, k, p) = (next().unwrap_or(0), next().unwrap_or(0), next().unwrap_or(0), next().unwrap_or(0));
                let (from, len) = (next().unwrap_or(0), next().unwrap_or(255));
                let payload = &payloads[usize::from(p) % payloads.len()];
                let a = (payload.len() * usize::from(from) / 256).min(payload.len());
                let b = if len == 255 {
                    payload.len()
                } else {
                    (a + payload.len() * usize::from(len) / 128).min(payload.len())
                };
                let mut data = payload[a..b].to_vec();
                if p >= 128 && !data.is_empty() {
                    let at = usize::from(n) * data.len() / 256;
                    data[at] ^= 0x5a;
                }
                let name = if op % 6 == 1 { "" } else { NAMES[usize::from(n) % NAMES.len()] };
                let kind = if op % 6 == 1 { "" } else { KINDS[usize::from(k) % KINDS.len()] };
                let dataset = DATASETS[usize::from(d) % DATASETS.len()];
                let up = sessions[s].as_mut().expect("opened above");
                if let Err(e) = up.push(dataset, name, kind, &data) {
                    check_source_error("push", &e)?;
                    sessions[s] = None; // the server ends the upload on an error
                    log.push_str("push-err;");
                }
            }
            2 | 3 => {
                if let Some(up) = sessions[s].take() {
                    match up.finish() {
                        Ok(sum) => {
                            for r in &sum.rejected {
                                printable_error("rejected", r)?;
                            }
                            let snap = store.source(&sum.dataset);
                            let n = snap.as_ref().map_or(0, |x| x.len() as u64);
                            if n != sum.sources
                                || (n > 0 && snap.as_ref().map(|x| x.fingerprint()) != Some(sum.fingerprint))
                            {
                                return Err(format!("summary {sum:?} does not match the stored dataset ({n} items)"));
                            }
                            log.push_str(&format!(
                                "ok {} {} {} {:x};",
                                sum.accepted,
                                sum.rejected.len(),
                                sum.sources,
                                sum.fingerprint
                            ));
                        }
                        Err(e) => {
                            check_source_error("finish", &e)?;
                            log.push_str("finish-err;");
                        }
                    }
                }
            }
            4 => sessions[s] = None,
            _ => {
                let dataset = DATASETS[usize::from(next().unwrap_or(0)) % DATASETS.len()];
                if store.remove(dataset) {
                    log.push_str("removed;");
                }
            }
        }
    }
    drop(sessions);
    if store.in_progress() != (0, 0) {
        return Err(format!("uploads in progress after every session ended: {:?}", store.in_progress()));
    }
    let infos = store.datasets();
    if store.total_bytes() > UPLOAD_LIMITS.max_total_bytes || infos.len() > UPLOAD_LIMITS.max_datasets {
        return Err(format!(
            "the store holds {} bytes in {} datasets, over its limits",
            store.total_bytes(),
            infos.len()
        ));
    }
    for info in infos {
        let src = store.source(&info.name).ok_or("a listed dataset without a snapshot")?;
        if src.len() > UPLOAD_LIMITS.max_items || src.is_empty() {
            return Err(format!("dataset {} holds {} items", info.name, src.len()));
        }
        // what was accepted loads: never accepted and failed later
        for i in 0..src.len() {
            src.load(i).map_err(|e| format!("accepted item {} of {} does not load: {e}", src.id(i), info.name))?;
        }
        log.push_str(&format!("{}={:x};", info.name, info.fingerprint));
    }
    Ok(log)
}

fn upload_seed_programs() -> Vec<Vec<u8>> {
    vec![
        // image a, depth a, finish
        vec![0, 0, 0, 0, 0, 0, 255, 0, 0, 0, 1, 3, 0, 255, 2],
        // image b in two chunks, mask b, finish; then a second session replacing b
        vec![0, 1, 1, 0, 1, 0, 100, 1, 0, 0, 0, 1, 128, 255, 0, 0, 1, 2, 6, 0, 255, 2, 0, 0, 1, 0, 2, 0, 255, 3],
        // two sessions at once, one dropped
        vec![0, 0, 0, 0, 0, 0, 255, 128, 1, 2, 0, 1, 0, 255, 4, 130, 0],
        // the same name twice, a bomb, junk after a PNG, NaN depth
        vec![
            0, 0, 0, 0, 0, 0, 255, 0, 0, 0, 0, 2, 0, 255, 0, 0, 1, 0, 8, 0, 255, 0, 0, 2, 0, 9, 0, 255, 0, 0, 2, 1, 5,
            0, 255, 2,
        ],
    ]
}

#[test]
fn fuzz_upload_chunk_sequences() {
    let _serial = serial();
    let payloads = upload_payloads();
    let seeds = upload_seed_programs();
    let l = upload_options().limits;
    fuzz(
        "upload_chunks",
        400,
        |rng| {
            if rng.random_bool(0.3) {
                (0..rng.random_range(1..160)).map(|_| rng.random()).collect()
            } else {
                mutate(rng, &seeds, 512)
            }
        },
        // every byte the store may hold or buffer, plus one decode at a time at its limits
        |_| {
            (UPLOAD_LIMITS.max_total_bytes + UPLOAD_LIMITS.max_buffer_bytes) as usize * 3
                + image_budget(&l)
                + 64 * l.max_pixels as usize
        },
        |program| {
            let first = run_upload_program(program, &payloads)?;
            // the same chunks give the same datasets and fingerprints
            let again = run_upload_program(program, &payloads)?;
            if first == again {
                Ok(())
            } else {
                Err(format!("the same program gave {first:?}, then {again:?}"))
            }
        },
    );
}

// ---------------------------------------------------------------------------------------------
// requests: protobuf bytes decoded as tonic does, then validated

fn request_seeds() -> Vec<Vec<u8>> {
    let ranges = serde_json::to_string(&mpiflow::sample::motion::MotionRanges::default()).unwrap();
    let stream = |r: pb::StreamRequest| r.encode_to_vec();
    let crop = Some(pb::OutputCrop { width: 64, height: 32, mode: 2 });
    vec![
        stream(pb::StreamRequest::default()),
        stream(pb::StreamRequest {
            rank: 1,
            world_size: 4,
            start_index: 100,
            count: 10,
            batch_size: 4,
            prefetch: 8,
            ..pb::SampleSpec {
                dataset: "photos".into(),
                seed: 7,
                fields: vec![1, 2, 3],
                flow_dtype: 2,
                compression: 2,
                crop,
                motion_preset: "reference".into(),
                motion_ranges_json: ranges.clone(),
                max_objects: Some(3),
                motions_per_image: Some(2),
                ..Default::default()
            }
            .stream()
        }),
        stream(pb::StreamRequest { start_index: u64::MAX - 3, count: 2, world_size: 2, ..Default::default() }),
        pb::SampleSpec { motion_ranges_json: ranges, crop, ..Default::default() }
            .samples(vec![0, 5, u64::MAX])
            .encode_to_vec(),
    ]
}

fn check_service_error(what: &str, e: mpiflow::service::ServiceError) -> Result<(), String> {
    let text = e.to_string();
    let field_first =
        matches!(&e, mpiflow::service::ServiceError::InvalidArgument { field, .. } if text.starts_with(field));
    if e.code() != tonic::Code::InvalidArgument || !field_first {
        return Err(format!("{what}: {:?} {text:?} is not INVALID_ARGUMENT naming its field first", e.code()));
    }
    printable_error(what, &text)?;
    let status: tonic::Status = e.into();
    printable_error(what, status.message())
}

#[test]
fn fuzz_requests() {
    let _serial = serial();
    let config = mpiflow::service::ServiceConfig::default();
    let seeds = request_seeds();
    fuzz(
        "requests",
        4000,
        |rng| {
            if rng.random_bool(0.3) {
                let long = "p".repeat(rng.random_range(0..20_000));
                let json =
                    ["", "{", "{}", "null", "[1,2]", "{\"camera\": 1}", &long][rng.random_range(0..7)].to_string();
                let pick64 = |rng: &mut ChaCha8Rng| {
                    [0, 1, 2, u64::MAX, u64::MAX - 1, 1 << 63, rng.random()][rng.random_range(0..7)]
                };
                let pick32 = |rng: &mut ChaCha8Rng| {
                    [0, 1, 2, 64, 65, 256, 1 << 20, (1 << 20) + 1, u32::MAX, rng.random()][rng.random_range(0..10)]
                };
                pb::StreamRequest {
                    rank: pick32(rng),
                    world_size: pick32(rng),
                    start_index: pick64(rng),
                    count: pick64(rng),
                    batch_size: pick32(rng),
                    prefetch: pick32(rng),
                    ..pb::SampleSpec {
                        fields: (0..rng.random_range(0..12)).map(|_| rng.random_range(-2..14)).collect(),
                        flow_dtype: rng.random_range(-1..4),
                        compression: rng.random_range(-1..4),
                        crop: rng.random_bool(0.5).then(|| pb::OutputCrop {
                            width: pick32(rng),
                            height: pick32(rng),
                            mode: rng.random_range(-1..4),
                        }),
                        motion_preset: if rng.random() { long.clone() } else { "paper-kitti".into() },
                        motion_ranges_json: json,
                        max_objects: rng.random_bool(0.5).then(|| pick32(rng)),
                        motions_per_image: rng.random_bool(0.5).then(|| pick32(rng)),
                        ..Default::default()
                    }
                    .stream()
                }
                .encode_to_vec()
            } else {
                mutate(rng, &seeds, 1 << 16)
            }
        },
        |input| 16 * input.len() + 4 * MIB,
        |input| {
            if let Ok(r) = pb::StreamRequest::decode(input) {
                match mpiflow::service::validate::stream_shape(&r, &config) {
                    Ok((rank, world, batch, prefetch)) => {
                        let first = r.start_index.checked_add(u64::from(rank));
                        let fits = r.count == 0
                            || first
                                .and_then(|f| {
                                    (r.count - 1).checked_mul(u64::from(world)).and_then(|d| d.checked_add(f))
                                })
                                .is_some_and(|l| l < u64::MAX);
                        if rank >= world
                            || batch == 0
                            || batch > config.max_batch_size
                            || prefetch < batch
                            || prefetch > config.max_prefetch.max(batch)
                            || !fits
                        {
                            return Err(format!("stream_shape accepted {r:?} as {:?}", (rank, world, batch, prefetch)));
                        }
                    }
                    Err(e) => check_service_error("stream_shape", e)?,
                }
                let spec = r.spec.unwrap_or_default();
                if let Err(e) = mpiflow::service::spec::Spec::try_from((&spec, &config)) {
                    check_service_error("spec", e)?;
                }
            }
            if let Ok(r) = pb::SamplesRequest::decode(input) {
                match mpiflow::service::validate::indices(&r.indices) {
                    Ok(v) if v.is_empty() || v.len() > mpiflow::service::validate::MAX_INDICES => {
                        return Err(format!("indices accepted {} indices", v.len()))
                    }
                    Ok(_) => {}
                    Err(e) => check_service_error("indices", e)?,
                }
            }
            Ok(())
        },
    );
}

// ---------------------------------------------------------------------------------------------
// regression tests: one per crash the harnesses found, named after it

/// Peak bytes allocated while `f` runs (above what was held before), one test at a time.
fn peak_of<T>(f: impl FnOnce() -> T) -> (T, usize) {
    let base = PeakAlloc.current_usage();
    PeakAlloc.reset_peak_usage();
    let out = f();
    (out, PeakAlloc.peak_usage().saturating_sub(base))
}

/// `npy_depth`: a `.npy` of 1 MiB of u8 whose shape is over the pixel limit is refused by the
/// shape in its header, before its data is read (read whole into f64 it would take 8 bytes per
/// byte of file: 10 MiB here, 2 GiB for a 256 MiB upload).
#[test]
fn regression_npy_depth_over_the_pixel_limit_is_refused_before_its_data_is_read() {
    let _serial = serial();
    let l = DEPTH_LIMITS;
    let bytes = npy_raw("|u1", false, "(1024, 1000)", &vec![3u8; 1024 * 1000]);
    let (r, peak) = peak_of(|| depth_npy_from_bytes(&bytes, &l));
    let (kind, message) = r.unwrap_err();
    assert_eq!(kind, FailureKind::TooLarge, "{message}");
    assert!(peak < 256 << 10, "refusing it allocated {peak} bytes");
}

/// `mask_disparity_png`: a 16-bit index PNG of 256 x 256 with 1024 distinct ids (a few KiB)
/// stands for 1024 full-frame f32 masks (256 MiB; at the default limits 40 MP x 1024 x 4 B =
/// 160 GB); instance masks over `MAX_MASK_FRAMES` frames of the pixel limit are refused before
/// they are allocated.
#[test]
fn regression_mask_png_with_many_instances_is_refused_before_its_masks_are_made() {
    let _serial = serial();
    let l = MASK_LIMITS;
    let bytes = png_gray16_ids(256, 256, 1024);
    let (r, peak) = peak_of(|| InstanceMasks::from_index_png_bytes(&bytes, "many.png", &l).map(|m| m.masks.len()));
    let e = r.expect_err("1024 instances of 256 x 256 over the mask budget");
    assert_eq!(e.failure_kind(), FailureKind::TooLarge, "{e}");
    assert!(peak < image_budget(&l) + 16 * l.max_pixels as usize, "refusing it allocated {peak} bytes");
    // as many instances as the budget allows still load
    let ok = png_gray16_ids(256, 256, mpiflow::raster::MAX_MASK_FRAMES as u32);
    assert_eq!(
        InstanceMasks::from_index_png_bytes(&ok, "ok.png", &l).unwrap().masks.len(),
        mpiflow::raster::MAX_MASK_FRAMES
    );
}

/// `npz_mpi`: an `.npz` whose arrays decompress to more values than the limit (a zip bomb: 16 Mi
/// zero f32 values deflate to 64 KiB) is refused by its arrays' header shapes, before their data
/// is read.
#[test]
fn regression_npz_zip_bomb_is_refused_by_its_shapes() {
    let _serial = serial();
    let dir = failure_dir().join("regression-npz");
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("bomb.npz");
    let zeros = npy_raw("<f4", false, "(1, 4, 3, 1024, 1024)", &vec![0u8; 4 * 3 * 1024 * 1024 * 4]);
    std::fs::write(&path, npz(&[("mpi_rgb", zeros)])).unwrap();
    assert!(std::fs::metadata(&path).unwrap().len() < 1 << 20);
    let (r, peak) = peak_of(|| mpiflow::mpi::npz::load_npz_limited(&path, NPZ_MAX_VALUES));
    let e = r.unwrap_err();
    assert!(e.to_string().contains("limit"), "{e}");
    assert!(peak < 4 * MIB, "refusing it allocated {peak} bytes");
}

/// `npz_mpi`: an `.npz` member whose version-2 npy header claims 4 GiB (a u32 length) is refused
/// without allocating that buffer: the length is checked against the member's size and the 64 KiB
/// header limit first (as for `.npy` depth files).
#[test]
fn regression_npz_member_header_length_is_checked_before_allocating() {
    let _serial = serial();
    let dir = failure_dir().join("regression-npz-header");
    std::fs::create_dir_all(&dir).unwrap();
    for claimed in [0xFFFF_FFF0u32, 1 << 20] {
        let mut member = b"\x93NUMPY\x02\x00".to_vec();
        member.extend_from_slice(&claimed.to_le_bytes());
        // a member long enough for the 1 MiB claim, so only the header limit can refuse it
        member.resize(12 + (1 << 20) + 64, b' ');
        let path = dir.join(format!("header-{claimed}.npz"));
        std::fs::write(&path, npz(&[("mpi_rgb", member)])).unwrap();
        let (r, peak) = peak_of(|| mpiflow::mpi::npz::load_npz_limited(&path, NPZ_MAX_VALUES));
        let e = r.unwrap_err().to_string();
        assert!(e.contains("mpi_rgb") && e.contains("header of"), "{claimed}: {e}");
        assert!(peak < 4 * MIB, "{claimed}: refusing it allocated {peak} bytes");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `requests`: a `motion_preset` of 15 000 characters was repeated whole in the error; it is
/// echoed short (`failure::echo`).
#[test]
fn regression_long_motion_preset_is_echoed_short() {
    let _serial = serial();
    let long = "p".repeat(15_000);
    let e = mpiflow::service::validate::overrides(&long, "", None, None).unwrap_err();
    let text = e.to_string();
    assert!(text.starts_with("motion_preset") && text.len() < MAX_ERROR_CHARS, "{} characters", text.len());
}

/// `requests`: `motion_ranges_json` with an unknown field or variant holding a control
/// character (DEL, escape) was quoted raw in the error by the JSON parser; it is made printable.
#[test]
fn regression_motion_ranges_json_error_quotes_no_control_characters() {
    let _serial = serial();
    let json = serde_json::to_string(&mpiflow::sample::motion::MotionRanges::default()).unwrap();
    let bad = json.replacen("\"camera\"", "\"cam\u{7f}\u{1b}[2Jera\"", 1);
    assert_ne!(bad, json);
    let text = mpiflow::service::validate::overrides("", &bad, None, None).unwrap_err().to_string();
    assert!(text.starts_with("motion_ranges_json") && !text.chars().any(char::is_control), "{text:?}");
}

fn saved(name: &str) -> Vec<u8> {
    std::fs::read(repo("tests/data/fuzz").join(name)).expect("a saved fuzz input")
}

/// `png_jpeg` case 128: a damaged JPEG's decoder error ended in a newline.
#[test]
fn regression_png_jpeg_case_128_decoder_error_is_one_printable_line() {
    let _serial = serial();
    let e = load_rgb_from_bytes(&saved("png_jpeg-case-128.bin"), &PHOTO_LIMITS).map(drop).expect_err("a damaged JPEG");
    check_image_error("photo", &e).unwrap();
}

/// `npy_depth` case 1: the `.npy` header parser's error was several lines quoting the header.
#[test]
fn regression_npy_depth_case_1_parser_error_is_one_printable_line() {
    let _serial = serial();
    let (kind, m) =
        depth_npy_from_bytes(&saved("npy_depth-case-1.bin"), &DEPTH_LIMITS).map(drop).expect_err("a damaged header");
    assert_eq!(kind, FailureKind::Depth);
    printable_error("depth", &m).unwrap();
}

/// `webdataset_shard` case 94: a damaged tar header's error quoted its raw bytes.
#[test]
fn regression_webdataset_shard_case_94_tar_error_is_printable() {
    let _serial = serial();
    let dir = failure_dir().join("regression-shard");
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("case-94.tar");
    std::fs::write(&path, saved("webdataset_shard-case-94.bin")).unwrap();
    let e = ShardSource::open(&path, &shard_options()).map(drop).expect_err("no usable sample");
    printable_error("open", &e.to_string()).unwrap();
}

/// `npy_depth` case 17955 (the 20-second run): a 65-byte version-2 `.npy` whose header length
/// field claims 662 MB made the header parser allocate that much; the claim is checked against
/// the file's size first (`io::npy::check_header_len`).
#[test]
fn regression_npy_depth_case_17955_header_length_bomb_is_refused_before_allocating() {
    let _serial = serial();
    let bytes = saved("npy_depth-case-17955.bin");
    let (r, peak) = peak_of(|| depth_npy_from_bytes(&bytes, &DEPTH_LIMITS).map(drop));
    let (kind, m) = r.expect_err("a header longer than the file");
    assert_eq!(kind, FailureKind::Depth, "{m}");
    assert!(peak < 64 << 10, "refusing it allocated {peak} bytes");
}

/// `npy_depth` cases 985645 and 1258446 (the 8-minute run): 176- and 565-byte `.npy` files whose
/// headers nest 13 and 15 `{`: the header parser backtracked over them and allocated 100 MB and
/// 25 MB (each further level multiplies it: a few more would take the machine). Headers nested
/// deeper than 4 brackets or holding a second dict are refused before the parser sees them
/// (`io::npy::check_header`), for depth files, uploads and `.npz` members alike.
#[test]
fn regression_npy_depth_case_985645_nested_header_is_refused_before_the_parser() {
    let _serial = serial();
    for case in ["npy_depth-case-985645.bin", "npy_depth-case-1258446.bin"] {
        let bytes = saved(case);
        let (r, peak) = peak_of(|| depth_npy_from_bytes(&bytes, &DEPTH_LIMITS).map(drop));
        let (kind, m) = r.expect_err("a nested header");
        assert_eq!(kind, FailureKind::Depth, "{case}: {m}");
        assert!(m.contains("deeper than") || m.contains("more than one dict"), "{case}: {m}");
        printable_error("depth", &m).unwrap();
        assert!(peak < 64 << 10, "{case}: refusing it allocated {peak} bytes");
    }
    // 40 nested levels in an `.npz` member: refused, nothing large allocated
    let dir = failure_dir().join("regression-npz-nested");
    std::fs::create_dir_all(&dir).unwrap();
    let header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {}1, }}", "(".repeat(40));
    let mut member = b"\x93NUMPY\x01\x00".to_vec();
    member.extend((header.len() as u16).to_le_bytes());
    member.extend(header.as_bytes());
    member.extend([0u8; 4]);
    let path = dir.join("nested.npz");
    std::fs::write(&path, npz(&[("mpi_rgb", member)])).unwrap();
    let (r, peak) = peak_of(|| mpiflow::mpi::npz::load_npz_limited(&path, NPZ_MAX_VALUES).map(drop));
    let e = r.unwrap_err().to_string();
    assert!(e.contains("mpi_rgb") && e.contains("deeper than"), "{e}");
    assert!(peak < 4 * MIB, "refusing it allocated {peak} bytes");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `npz_mpi` cases 308105 and 336076 (the 8-minute run): `.npz` MPIs whose disparities (1e301,
/// 1e-300) do not decrease; the error printed them with `{}`, 300 digits each, 639 characters in
/// all. They are printed in the shortest round-trip form (`9.37e300`).
#[test]
fn regression_npz_mpi_case_308105_huge_disparity_is_printed_short() {
    let _serial = serial();
    let dir = failure_dir().join("regression-npz-308105");
    std::fs::create_dir_all(&dir).unwrap();
    for case in ["npz_mpi-case-308105.bin", "npz_mpi-case-336076.bin"] {
        let path = dir.join(case.replace(".bin", ".npz"));
        std::fs::write(&path, saved(case)).unwrap();
        let e = mpiflow::mpi::npz::load_npz_limited(&path, 1 << 20)
            .and_then(|m| m.validate().map(|()| m))
            .map(drop)
            .expect_err("disparities that do not decrease");
        let m = e.to_string();
        assert!(m.contains("must decrease strictly") && m.len() < 400, "{case}: {} characters: {m}", m.len());
        printable_error("npz", &m).unwrap();
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `npz_mpi` case 28955 (the 150-second run): an `.npz` whose `K` member's header holds control
/// bytes. Messages are cut by their escaped length (`failure::printable`, `failure::echo`): cut to
/// 300 characters and then escaped, this one would be 910 characters.
#[test]
fn regression_npz_mpi_case_28955_escaped_error_is_cut() {
    let _serial = serial();
    let dir = failure_dir().join("regression-npz-28955");
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("case-28955.npz");
    std::fs::write(&path, saved("npz_mpi-case-28955.bin")).unwrap();
    let e = mpiflow::mpi::npz::load_npz_limited(&path, 1 << 20).map(drop).expect_err("a damaged header");
    printable_error("npz", &e.to_string()).unwrap();
}
