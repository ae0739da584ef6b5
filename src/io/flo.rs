//! Optical-flow files: Middlebury `.flo` (float32 u, v) and KITTI 16-bit flow PNGs (u, v, valid).
//!
//! `.flo`: the float32 magic 202021.25, int32 width, int32 height, then H x W x (u, v) float32,
//! all little-endian. Values with |u| or |v| above 1e9 mean "unknown".
//!
//! KITTI: a 16-bit RGB PNG with u = (R - 2^15) / 64, v = (G - 2^15) / 64 and B = 1 where the
//! flow is valid, 0 elsewhere.

use super::image::{decode_file_as_stored, write_png, ImageError, ImageLimits};
use ::image::{DynamicImage, ExtendedColorType};
use std::fs::File;
use std::io::{self, BufReader, BufWriter, Read, Write};
use std::path::Path;

/// The `.flo` magic number, stored as a little-endian float32 (bytes "PIEH").
pub const FLO_MAGIC: f32 = 202021.25;

/// Flow components above this magnitude mark an unknown flow in `.flo` files.
pub const UNKNOWN_FLOW_THRESH: f32 = 1e9;

/// Largest accepted `.flo` size in pixels (2^28, i.e. 2 GiB of data).
pub const MAX_FLO_PIXELS: u64 = 1 << 28;

const HEADER_LEN: u64 = 12;

fn invalid_data(msg: String) -> io::Error {
    io::Error::new(io::ErrorKind::InvalidData, msg)
}

fn invalid_input(msg: String) -> io::Error {
    io::Error::new(io::ErrorKind::InvalidInput, msg)
}

/// Whether a `.flo` vector means "unknown flow" (a component above 1e9 in magnitude, or not
/// a number).
pub fn is_unknown_flow(u: f32, v: f32) -> bool {
    !(u.abs() <= UNKNOWN_FLOW_THRESH && v.abs() <= UNKNOWN_FLOW_THRESH)
}

fn check_flow_len(width: usize, height: usize, len: usize) -> io::Result<()> {
    let need = width.checked_mul(height).and_then(|n| n.checked_mul(2));
    if need != Some(len) {
        return Err(invalid_input(format!(
            "a {width} x {height} flow needs {} values, the buffer holds {len}",
            width.saturating_mul(height).saturating_mul(2)
        )));
    }
    Ok(())
}

/// Writes an H x W x 2 flow (u, v interleaved, row-major) as a Middlebury `.flo` stream.
pub fn write_flo_to<W: Write>(mut w: W, width: usize, height: usize, flow: &[f32]) -> io::Result<()> {
    check_flow_len(width, height, flow.len())?;
    let pixels = (width as u64) * (height as u64);
    let (wi, hi) = match (i32::try_from(width), i32::try_from(height)) {
        (Ok(wi), Ok(hi)) if wi > 0 && hi > 0 && pixels <= MAX_FLO_PIXELS => (wi, hi),
        _ => {
            return Err(invalid_input(format!(
                "cannot write a {width} x {height} .flo (sides must be positive, at most \
                 {MAX_FLO_PIXELS} pixels)"
            )))
        }
    };
    w.write_all(&FLO_MAGIC.to_le_bytes())?;
    w.write_all(&wi.to_le_bytes())?;
    w.write_all(&hi.to_le_bytes())?;
    let mut buf = Vec::with_capacity(64 * 1024);
    for chunk in flow.chunks(16 * 1024) {
        buf.clear();
        buf.extend(chunk.iter().flat_map(|v| v.to_le_bytes()));
        w.write_all(&buf)?;
    }
    w.flush()
}

/// Writes an H x W x 2 flow (u, v interleaved, row-major) as a Middlebury `.flo` file.
pub fn write_flo(path: &Path, width: usize, height: usize, flow: &[f32]) -> io::Result<()> {
    check_flow_len(width, height, flow.len())?;
    write_flo_to(BufWriter::new(File::create(path)?), width, height, flow)
}

/// Parses and validates the 12-byte header; returns (width, height) and the expected data length.
fn parse_header(hd: &[u8; 12]) -> io::Result<(usize, usize, u64)> {
    let magic = f32::from_le_bytes([hd[0], hd[1], hd[2], hd[3]]);
    if magic != FLO_MAGIC {
        return Err(invalid_data(format!(
            "not a .flo file: magic is {:02x?} ({magic}), expected {FLO_MAGIC} (\"PIEH\")",
            &hd[..4]
        )));
    }
    let w = i32::from_le_bytes([hd[4], hd[5], hd[6], hd[7]]);
    let h = i32::from_le_bytes([hd[8], hd[9], hd[10], hd[11]]);
    if w <= 0 || h <= 0 {
        return Err(invalid_data(format!(".flo header has invalid dimensions {w} x {h}")));
    }
    let pixels = w as u64 * h as u64;
    if pixels > MAX_FLO_PIXELS {
        return Err(invalid_data(format!(
            ".flo header claims {w} x {h} pixels, more than the limit of {MAX_FLO_PIXELS}"
        )));
    }
    Ok((w as usize, h as usize, pixels * 8))
}

fn decode_values(bytes: &[u8]) -> Vec<f32> {
    bytes.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect()
}

fn length_error(width: usize, height: usize, expected: u64, actual: u64) -> io::Error {
    invalid_data(format!(
        ".flo of {width} x {height} must be {} bytes long, found {} (truncated or trailing data)",
        HEADER_LEN + expected,
        actual
    ))
}

/// Parses a `.flo` file held in memory; returns (width, height, H x W x 2 flow).
pub fn read_flo_from_bytes(bytes: &[u8]) -> io::Result<(usize, usize, Vec<f32>)> {
    let header: &[u8; 12] = bytes
        .get(..12)
        .and_then(|h| h.try_into().ok())
        .ok_or_else(|| invalid_data(format!(".flo is {} bytes, shorter than its header", bytes.len())))?;
    let (w, h, data_len) = parse_header(header)?;
    if bytes.len() as u64 != HEADER_LEN + data_len {
        return Err(length_error(w, h, data_len, bytes.len() as u64));
    }
    Ok((w, h, decode_values(&bytes[12..])))
}

/// Reads a Middlebury `.flo` file; returns (width, height, H x W x 2 flow). The magic, the
/// dimensions (positive, at most 2^28 pixels) and the file length are checked before the data
/// is read.
pub fn read_flo(path: &Path) -> io::Result<(usize, usize, Vec<f32>)> {
    read_flo_file(path).map_err(|e| io::Error::new(e.kind(), format!("{}: {e}", path.display())))
}

fn read_flo_file(path: &Path) -> io::Result<(usize, usize, Vec<f32>)> {
    let file = File::open(path)?;
    let file_len = file.metadata()?.len();
    let mut r = BufReader::new(file);
    let mut header = [0u8; 12];
    if file_len < HEADER_LEN {
        return Err(invalid_data(format!(".flo is {file_len} bytes, shorter than its header")));
    }
    r.read_exact(&mut header)?;
    let (w, h, data_len) = parse_header(&header)?;
    if file_len != HEADER_LEN + data_len {
        return Err(length_error(w, h, data_len, file_len));
    }
    let mut bytes = vec![0u8; data_len as usize];
    r.read_exact(&mut bytes).map_err(|e| {
        if e.kind() == io::ErrorKind::UnexpectedEof {
            length_error(w, h, data_len, file_len)
        } else {
            e
        }
    })?;
    Ok((w, h, decode_values(&bytes)))
}

/// A flow field read from a KITTI flow PNG.
#[derive(Clone, Debug, PartialEq)]
pub struct KittiFlow {
    pub width: usize,
    pub height: usize,
    /// H x W x 2, (u, v) interleaved, row-major, in pixels (as stored, also where invalid).
    pub flow: Vec<f32>,
    /// H x W, 1 where the flow is valid (B channel > 0), else 0.
    pub valid: Vec<u8>,
}

/// Encodes one flow component: round(64 x + 2^15), clamped to 0..=65535 (about +-512 px).
#[inline]
fn kitti_encode(x: f32) -> u16 {
    (x * 64.0 + 32768.0).round().clamp(0.0, 65535.0) as u16
}

/// Writes a KITTI 16-bit flow PNG. `valid` (H x W, non-zero = valid) defaults to all valid;
/// pixels with a non-finite component are written as invalid with zero flow. Components are
/// rounded to 1/64 px and clamped to [-512, 511.98] px.
pub fn write_kitti_flow_png(
    path: &Path,
    width: usize,
    height: usize,
    flow: &[f32],
    valid: Option<&[u8]>,
) -> io::Result<()> {
    check_flow_len(width, height, flow.len())?;
    if let Some(v) = valid {
        if v.len() != flow.len() / 2 {
            return Err(invalid_input(format!(
                "a {width} x {height} valid mask needs {} values, the buffer holds {}",
                flow.len() / 2,
                v.len()
            )));
        }
    }
    let (w, h) = match (u32::try_from(width), u32::try_from(height)) {
        (Ok(w), Ok(h)) if w > 0 && h > 0 => (w, h),
        _ => return Err(invalid_input(format!("cannot write a {width} x {height} KITTI PNG"))),
    };
    let mut bytes = Vec::with_capacity(flow.len() / 2 * 6);
    for (i, p) in flow.chunks_exact(2).enumerate() {
        let px = if p[0].is_finite() && p[1].is_finite() {
            let ok = valid.is_none_or(|v| v[i] != 0);
            [kitti_encode(p[0]), kitti_encode(p[1]), u16::from(ok)]
        } else {
            [32768, 32768, 0]
        };
        for c in px {
            bytes.extend_from_slice(&c.to_ne_bytes());
        }
    }
    write_png(path, w, h, &bytes, ExtendedColorType::Rgb16).map_err(io::Error::from)
}

/// Reads a KITTI 16-bit flow PNG (default image limits). Anything but a 16-bit RGB(A) PNG is
/// refused as invalid data.
pub fn read_kitti_flow_png(path: &Path) -> io::Result<KittiFlow> {
    read_kitti_flow_png_with_limits(path, &ImageLimits::default())
}

/// [`read_kitti_flow_png`] with explicit limits.
pub fn read_kitti_flow_png_with_limits(path: &Path, limits: &ImageLimits) -> io::Result<KittiFlow> {
    let (w, h, raw, channels) = match decode_file_as_stored(path, limits)? {
        DynamicImage::ImageRgb16(b) => (b.width(), b.height(), b.into_raw(), 3),
        DynamicImage::ImageRgba16(b) => (b.width(), b.height(), b.into_raw(), 4),
        other => {
            return Err(ImageError::Unsupported {
                path: path.to_path_buf(),
                reason: format!("a KITTI flow PNG must be 16-bit RGB, found {:?}", other.color()),
            }
            .into())
        }
    };
    let n = w as usize * h as usize;
    let mut flow = Vec::with_capacity(n * 2);
    let mut valid = Vec::with_capacity(n);
    for px in raw.chunks_exact(channels) {
        flow.push((f32::from(px[0]) - 32768.0) / 64.0);
        flow.push((f32::from(px[1]) - 32768.0) / 64.0);
        valid.push(u8::from(px[2] > 0));
    }
    Ok(KittiFlow { width: w as usize, height: h as usize, flow, valid })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::PathBuf;

    fn tmpdir(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("mpiflow-io-flo-{}-{name}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    fn sample_flow(w: usize, h: usize) -> Vec<f32> {
        (0..w * h * 2).map(|i| (i as f32 * 0.37).sin() * 40.0 - 3.25).collect()
    }

    #[test]
    fn flo_roundtrip_and_layout() {
        let dir = tmpdir("roundtrip");
        let (w, h) = (5, 3);
        let mut flow = sample_flow(w, h);
        flow[4] = 1e10; // unknown flow survives as is
        let p = dir.join("a.flo");
        write_flo(&p, w, h, &flow).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        assert_eq!(&bytes[..4], b"PIEH");
        assert_eq!(bytes.len(), 12 + w * h * 8);
        assert_eq!(&bytes[4..12], &[5, 0, 0, 0, 3, 0, 0, 0]);
        assert_eq!(&bytes[12..16], &flow[0].to_le_bytes());
        let (rw, rh, back) = read_flo(&p).unwrap();
        assert_eq!((rw, rh), (w, h));
        assert_eq!(back, flow);
        assert_eq!(read_flo_from_bytes(&bytes).unwrap(), (w, h, flow));
        assert!(is_unknown_flow(back[4], back[5]));
        assert!(is_unknown_flow(f32::NAN, 0.0));
        assert!(!is_unknown_flow(back[0], back[1]));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn flo_truncated_and_trailing() {
        let dir = tmpdir("truncated");
        let p = dir.join("t.flo");
        write_flo(&p, 4, 4, &sample_flow(4, 4)).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        for cut in [bytes.len() - 1, 20, 12, 7, 0] {
            std::fs::write(&p, &bytes[..cut]).unwrap();
            let e = read_flo(&p).unwrap_err();
            assert_eq!(e.kind(), io::ErrorKind::InvalidData, "cut {cut}: {e}");
            let e2 = read_flo_from_bytes(&bytes[..cut]).unwrap_err();
            assert_eq!(e2.kind(), io::ErrorKind::InvalidData);
            if cut >= 12 {
                assert!(e.to_string().contains("must be 140 bytes long"), "{e}");
            }
        }
        let mut long = bytes.clone();
        long.extend_from_slice(&[0; 4]);
        std::fs::write(&p, &long).unwrap();
        assert!(read_flo(&p).unwrap_err().to_string().contains("trailing"));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn flo_bad_header() {
        let mut bytes = Vec::new();
        write_flo_to(&mut bytes, 2, 2, &[0.0; 8]).unwrap();
        let mut wrong = bytes.clone();
        wrong[..4].copy_from_slice(&202021.0f32.to_le_bytes());
        let e = read_flo_from_bytes(&wrong).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::InvalidData);
        assert!(e.to_string().contains("magic"), "{e}");

        let mut neg = bytes.clone();
        neg[4..8].copy_from_slice(&(-2i32).to_le_bytes());
        assert!(read_flo_from_bytes(&neg).unwrap_err().to_string().contains("-2 x 2"));

        // a header promising 2^30 pixels is refused without allocating
        let mut huge = bytes.clone();
        huge[4..8].copy_from_slice(&(1i32 << 15).to_le_bytes());
        huge[8..12].copy_from_slice(&(1i32 << 15).to_le_bytes());
        assert!(read_flo_from_bytes(&huge).unwrap_err().to_string().contains("limit"));

        let e = read_flo(Path::new("/nonexistent/x.flo")).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::NotFound);
        assert!(e.to_string().starts_with("/nonexistent/x.flo: "), "{e}");
    }

    #[test]
    fn flo_write_checks_the_buffer() {
        let e = write_flo_to(Vec::new(), 2, 2, &[0.0; 7]).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::InvalidInput);
        let e = write_flo_to(Vec::new(), 0, 0, &[]).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::InvalidInput);
    }

    #[test]
    fn kitti_roundtrip() {
        let dir = tmpdir("kitti");
        let (w, h) = (4, 3);
        let mut flow: Vec<f32> = sample_flow(w, h).iter().map(|v| (v * 64.0).round() / 64.0).collect();
        flow[2] = 1000.0; // clamped to the largest representable value
        flow[3] = -1000.0;
        flow[6] = f32::NAN;
        let mut valid = vec![1u8; w * h];
        valid[5] = 0;
        let p = dir.join("k.png");
        write_kitti_flow_png(&p, w, h, &flow, Some(&valid)).unwrap();
        let k = read_kitti_flow_png(&p).unwrap();
        assert_eq!((k.width, k.height), (w, h));
        for i in 0..w * h {
            let expect_valid = u8::from(valid[i] == 1 && i != 3);
            assert_eq!(k.valid[i], expect_valid, "pixel {i}");
            for c in 0..2 {
                let (a, b) = (k.flow[2 * i + c], flow[2 * i + c]);
                match (i, c) {
                    (1, 0) => assert_eq!(a, 511.984_38),
                    (1, 1) => assert_eq!(a, -512.0),
                    (3, _) => assert_eq!(a, 0.0),
                    _ => assert_eq!(a, b, "pixel {i} component {c}"),
                }
            }
        }
        // unquantised values come back within 1/128 px
        let raw = sample_flow(w, h);
        write_kitti_flow_png(&p, w, h, &raw, None).unwrap();
        let k = read_kitti_flow_png(&p).unwrap();
        assert!(k.valid.iter().all(|&v| v == 1));
        let err = k.flow.iter().zip(&raw).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        assert!(err <= 1.0 / 128.0 + 1e-6, "max error {err}");

        // an 8-bit PNG is not a KITTI flow file
        let g = dir.join("g.png");
        crate::io::image::save_gray_png(&g, 2, 2, &[0; 4]).unwrap();
        let e = read_kitti_flow_png(&g).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::InvalidData);
        assert!(e.to_string().contains("16-bit RGB"), "{e}");
        let e = write_kitti_flow_png(&p, 2, 2, &[0.0; 8], Some(&[1, 1])).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::InvalidInput);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
