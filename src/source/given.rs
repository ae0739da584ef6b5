//! Readers of the files that come with a source image: depth (`.npy`, PFM, 16-bit PNG),
//! 8-bit disparity PNGs, from a path or from bytes (shards, uploads), and resizing them (and the
//! image) to the run's size. Each failure carries its [`FailureKind`] (`depth`, `too-large`, ...).

use super::{FailureKind, SourceError};
use crate::io::image::{decode_file, load_depth_png16_with_limits, ImageLimits, RgbImage};
use crate::raster::resize_depth;
use ::image::DynamicImage;
use std::path::Path;

/// The kind of a depth file.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DepthFile {
    Npy,
    Pfm,
    Png16,
}

/// A file that cannot be opened or read; `part` is the kind of failure of the file's role
/// ([`FailureKind::Decode`] for images, `Depth`, `Mask`, `Mpi` for companions).
pub(crate) fn io_err(path: &Path, e: &std::io::Error, part: FailureKind) -> SourceError {
    let message = if e.kind() == std::io::ErrorKind::NotFound { "not found".to_string() } else { e.to_string() };
    SourceError::file(path.display().to_string(), part, message)
}

/// A file error of `kind` whose message does not repeat the path when the underlying error
/// already starts with it.
pub(crate) fn file_err(path: &Path, kind: FailureKind, e: impl std::fmt::Display) -> SourceError {
    let p = path.display().to_string();
    let m = e.to_string();
    let message = m.strip_prefix(&format!("{p}: ")).map(str::to_string).unwrap_or(m);
    SourceError::file(p, kind, message)
}

/// The message of a file over the byte limit.
pub(crate) fn over_limit(size: u64, limits: &ImageLimits) -> String {
    format!("{size} bytes is larger than the limit of {} bytes", limits.max_bytes)
}

/// Whether a companion raster of `w` x `h` (depth, disparity, masks) has the aspect of its photo
/// of `w0` x `h0` within a pixel of rounding: scaled to the larger of the two, each side lands
/// within one pixel of the smaller one's (`|w h0 - h w0| <= max(W, H)` of the larger raster).
pub fn same_aspect(w: usize, h: usize, w0: usize, h0: usize) -> bool {
    let cross = (w as u128 * h0 as u128).abs_diff(h as u128 * w0 as u128);
    let larger = if w * h >= w0 * h0 { w.max(h) } else { w0.max(h0) };
    cross <= larger as u128
}

/// Checks a companion raster's shape against its photo's (as displayed, after its EXIF
/// orientation): the same aspect within a pixel of rounding ([`same_aspect`]), else the message
/// naming both shapes and the likely cause. `what` is `depth`, `disparity` or `masks`.
pub(crate) fn check_shape(what: &str, w: usize, h: usize, w0: usize, h0: usize) -> Result<(), String> {
    if same_aspect(w, h, w0, h0) {
        return Ok(());
    }
    let cause = if same_aspect(w, h, h0, w0) {
        "it is turned a quarter against the photo: depth and masks are taken in the orientation of the \
         photo as displayed (after its EXIF orientation), so make them from the upright photo, or check \
         that the photo's orientation tag is the one the depth was made for"
    } else {
        "it is of another view: a crop of the photo, or another photo's file"
    };
    Err(format!(
        "{what} is {w} x {h} but its photo is {w0} x {h0} (as displayed): the aspects differ by more than a \
         pixel of rounding, so it cannot be resized to the photo; {cause}"
    ))
}

/// Resizes a depth or disparity map `data` (w x h) to (w0 x h0) when the sizes differ:
/// bilinear on a surface, nearest across its edges and next to unknown values
/// ([`resize_depth`]). A map of another aspect is refused ([`check_shape`]).
pub(crate) fn fit(what: &str, data: Vec<f32>, w: usize, h: usize, w0: usize, h0: usize) -> Result<Vec<f32>, String> {
    if (w, h) == (w0, h0) {
        return Ok(data);
    }
    check_shape(what, w, h, w0, h0)?;
    Ok(resize_depth(&data, w, h, w0, h0))
}

/// Reads a depth file as (width, height, values).
pub fn read_depth(p: &Path, kind: DepthFile, limits: &ImageLimits) -> Result<(usize, usize, Vec<f32>), SourceError> {
    match kind {
        DepthFile::Npy => read_depth_npy(p, limits),
        DepthFile::Pfm => {
            let pfm =
                super::pfm::read_pfm(p, limits).map_err(|e| file_err(p, e.kind.in_part(FailureKind::Depth), e))?;
            if pfm.channels != 1 {
                let m = "a colour PFM (PF) cannot be read as depth; expected a one-channel Pf";
                return Err(file_err(p, FailureKind::Depth, m));
            }
            Ok((pfm.width, pfm.height, pfm.data))
        }
        DepthFile::Png16 => load_depth_png16_with_limits(p, limits)
            .map_err(|e| file_err(p, e.failure_kind().in_part(FailureKind::Depth), e)),
    }
}

/// Reads a float (or integer) `.npy` depth of shape `[H, W]`, `[1, H, W]`, `[H, W, 1]` or
/// `[1, 1, H, W]`, under the limits (file size, then dimensions).
pub fn read_depth_npy(p: &Path, limits: &ImageLimits) -> Result<(usize, usize, Vec<f32>), SourceError> {
    let size = std::fs::metadata(p).map_err(|e| io_err(p, &e, FailureKind::Depth))?.len();
    if size > limits.max_bytes {
        return Err(file_err(p, FailureKind::TooLarge, over_limit(size, limits)));
    }
    let not_valid = |e: std::io::Error| {
        if e.kind() == std::io::ErrorKind::NotFound {
            io_err(p, &e, FailureKind::Depth)
        } else {
            file_err(p, FailureKind::Depth, not_a_depth(&e))
        }
    };
    let mut f = std::fs::File::open(p).map_err(not_valid)?;
    crate::io::npy::check_header(&mut f, size).map_err(not_valid)?;
    std::io::Seek::rewind(&mut f).map_err(not_valid)?;
    let npy = npyz::NpyFile::new(std::io::BufReader::new(f)).map_err(not_valid)?;
    // the shape from the header against the limits before any data is read
    depth_dims(npy.shape(), limits).map_err(|(kind, m)| file_err(p, kind, m))?;
    let a = crate::io::npy::read_array(npy).map_err(not_valid)?;
    depth_from_array(a, limits).map_err(|(kind, m)| file_err(p, kind, m))
}

/// The message of a `.npy` that does not parse (the parser's own text made one printable line).
fn not_a_depth(e: &std::io::Error) -> String {
    format!("not a valid .npy depth: {}", crate::failure::printable(&e.to_string(), 300))
}

/// [`read_depth_npy`] for an `.npy` held in memory (errors without a name, with their kind).
pub fn depth_npy_from_bytes(
    bytes: &[u8],
    limits: &ImageLimits,
) -> Result<(usize, usize, Vec<f32>), (FailureKind, String)> {
    if bytes.len() as u64 > limits.max_bytes {
        return Err((FailureKind::TooLarge, over_limit(bytes.len() as u64, limits)));
    }
    crate::io::npy::check_header(&mut &bytes[..], bytes.len() as u64)
        .map_err(|e| (FailureKind::Depth, not_a_depth(&e)))?;
    let npy = npyz::NpyFile::new(bytes).map_err(|e| (FailureKind::Depth, not_a_depth(&e)))?;
    // the shape from the header against the limits before any data is read
    depth_dims(npy.shape(), limits)?;
    let a = crate::io::npy::read_array(npy).map_err(|e| (FailureKind::Depth, not_a_depth(&e)))?;
    depth_from_array(a, limits)
}

/// A depth array's shape checked (`[H, W]`, `[1, H, W]`, `[H, W, 1]`, `[1, 1, H, W]`) against the
/// limits, as (width, height, values).
fn depth_from_array(
    a: crate::io::npy::Array,
    limits: &ImageLimits,
) -> Result<(usize, usize, Vec<f32>), (FailureKind, String)> {
    let (w, h) = depth_dims(&a.shape, limits)?;
    Ok((w, h, a.data.into_iter().map(|v| v as f32).collect()))
}

/// A depth array's (width, height) from its shape, checked against the limits.
fn depth_dims(shape: &[u64], limits: &ImageLimits) -> Result<(usize, usize), (FailureKind, String)> {
    let (h, w) = match shape {
        [h, w] | [1, h, w] | [h, w, 1] | [1, 1, h, w] => (*h, *w),
        s => {
            let m = format!("depth array has shape {s:?}, expected [H, W] (or [1, H, W], [H, W, 1], [1, 1, H, W])");
            return Err((FailureKind::Depth, m));
        }
    };
    let dims_ok = matches!((u32::try_from(w), u32::try_from(h)), (Ok(w), Ok(h)) if w > 0 && h > 0 && limits.check_dimensions(w, h));
    if !dims_ok {
        return Err((FailureKind::TooLarge, format!("depth of {w} x {h} pixels is empty or too large ({limits})")));
    }
    Ok((w as usize, h as usize))
}

/// Reads a grey disparity PNG as values in [0, 1]: 8-bit / 255, 16-bit / 65535 (alpha ignored;
/// an RGB PNG is accepted when it is grey, R = G = B).
pub fn read_disparity_png(p: &Path, limits: &ImageLimits) -> Result<(usize, usize, Vec<f32>), SourceError> {
    let img = decode_file(p, limits).map_err(|e| file_err(p, e.failure_kind().in_part(FailureKind::Depth), e))?;
    disparity_from_image(&img).map_err(|m| file_err(p, FailureKind::Depth, m))
}

/// [`read_disparity_png`] for a PNG held in memory, named `name` in errors.
pub fn disparity_png_from_bytes(
    bytes: &[u8],
    name: &str,
    limits: &ImageLimits,
) -> Result<(usize, usize, Vec<f32>), SourceError> {
    let p = Path::new(name);
    let img = crate::io::image::decode_bytes(bytes, p, limits)
        .map_err(|e| file_err(p, e.failure_kind().in_part(FailureKind::Depth), e))?;
    disparity_from_image(&img).map_err(|m| file_err(p, FailureKind::Depth, m))
}

fn disparity_from_image(img: &DynamicImage) -> Result<(usize, usize, Vec<f32>), String> {
    let (w, h) = (img.width() as usize, img.height() as usize);
    fn grey<T: Copy + Into<f32> + PartialEq>(raw: &[T], ch: usize, max: f32) -> Option<Vec<f32>> {
        let mut out = Vec::with_capacity(raw.len() / ch);
        for px in raw.chunks_exact(ch) {
            if ch >= 3 && (px[0] != px[1] || px[1] != px[2]) {
                return None;
            }
            out.push(px[0].into() / max);
        }
        Some(out)
    }
    let data = match img {
        DynamicImage::ImageLuma8(b) => grey(b.as_raw(), 1, 255.0),
        DynamicImage::ImageLumaA8(b) => grey(b.as_raw(), 2, 255.0),
        DynamicImage::ImageRgb8(b) => grey(b.as_raw(), 3, 255.0),
        DynamicImage::ImageRgba8(b) => grey(b.as_raw(), 4, 255.0),
        DynamicImage::ImageLuma16(b) => grey(b.as_raw(), 1, 65535.0),
        DynamicImage::ImageLumaA16(b) => grey(b.as_raw(), 2, 65535.0),
        DynamicImage::ImageRgb16(b) => grey(b.as_raw(), 3, 65535.0),
        DynamicImage::ImageRgba16(b) => grey(b.as_raw(), 4, 65535.0),
        _ => None,
    };
    data.map(|d| (w, h, d)).ok_or_else(|| {
        format!("a {:?} image is not a grey disparity map (expected an 8- or 16-bit grey PNG)", img.color())
    })
}

/// Resizes an RGB image with the `image` crate's triangle filter (bilinear when enlarging,
/// antialiased when shrinking).
pub fn resize_rgb(img: RgbImage, width: usize, height: usize) -> RgbImage {
    if (img.width, img.height) == (width, height) {
        return img;
    }
    let buf = ::image::Rgb32FImage::from_raw(img.width as u32, img.height as u32, img.data)
        .expect("RgbImage holds width * height * 3 values");
    let out = ::image::imageops::resize(&buf, width as u32, height as u32, ::image::imageops::FilterType::Triangle);
    RgbImage { width, height, data: out.into_raw().into_iter().map(|v| v.clamp(0.0, 1.0)).collect() }
}
