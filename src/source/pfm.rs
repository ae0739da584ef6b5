//! Portable float maps (`.pfm`): the float image format of Middlebury, KITTI tools and many depth
//! and disparity datasets; read (with size limits) and written.
//!
//! # Format
//!
//! An ASCII header of three whitespace-separated fields, then raw IEEE-754 `f32` samples:
//!
//! 1. `Pf` (one channel) or `PF` (three channels, interleaved RGB);
//! 2. width and height in pixels (decimal);
//! 3. the scale: a non-zero decimal number whose **sign gives the byte order** (negative =
//!    little-endian, positive = big-endian); its magnitude is a unit that most tools ignore, and
//!    so do we (it is returned as [`Pfm::scale`]).
//!
//! Exactly one whitespace byte (normally `\n`) separates the scale from the samples. Rows are
//! stored **bottom to top**; [`Pfm::data`] is returned top to bottom (row 0 = the image's top
//! row), like every other image in this crate. Non-finite samples (Middlebury's `inf` for unknown
//! disparity) are kept as they are; callers decide what they mean.

use super::FailureKind;
use crate::io::image::ImageLimits;
use std::io::Write;
use std::path::Path;

/// Why a PFM could not be read: a message without the path (callers add it) and its kind
/// ([`FailureKind::TooLarge`], [`FailureKind::Truncated`] or [`FailureKind::Decode`]).
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{message}")]
pub struct PfmError {
    pub kind: FailureKind,
    pub message: String,
}

fn pfm_err(kind: FailureKind, message: impl Into<String>) -> PfmError {
    PfmError { kind, message: message.into() }
}

/// A decoded float map.
#[derive(Clone, Debug, PartialEq)]
pub struct Pfm {
    pub width: usize,
    pub height: usize,
    /// 1 (`Pf`) or 3 (`PF`).
    pub channels: usize,
    /// The magnitude of the header's scale field.
    pub scale: f32,
    /// `height * width * channels` samples, rows top to bottom, channels interleaved.
    pub data: Vec<f32>,
}

/// Longest accepted header (three short fields and their separators).
const MAX_HEADER: usize = 256;

/// Decodes a PFM held in memory. Errors say what is wrong (without naming a file).
pub fn parse_pfm(bytes: &[u8], limits: &ImageLimits) -> Result<Pfm, PfmError> {
    if bytes.len() as u64 > limits.max_bytes {
        let m = format!("{} bytes is larger than the limit of {} bytes", bytes.len(), limits.max_bytes);
        return Err(pfm_err(FailureKind::TooLarge, m));
    }
    // three whitespace-separated tokens, then exactly one whitespace byte
    let mut pos = 0usize;
    let mut tokens: Vec<&[u8]> = Vec::with_capacity(4);
    while tokens.len() < 4 {
        while pos < bytes.len() && bytes[pos].is_ascii_whitespace() {
            pos += 1;
        }
        let start = pos;
        while pos < bytes.len() && !bytes[pos].is_ascii_whitespace() {
            pos += 1;
        }
        if start == pos || pos >= bytes.len() || pos > MAX_HEADER {
            // the data ends inside the header, or the header is not one
            let kind =
                if pos >= bytes.len() && !tokens.is_empty() { FailureKind::Truncated } else { FailureKind::Decode };
            return Err(pfm_err(
                kind,
                "not a PFM file: truncated or malformed header (expected `Pf` or `PF`, width height, scale)",
            ));
        }
        tokens.push(&bytes[start..pos]);
    }
    let channels = match tokens[0] {
        b"Pf" => 1,
        b"PF" => 3,
        other => {
            return Err(pfm_err(
                FailureKind::Decode,
                format!(
                    "not a PFM file: magic {:?}, expected \"Pf\" (grey) or \"PF\" (colour)",
                    String::from_utf8_lossy(&other[..other.len().min(8)])
                ),
            ))
        }
    };
    let text = |t: &[u8]| String::from_utf8_lossy(t).into_owned();
    let bad = |m: String| pfm_err(FailureKind::Decode, m);
    let width: u64 = text(tokens[1]).parse().map_err(|_| bad(format!("bad PFM width {:?}", text(tokens[1]))))?;
    let height: u64 = text(tokens[2]).parse().map_err(|_| bad(format!("bad PFM height {:?}", text(tokens[2]))))?;
    let scale: f32 = text(tokens[3]).parse().map_err(|_| bad(format!("bad PFM scale {:?}", text(tokens[3]))))?;
    if !scale.is_finite() || scale == 0.0 {
        return Err(bad(format!("bad PFM scale {scale}: must be finite and non-zero (its sign gives the byte order)")));
    }
    if width == 0 || height == 0 {
        return Err(bad(format!("empty PFM image ({width} x {height})")));
    }
    let (w32, h32) = (u32::try_from(width), u32::try_from(height));
    match (w32, h32) {
        (Ok(w), Ok(h)) if limits.check_dimensions(w, h) => {}
        _ => {
            let m = format!("image of {width} x {height} pixels is too large ({limits})");
            return Err(pfm_err(FailureKind::TooLarge, m));
        }
    }
    // `pos` is at the whitespace byte that ends the scale field
    let data_start = pos + 1;
    let (w, h) = (width as usize, height as usize);
    let n = w * h * channels;
    let need = n * 4;
    let have = bytes.len().saturating_sub(data_start);
    if have < need {
        return Err(pfm_err(
            FailureKind::Truncated,
            format!("truncated PFM: {w} x {h} x {channels} samples need {need} bytes of data, the file holds {have}"),
        ));
    }
    let little = scale < 0.0;
    let raw = &bytes[data_start..data_start + need];
    let row_len = w * channels;
    let mut data = vec![0f32; n];
    for (file_row, chunk) in raw.chunks_exact(row_len * 4).enumerate() {
        let y = h - 1 - file_row;
        let dst = &mut data[y * row_len..(y + 1) * row_len];
        for (d, b) in dst.iter_mut().zip(chunk.chunks_exact(4)) {
            let b = [b[0], b[1], b[2], b[3]];
            *d = if little { f32::from_le_bytes(b) } else { f32::from_be_bytes(b) };
        }
    }
    Ok(Pfm { width: w, height: h, channels, scale: scale.abs(), data })
}

/// Reads a PFM file, refusing files over `limits.max_bytes` before reading them and images over
/// the dimension limits before allocating. Errors are messages without the path (callers add it).
pub fn read_pfm(path: &Path, limits: &ImageLimits) -> Result<Pfm, PfmError> {
    let io = |e: std::io::Error| pfm_err(FailureKind::Decode, io_message(&e));
    let meta = std::fs::metadata(path).map_err(io)?;
    if !meta.is_file() {
        return Err(pfm_err(FailureKind::Decode, "not a regular file"));
    }
    if meta.len() > limits.max_bytes {
        let m = format!("{} bytes is larger than the limit of {} bytes", meta.len(), limits.max_bytes);
        return Err(pfm_err(FailureKind::TooLarge, m));
    }
    let bytes = std::fs::read(path).map_err(io)?;
    parse_pfm(&bytes, limits)
}

fn io_message(e: &std::io::Error) -> String {
    if e.kind() == std::io::ErrorKind::NotFound {
        "file not found".into()
    } else {
        e.to_string()
    }
}

/// Encodes a PFM: `data` is `height * width * channels` samples top to bottom (channels 1 or 3),
/// written bottom to top with scale `-1` (little-endian) or `1` (big-endian).
///
/// # Panics
/// If `channels` is not 1 or 3 or the data length does not match.
pub fn encode_pfm(width: usize, height: usize, channels: usize, data: &[f32], little_endian: bool) -> Vec<u8> {
    assert!(channels == 1 || channels == 3, "PFM holds 1 or 3 channels, not {channels}");
    assert_eq!(data.len(), width * height * channels, "PFM data length does not match {width} x {height} x {channels}");
    let magic = if channels == 1 { "Pf" } else { "PF" };
    let scale = if little_endian { "-1.0" } else { "1.0" };
    let mut out = format!("{magic}\n{width} {height}\n{scale}\n").into_bytes();
    out.reserve(data.len() * 4);
    let row_len = width * channels;
    for y in (0..height).rev() {
        for &v in &data[y * row_len..(y + 1) * row_len] {
            out.extend_from_slice(&if little_endian { v.to_le_bytes() } else { v.to_be_bytes() });
        }
    }
    out
}

/// Writes [`encode_pfm`] to a file.
pub fn write_pfm(
    path: &Path,
    width: usize,
    height: usize,
    channels: usize,
    data: &[f32],
    little_endian: bool,
) -> std::io::Result<()> {
    let mut f = std::io::BufWriter::new(std::fs::File::create(path)?);
    f.write_all(&encode_pfm(width, height, channels, data, little_endian))?;
    f.flush()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_both_byte_orders_and_row_order() {
        let data: Vec<f32> = vec![1.0, 2.0, 3.0, 4.0, 5.0, f32::INFINITY];
        for little in [true, false] {
            let bytes = encode_pfm(3, 2, 1, &data, little);
            let p = parse_pfm(&bytes, &ImageLimits::default()).unwrap();
            assert_eq!((p.width, p.height, p.channels, p.scale), (3, 2, 1, 1.0));
            assert_eq!(p.data, data);
        }
        // the first stored row is the bottom one
        let bytes = encode_pfm(1, 2, 1, &[7.0, 9.0], true);
        assert_eq!(&bytes[bytes.len() - 8..bytes.len() - 4], &9.0f32.to_le_bytes());
    }

    #[test]
    fn hand_written_big_endian_colour() {
        let mut bytes = b"PF 1 1 2.5\n".to_vec();
        for v in [0.25f32, 0.5, 0.75] {
            bytes.extend_from_slice(&v.to_be_bytes());
        }
        let p = parse_pfm(&bytes, &ImageLimits::default()).unwrap();
        assert_eq!((p.channels, p.scale), (3, 2.5));
        assert_eq!(p.data, vec![0.25, 0.5, 0.75]);
    }

    #[test]
    fn errors() {
        let l = ImageLimits::default();
        let err = |b: &[u8]| parse_pfm(b, &l).unwrap_err();
        let (magic, cut, width) = (err(b"P6\n1 1\n255\n"), err(b"Pf\n2 2\n-1\n\0\0\0\0"), err(b"Pf\nx 2\n-1\n"));
        assert!(magic.message.contains("magic") && magic.kind == FailureKind::Decode, "{magic}");
        assert!(cut.message.contains("truncated") && cut.kind == FailureKind::Truncated, "{cut}");
        assert!(width.message.contains("width") && width.kind == FailureKind::Decode, "{width}");
        assert!(err(b"Pf\n1 1\n0\n\0\0\0\0").message.contains("scale"));
        let big = err(b"Pf\n100000 100000\n-1\n");
        assert!(big.message.contains("too large") && big.kind == FailureKind::TooLarge, "{big}");
        assert_eq!(err(b"Pf\n2 2").kind, FailureKind::Truncated);
        assert!(parse_pfm(b"Pf", &l).is_err());
    }
}
