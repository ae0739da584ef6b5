//! Photos decoded at reduced scale: a sequential JPEG's DCT scaling (to 1/2, 1/4 or 1/8 of each
//! side) down to the smallest size that still covers the size the photo is brought to, so that a
//! phone's 48-megapixel photo is never held at full resolution.
//!
//! Only sequential (baseline or extended) JPEGs of one or three components are scaled: their
//! decoder keeps the image at the reduced size as it goes, so its memory follows the decoded
//! size. A progressive JPEG's decoder holds every coefficient of the full image, a PNG or WebP
//! has no reduced decoding: those are decoded whole, and their size as stored is what the limits
//! apply to.

use ::image::{DynamicImage, GrayImage};
use std::io::Cursor;

/// Why a reduced-scale decode failed (the caller names the file: `io::image`'s `ImageError`).
#[derive(Debug)]
pub(crate) enum ScaledError {
    /// the file is not a JPEG the decoder can read
    Corrupt(String),
    /// a JPEG of a kind with no reduced decoding here
    Unsupported(String),
}

/// Whether `bytes` are a sequential JPEG (start-of-frame `SOF0` or `SOF1`, Huffman coded) of one
/// or three components: a JPEG decodable at 1/2, 1/4 or 1/8 scale. The marker segments are
/// walked from the start up to the first start-of-frame; anything else is `false`.
pub fn jpeg_scalable(bytes: &[u8]) -> bool {
    if !bytes.starts_with(&[0xFF, 0xD8]) {
        return false;
    }
    let mut pos = 2usize;
    while pos + 4 <= bytes.len() {
        if bytes[pos] != 0xFF {
            return false;
        }
        let code = bytes[pos + 1];
        if code == 0xFF {
            pos += 1;
            continue;
        }
        let len = usize::from(u16::from_be_bytes([bytes[pos + 2], bytes[pos + 3]]));
        match code {
            // SOF0 / SOF1: sequential DCT, Huffman; the component count follows precision,
            // height and width
            0xC0 | 0xC1 => return bytes.get(pos + 9).is_some_and(|&n| n == 1 || n == 3),
            // any other start of frame (progressive, lossless, arithmetic), or the scan itself
            0xC2..=0xC3 | 0xC5..=0xC7 | 0xC9..=0xCB | 0xCD..=0xCF | 0xDA | 0xD9 => return false,
            _ => {}
        }
        if len < 2 {
            return false;
        }
        pos += 2 + len;
    }
    false
}

/// A side of `len` pixels decoded at `eighths` / 8 of its size, as the JPEG decoder rounds it
/// (up).
pub fn scaled_side(len: u32, eighths: u32) -> u32 {
    if len == 0 {
        return 0;
    }
    ((u64::from(len) * u64::from(eighths) - 1) / 8 + 1) as u32
}

/// The smallest DCT scale, in eighths (1, 2, 4 or 8), at which a JPEG of `stored` size (width,
/// height, as stored) still covers `need` on both sides; 8 (full size) when no reduced one does.
pub fn decode_scale(stored: (u32, u32), need: (u32, u32)) -> u32 {
    [1, 2, 4]
        .into_iter()
        .find(|&e| scaled_side(stored.0, e) >= need.0 && scaled_side(stored.1, e) >= need.1)
        .unwrap_or(8)
}

/// Decodes a sequential JPEG ([`jpeg_scalable`]) at `eighths` / 8 of its stored size, its pixels
/// as stored (the caller turns them to the file's orientation). `max_bytes` bounds the decoded
/// buffer.
pub(crate) fn decode_jpeg_scaled(bytes: &[u8], eighths: u32, max_bytes: usize) -> Result<DynamicImage, ScaledError> {
    let corrupt = |e: jpeg_decoder::Error| ScaledError::Corrupt(crate::failure::printable(&e.to_string(), 300));
    let mut decoder = jpeg_decoder::Decoder::new(Cursor::new(bytes));
    decoder.set_max_decoding_buffer_size(max_bytes);
    decoder.read_info().map_err(corrupt)?;
    let info = decoder.info().ok_or_else(|| ScaledError::Corrupt("no frame header".into()))?;
    let (w, h) = (u32::from(info.width), u32::from(info.height));
    let want = (scaled_side(w, eighths), scaled_side(h, eighths));
    // the decoder picks the smallest scale that reaches one of the requested sides: asking for
    // the sides at `eighths` gives that scale (smaller scales give shorter sides)
    let (sw, sh) = decoder.scale(want.0 as u16, want.1 as u16).map_err(corrupt)?;
    let pixels = decoder.decode().map_err(corrupt)?;
    let image = match info.pixel_format {
        jpeg_decoder::PixelFormat::L8 => {
            GrayImage::from_raw(u32::from(sw), u32::from(sh), pixels).map(DynamicImage::ImageLuma8)
        }
        jpeg_decoder::PixelFormat::RGB24 => {
            ::image::RgbImage::from_raw(u32::from(sw), u32::from(sh), pixels).map(DynamicImage::ImageRgb8)
        }
        other => {
            return Err(ScaledError::Unsupported(format!(
                "a JPEG of pixel format {other:?} cannot be decoded at reduced scale"
            )))
        }
    };
    image.ok_or_else(|| ScaledError::Corrupt(format!("the decoder gave too few pixels for {sw} x {sh}")))
}
