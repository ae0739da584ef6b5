//! PNG/JPEG/WebP decoding and PNG encoding with size limits: photos to f32 RGB in [0, 1] as displayed
//! (their EXIF orientation applied), 16-bit depth PNGs, image headers (displayed size,
//! orientation) without decoding, and PNG writers for RGB and grayscale results.
//!
//! Limits are checked against the file size and the dimensions in the image header before any
//! pixel buffer is allocated, so a decompression bomb (a small file whose header promises a huge
//! image) is refused cheaply.

use ::image::codecs::png::PngEncoder;
use ::image::{DynamicImage, ExtendedColorType, ImageDecoder, ImageEncoder, ImageFormat};
use std::fs::File;
use std::io::{self, BufRead, BufReader, BufWriter, Cursor, Read, Seek, Write};
use std::path::{Path, PathBuf};

use super::scaled::{decode_jpeg_scaled, decode_scale, jpeg_scalable, scaled_side, ScaledError};
use crate::failure::FailureKind;

/// An RGB image, H x W x 3 values in [0, 1], row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct RgbImage {
    pub width: usize,
    pub height: usize,
    pub data: Vec<f32>,
}

/// The name given to in-memory sources in errors.
pub const MEMORY_SOURCE: &str = "<memory>";

/// Size limits applied before decoding.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ImageLimits {
    /// Largest accepted width in pixels.
    pub max_width: u32,
    /// Largest accepted height in pixels.
    pub max_height: u32,
    /// Largest accepted width x height.
    pub max_pixels: u64,
    /// Largest accepted encoded size (file or byte buffer) in bytes.
    pub max_bytes: u64,
}

impl Default for ImageLimits {
    /// 8192 x 8192 at most, 40 megapixels, 256 MiB encoded.
    fn default() -> Self {
        ImageLimits { max_width: 8192, max_height: 8192, max_pixels: 40_000_000, max_bytes: 256 << 20 }
    }
}

impl std::fmt::Display for ImageLimits {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "at most {} x {}, {} pixels, {} bytes",
            self.max_width, self.max_height, self.max_pixels, self.max_bytes
        )
    }
}

impl ImageLimits {
    /// Checks decoded dimensions against the limits.
    pub fn check_dimensions(&self, width: u32, height: u32) -> bool {
        width <= self.max_width && height <= self.max_height && u64::from(width) * u64::from(height) <= self.max_pixels
    }

    /// The equivalent limits of the `image` crate; the allocation budget covers the largest
    /// accepted image at 8 bytes per pixel (RGBA16) plus decoder working memory.
    fn to_image_limits(self) -> ::image::Limits {
        let mut l = ::image::Limits::default();
        l.max_image_width = Some(self.max_width);
        l.max_image_height = Some(self.max_height);
        l.max_alloc = Some(self.max_pixels.saturating_mul(8).saturating_add(64 << 20));
        l
    }
}

/// Errors of image reading and writing; each names the file (or [`MEMORY_SOURCE`]).
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    #[error("{}: file not found", .path.display())]
    NotFound { path: PathBuf },
    #[error("{}: {source}", .path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: io::Error,
    },
    #[error("{}: unsupported image: {reason}", .path.display())]
    Unsupported { path: PathBuf, reason: String },
    #[error("{}: corrupt or truncated image: {reason}", .path.display())]
    Corrupt { path: PathBuf, reason: String },
    /// The data ends early (a truncated JPEG or PNG).
    #[error("{}: corrupt or truncated image: {reason}", .path.display())]
    Truncated { path: PathBuf, reason: String },
    #[error("{}: image of {width} x {height} pixels is too large ({limits})", .path.display())]
    TooLarge { path: PathBuf, width: u64, height: u64, limits: ImageLimits },
    /// A JPEG over the limits even at the reduced scale it is decoded at ([`load_photo`]).
    #[error(
        "{}: image of {width} x {height} pixels is too large even decoded at {eighths}/8 scale, {scaled_width} x \
         {scaled_height} ({limits})",
        .path.display()
    )]
    ScaledTooLarge {
        path: PathBuf,
        width: u64,
        height: u64,
        eighths: u32,
        scaled_width: u64,
        scaled_height: u64,
        limits: ImageLimits,
    },
    #[error("{}: {bytes} bytes is larger than the limit of {max_bytes} bytes", .path.display())]
    FileTooLarge { path: PathBuf, bytes: u64, max_bytes: u64 },
    #[error("{}: invalid image buffer: {reason}", .path.display())]
    InvalidInput { path: PathBuf, reason: String },
}

impl ImageError {
    /// What kind of source failure this is: [`FailureKind::TooLarge`] over a limit,
    /// [`FailureKind::Truncated`] for data that ends early, [`FailureKind::Decode`] otherwise.
    pub fn failure_kind(&self) -> FailureKind {
        match self {
            ImageError::TooLarge { .. } | ImageError::ScaledTooLarge { .. } | ImageError::FileTooLarge { .. } => {
                FailureKind::TooLarge
            }
            ImageError::Truncated { .. } => FailureKind::Truncated,
            _ => FailureKind::Decode,
        }
    }
}

impl From<ImageError> for io::Error {
    fn from(e: ImageError) -> io::Error {
        let kind = match &e {
            ImageError::NotFound { .. } => io::ErrorKind::NotFound,
            ImageError::Io { source, .. } => source.kind(),
            ImageError::InvalidInput { .. } => io::ErrorKind::InvalidInput,
            _ => io::ErrorKind::InvalidData,
        };
        io::Error::new(kind, e)
    }
}

/// A decoder's message as one printable line (some end in a newline or quote raw bytes).
fn reason(e: &dyn std::fmt::Display) -> String {
    crate::failure::printable(e.to_string().trim_end(), 300)
}

fn map_decode_error(path: &Path, e: ::image::ImageError) -> ImageError {
    use ::image::ImageError as E;
    let path = path.to_path_buf();
    match e {
        E::Unsupported(u) => ImageError::Unsupported { path, reason: reason(&u) },
        E::Decoding(d) => ImageError::Corrupt { path, reason: reason(&d) },
        E::Parameter(p) => ImageError::Corrupt { path, reason: reason(&p) },
        E::IoError(io) if io.kind() == io::ErrorKind::UnexpectedEof => {
            ImageError::Truncated { path, reason: format!("unexpected end of data ({})", reason(&io)) }
        }
        E::IoError(io) => ImageError::Io { path, source: io },
        // a header within our limits whose decoding still needs more memory than budgeted
        E::Limits(l) => ImageError::Corrupt { path, reason: reason(&l) },
        E::Encoding(x) => ImageError::Corrupt { path, reason: reason(&x) },
    }
}

/// The advice for a HEIC/HEIF photo (the iPhone's default): no maintained pure-Rust decoder
/// reads them, so they are named and left out.
pub const HEIC_ADVICE: &str = "HEIC: not supported, convert to JPEG (e.g. `heif-convert IMG.HEIC IMG.jpg`, or \
                               set the phone's camera format to Most Compatible)";

/// Whether a file name has a HEIC/HEIF extension (`.heic`, `.heif`, `.hif`, any case).
pub fn is_heif(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| ["heic", "heif", "hif"].iter().any(|x| e.eq_ignore_ascii_case(x)))
}

/// What an image's header tells before any pixel is decoded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ImageHeader {
    /// The size as displayed: after the orientation (sides swapped for the quarter turns).
    pub width: u32,
    pub height: u32,
    /// The size as stored in the file, before the orientation.
    pub stored_width: u32,
    pub stored_height: u32,
    /// The EXIF orientation (1 to 8; 1 when the file carries none): the turn or mirror a viewer
    /// applies to show the photo upright, and the decoders of this module apply.
    pub orientation: u8,
    /// A sequential JPEG of one or three components: decodable at 1/2, 1/4 or 1/8 scale
    /// ([`load_photo`], [`super::scaled`]).
    pub scalable: bool,
}

impl ImageHeader {
    /// Whether the file carries an orientation other than the identity (its pixels are turned
    /// or mirrored when decoded).
    pub fn is_oriented(&self) -> bool {
        self.orientation != 1
    }
}

/// Whether an EXIF orientation swaps width and height (the quarter turns, 5 to 8).
fn swaps_sides(orientation: ::image::metadata::Orientation) -> bool {
    orientation.to_exif() >= 5
}

/// Opens a PNG, JPEG or WebP stream's decoder, checks its header against `limits` (unless
/// `check` is false: the caller checks the size it decodes at) and reads its orientation; with
/// `decode`, decodes its pixels too (as stored: the caller orients them).
fn open_reader<R: BufRead + Seek>(
    reader: R,
    path: &Path,
    limits: &ImageLimits,
    decode: bool,
    check: bool,
) -> Result<(ImageHeader, Option<DynamicImage>), ImageError> {
    let mut reader = ::image::ImageReader::new(reader)
        .with_guessed_format()
        .map_err(|source| ImageError::Io { path: path.to_path_buf(), source })?;
    match reader.format() {
        Some(ImageFormat::Png | ImageFormat::Jpeg | ImageFormat::WebP) => {}
        Some(other) => {
            return Err(ImageError::Unsupported {
                path: path.to_path_buf(),
                reason: format!("{other:?} images are not supported; use PNG, JPEG or WebP"),
            })
        }
        None if is_heif(path) => {
            return Err(ImageError::Unsupported { path: path.to_path_buf(), reason: HEIC_ADVICE.into() })
        }
        None => {
            return Err(ImageError::Unsupported {
                path: path.to_path_buf(),
                reason: "not a PNG, JPEG or WebP file (unrecognised signature)".into(),
            })
        }
    }
    // read the header only, without dimension limits, to report the promised size ourselves
    reader.no_limits();
    let mut decoder = reader.into_decoder().map_err(|e| map_decode_error(path, e))?;
    let (width, height) = decoder.dimensions();
    if check && !limits.check_dimensions(width, height) {
        return Err(ImageError::TooLarge {
            path: path.to_path_buf(),
            width: width.into(),
            height: height.into(),
            limits: *limits,
        });
    }
    let orientation = decoder.orientation().map_err(|e| map_decode_error(path, e))?;
    let (dw, dh) = if swaps_sides(orientation) { (height, width) } else { (width, height) };
    let header = ImageHeader {
        width: dw,
        height: dh,
        stored_width: width,
        stored_height: height,
        orientation: orientation.to_exif(),
        scalable: false,
    };
    if !decode {
        return Ok((header, None));
    }
    let mut il = limits.to_image_limits();
    il.reserve(decoder.total_bytes()).map_err(|e| map_decode_error(path, e))?;
    decoder.set_limits(il).map_err(|e| map_decode_error(path, e))?;
    let img = DynamicImage::from_decoder(decoder).map_err(|e| map_decode_error(path, e))?;
    Ok((header, Some(img)))
}

/// Decodes a PNG, JPEG or WebP stream after checking its header against `limits`; with `orient`, the
/// pixels are turned to the orientation the file asks for (EXIF in JPEG, `eXIf` in PNG), so the
/// result is the image as a viewer displays it.
fn decode_reader<R: BufRead + Seek>(
    reader: R,
    path: &Path,
    limits: &ImageLimits,
    orient: bool,
) -> Result<DynamicImage, ImageError> {
    let (header, img) = open_reader(reader, path, limits, true, true)?;
    let mut img = img.ok_or_else(|| ImageError::Corrupt { path: path.to_path_buf(), reason: "no pixels".into() })?;
    if orient {
        if let Some(o) = ::image::metadata::Orientation::from_exif(header.orientation) {
            img.apply_orientation(o);
        }
    }
    Ok(img)
}

/// Reads an image file's header (size, orientation) under `limits`, without decoding its
/// pixels: the file size, a JPEG's completeness and the header's dimensions are checked as the
/// decoders check them.
pub fn read_header(path: &Path, limits: &ImageLimits) -> Result<ImageHeader, ImageError> {
    let bytes = read_file(path, limits)?;
    read_header_bytes(&bytes, path, limits)
}

/// [`read_header`] for an encoded image held in memory, named `path` in errors.
pub fn read_header_bytes(bytes: &[u8], path: &Path, limits: &ImageLimits) -> Result<ImageHeader, ImageError> {
    check_encoded(bytes, path, limits)?;
    let (header, _) = open_reader(Cursor::new(bytes), path, limits, false, true)?;
    Ok(ImageHeader { scalable: jpeg_scalable(bytes), ..header })
}

/// [`read_header`] for a photo that is brought to a smaller size ([`load_photo`]): a sequential
/// JPEG ([`ImageHeader::scalable`]) is checked against `limits` at the smallest size it decodes
/// at (1/8 of each side), every other image at its size as stored.
pub fn read_photo_header(path: &Path, limits: &ImageLimits) -> Result<ImageHeader, ImageError> {
    let bytes = read_file(path, limits)?;
    let header = unchecked_header(&bytes, path, limits)?;
    check_photo(&header, if header.scalable { 1 } else { 8 }, path, limits)?;
    Ok(header)
}

/// The header of an image's `bytes`, its file size and completeness checked but not its
/// dimensions.
fn unchecked_header(bytes: &[u8], path: &Path, limits: &ImageLimits) -> Result<ImageHeader, ImageError> {
    check_encoded(bytes, path, limits)?;
    let (header, _) = open_reader(Cursor::new(bytes), path, limits, false, false)?;
    Ok(ImageHeader { scalable: jpeg_scalable(bytes), ..header })
}

/// Checks a photo's size decoded at `eighths` / 8 scale against `limits`.
fn check_photo(header: &ImageHeader, eighths: u32, path: &Path, limits: &ImageLimits) -> Result<(), ImageError> {
    let (sw, sh) = (scaled_side(header.stored_width, eighths), scaled_side(header.stored_height, eighths));
    if limits.check_dimensions(sw, sh) {
        return Ok(());
    }
    let (width, height) = (header.stored_width.into(), header.stored_height.into());
    Err(if eighths == 8 {
        ImageError::TooLarge { path: path.to_path_buf(), width, height, limits: *limits }
    } else {
        ImageError::ScaledTooLarge {
            path: path.to_path_buf(),
            width,
            height,
            eighths,
            scaled_width: sw.into(),
            scaled_height: sh.into(),
            limits: *limits,
        }
    })
}

/// The scale, in eighths, a photo with `header` is decoded at to cover `need` (width, height as
/// displayed; `None`: kept at its size): 8 (its full size) unless it is a sequential JPEG
/// ([`ImageHeader::scalable`]) brought to a smaller size, else the smallest of 1/8, 1/4, 1/2
/// that covers `need` ([`decode_scale`]).
pub fn photo_scale(header: &ImageHeader, need: Option<(usize, usize)>) -> u32 {
    let Some((nw, nh)) = need.filter(|_| header.scalable) else { return 8 };
    let side = |v: usize| u32::try_from(v).unwrap_or(u32::MAX);
    // `need` is as displayed; the scale applies to the sides as stored
    let swapped = (header.width, header.height) != (header.stored_width, header.stored_height);
    let stored_need = if swapped { (side(nh), side(nw)) } else { (side(nw), side(nh)) };
    decode_scale((header.stored_width, header.stored_height), stored_need)
}

/// Decodes a photo that is brought to cover `need` (width, height as displayed; `None`: kept at
/// its size) as small as its format allows: a sequential JPEG at the smallest DCT scale that
/// covers `need` ([`photo_scale`]), every other image whole. The limits apply to the size it is
/// decoded at; the file size is checked before reading. The EXIF orientation is applied (as
/// [`load_rgb`]). Gives the image and the photo's header (its full size).
pub fn load_photo(
    path: &Path,
    limits: &ImageLimits,
    need: Option<(usize, usize)>,
) -> Result<(RgbImage, ImageHeader), ImageError> {
    let bytes = read_file(path, limits)?;
    let header = unchecked_header(&bytes, path, limits)?;
    let eighths = photo_scale(&header, need);
    check_photo(&header, eighths, path, limits)?;
    if eighths == 8 {
        return Ok((decode_bytes(&bytes, path, limits).map(dynamic_to_rgb)?, header));
    }
    let (sw, sh) = (scaled_side(header.stored_width, eighths), scaled_side(header.stored_height, eighths));
    let max = usize::try_from(u64::from(sw) * u64::from(sh) * 3).unwrap_or(usize::MAX);
    let mut img = decode_jpeg_scaled(&bytes, eighths, max).map_err(|e| match e {
        ScaledError::Corrupt(reason) => ImageError::Corrupt { path: path.to_path_buf(), reason },
        ScaledError::Unsupported(reason) => ImageError::Unsupported { path: path.to_path_buf(), reason },
    })?;
    drop(bytes);
    if let Some(o) = ::image::metadata::Orientation::from_exif(header.orientation) {
        img.apply_orientation(o);
    }
    Ok((dynamic_to_rgb(img), header))
}

/// Reads a file whole, refusing files over `limits.max_bytes` before reading them.
fn read_file(path: &Path, limits: &ImageLimits) -> Result<Vec<u8>, ImageError> {
    let open_err = |source: io::Error| {
        if source.kind() == io::ErrorKind::NotFound {
            ImageError::NotFound { path: path.to_path_buf() }
        } else {
            ImageError::Io { path: path.to_path_buf(), source }
        }
    };
    let file = File::open(path).map_err(open_err)?;
    let meta = file.metadata().map_err(open_err)?;
    if !meta.is_file() {
        return Err(ImageError::Io {
            path: path.to_path_buf(),
            source: io::Error::new(io::ErrorKind::InvalidInput, "not a regular file"),
        });
    }
    if meta.len() > limits.max_bytes {
        return Err(ImageError::FileTooLarge {
            path: path.to_path_buf(),
            bytes: meta.len(),
            max_bytes: limits.max_bytes,
        });
    }
    // read whole (the JPEG decoder buffers the whole stream anyway), at most max_bytes + 1
    let mut bytes = Vec::with_capacity(meta.len() as usize);
    BufReader::new(file)
        .take(limits.max_bytes.saturating_add(1))
        .read_to_end(&mut bytes)
        .map_err(|source| ImageError::Io { path: path.to_path_buf(), source })?;
    Ok(bytes)
}

/// Opens a file and decodes it, refusing files over `limits.max_bytes` before reading them;
/// the pixels are oriented as the file asks ([`decode_bytes`]).
pub(crate) fn decode_file(path: &Path, limits: &ImageLimits) -> Result<DynamicImage, ImageError> {
    let bytes = read_file(path, limits)?;
    decode_bytes(&bytes, path, limits)
}

/// [`decode_file`] with the pixels as stored, whatever orientation the file carries (rasters
/// whose values are directions, such as flow, cannot be turned as pixels).
pub(crate) fn decode_file_as_stored(path: &Path, limits: &ImageLimits) -> Result<DynamicImage, ImageError> {
    let bytes = read_file(path, limits)?;
    check_encoded(&bytes, path, limits)?;
    decode_reader(Cursor::new(&bytes[..]), path, limits, false)
}

/// The checks on encoded bytes before their header is read: the byte size and a JPEG's
/// completeness ([`jpeg_truncation`]).
fn check_encoded(bytes: &[u8], path: &Path, limits: &ImageLimits) -> Result<(), ImageError> {
    if bytes.len() as u64 > limits.max_bytes {
        return Err(ImageError::FileTooLarge {
            path: path.to_path_buf(),
            bytes: bytes.len() as u64,
            max_bytes: limits.max_bytes,
        });
    }
    if let Some(reason) = jpeg_truncation(bytes) {
        return Err(ImageError::Truncated { path: path.to_path_buf(), reason });
    }
    Ok(())
}

/// Decodes an encoded PNG, JPEG or WebP held in memory, named `path` in errors: the byte size, a
/// JPEG's completeness ([`jpeg_truncation`]) and the header's dimensions are checked before any
/// pixel buffer is allocated. The pixels are turned to the orientation the file carries (EXIF
/// in JPEG, `eXIf` in PNG): the image as a viewer displays it, for photos, masks and depth alike.
pub(crate) fn decode_bytes(bytes: &[u8], path: &Path, limits: &ImageLimits) -> Result<DynamicImage, ImageError> {
    check_encoded(bytes, path, limits)?;
    decode_reader(Cursor::new(bytes), path, limits, true)
}

/// The bytes of an image's start that [`orientation_of_prefix`] needs at most: a JPEG's EXIF
/// segment lies in its first 64 KiB.
pub const ORIENTATION_PREFIX: usize = 1 << 16;

/// The EXIF orientation (1 to 8) an encoded image carries, from its first bytes alone (a JPEG's
/// `APP1` Exif segment, a PNG's `eXIf` chunk before its pixel data); 1 when it carries none, the
/// tag is not valid, or the bytes are neither. It reads the tag the decoders of this module read
/// and apply, without decoding anything: for sources that fingerprint their items without opening
/// them (shards, uploads).
pub fn orientation_of_prefix(bytes: &[u8]) -> u8 {
    let from_chunk = |chunk: &[u8]| {
        ::image::metadata::Orientation::from_exif_chunk(chunk).map_or(1, ::image::metadata::Orientation::to_exif)
    };
    if bytes.starts_with(&[0xFF, 0xD8]) {
        let mut pos = 2usize;
        while pos + 4 <= bytes.len() && bytes[pos] == 0xFF {
            let code = bytes[pos + 1];
            if code == 0xFF {
                pos += 1;
                continue;
            }
            if code == 0xDA || code == 0xD9 {
                break;
            }
            let len = usize::from(u16::from_be_bytes([bytes[pos + 2], bytes[pos + 3]]));
            let body = &bytes[(pos + 4).min(bytes.len())..(pos + 2 + len).min(bytes.len())];
            if code == 0xE1 && body.starts_with(b"Exif\0\0") {
                return from_chunk(&body[6..]);
            }
            if len < 2 {
                break;
            }
            pos += 2 + len;
        }
    } else if bytes.starts_with(b"\x89PNG\r\n\x1a\n") {
        let mut pos = 8usize;
        while pos + 8 <= bytes.len() {
            let len = u32::from_be_bytes([bytes[pos], bytes[pos + 1], bytes[pos + 2], bytes[pos + 3]]) as usize;
            let kind = &bytes[pos + 4..pos + 8];
            if kind == b"IDAT" {
                break;
            }
            if kind == b"eXIf" {
                return from_chunk(&bytes[(pos + 8).min(bytes.len())..(pos + 8).saturating_add(len).min(bytes.len())]);
            }
            pos = pos.saturating_add(12).saturating_add(len);
        }
    }
    1
}

/// Why a JPEG stream is truncated (`None` when it is complete or not a JPEG).
///
/// The decoder is lenient (it fills what is missing of a truncated JPEG with grey and reports
/// success), so completeness is checked here: the marker segments are walked from the start
/// (by their lengths, over the entropy-coded data of each scan, where `FF 00` stuffing and
/// restart markers are skipped) until the end-of-image marker `FF D9`. Running off the end first
/// means truncation. Anything else malformed is left to the decoder to report. Bytes after the
/// end-of-image marker (camera trailers, appended videos) are allowed.
pub fn jpeg_truncation(bytes: &[u8]) -> Option<String> {
    if bytes.len() < 3 || bytes[0] != 0xFF || bytes[1] != 0xD8 || bytes[2] != 0xFF {
        return None;
    }
    let truncated = |what: &str| Some(format!("truncated JPEG: the data ends {what} before the end-of-image marker"));
    let n = bytes.len();
    let mut pos = 2usize;
    loop {
        // a marker: 0xFF (any number of fill bytes), then its code
        if pos >= n {
            return truncated("between segments");
        }
        if bytes[pos] != 0xFF {
            return None; // malformed: the decoder reports it (or copes)
        }
        while pos < n && bytes[pos] == 0xFF {
            pos += 1;
        }
        if pos >= n {
            return truncated("in a marker");
        }
        let code = bytes[pos];
        pos += 1;
        match code {
            0xD9 => return None,
            0x01 | 0xD0..=0xD7 => continue,
            0x00 => return None,
            _ => {}
        }
        if pos + 2 > n {
            return truncated("in a segment header");
        }
        let len = usize::from(u16::from_be_bytes([bytes[pos], bytes[pos + 1]]));
        if len < 2 {
            return None;
        }
        pos += len;
        if pos > n {
            return truncated("inside a segment");
        }
        if code == 0xDA {
            // entropy-coded data up to the next marker that is not stuffing or a restart
            loop {
                match bytes[pos..].iter().position(|&b| b == 0xFF) {
                    None => return truncated("inside the image data"),
                    Some(off) => {
                        let p = pos + off;
                        match bytes.get(p + 1) {
                            None => return truncated("inside the image data"),
                            Some(0x00 | 0xD0..=0xD7) => pos = p + 2,
                            Some(0xFF) => pos = p + 1,
                            Some(_) => {
                                pos = p;
                                break;
                            }
                        }
                    }
                }
            }
        }
    }
}

/// Converts interleaved samples with `channels` per pixel to RGB f32 (gray is replicated, alpha
/// dropped), each value divided by `max`.
fn to_rgb_f32<T: Copy + Into<f32>>(raw: &[T], channels: usize, max: f32) -> Vec<f32> {
    if channels == 3 {
        // one pass over the whole buffer (the compiler vectorises it)
        return raw.iter().map(|&c| c.into() / max).collect();
    }
    let mut out = Vec::with_capacity(raw.len() / channels * 3);
    for px in raw.chunks_exact(channels) {
        if channels < 3 {
            let g = px[0].into() / max;
            out.extend_from_slice(&[g, g, g]);
        } else {
            out.extend(px[..3].iter().map(|&c| c.into() / max));
        }
    }
    out
}

fn dynamic_to_rgb(img: DynamicImage) -> RgbImage {
    let (width, height) = (img.width() as usize, img.height() as usize);
    let data = match &img {
        DynamicImage::ImageLuma8(b) => to_rgb_f32(b.as_raw(), 1, 255.0),
        DynamicImage::ImageLumaA8(b) => to_rgb_f32(b.as_raw(), 2, 255.0),
        DynamicImage::ImageRgb8(b) => to_rgb_f32(b.as_raw(), 3, 255.0),
        DynamicImage::ImageRgba8(b) => to_rgb_f32(b.as_raw(), 4, 255.0),
        DynamicImage::ImageLuma16(b) => to_rgb_f32(b.as_raw(), 1, 65535.0),
        DynamicImage::ImageLumaA16(b) => to_rgb_f32(b.as_raw(), 2, 65535.0),
        DynamicImage::ImageRgb16(b) => to_rgb_f32(b.as_raw(), 3, 65535.0),
        DynamicImage::ImageRgba16(b) => to_rgb_f32(b.as_raw(), 4, 65535.0),
        other => other.to_rgb32f().into_raw().into_iter().map(|v| v.clamp(0.0, 1.0)).collect(),
    };
    RgbImage { width, height, data }
}

/// Decodes a PNG, JPEG or WebP file (8 or 16 bit; gray, gray+alpha, RGB or RGBA) to RGB in [0, 1];
/// alpha is dropped. The file size and the header's dimensions are checked against `limits`
/// before any pixel buffer is allocated. The EXIF orientation is applied: the result is the
/// photo as a viewer displays it (a phone photo stored sideways with orientation 6 comes out
/// upright, its width and height swapped).
pub fn load_rgb(path: &Path, limits: &ImageLimits) -> Result<RgbImage, ImageError> {
    decode_file(path, limits).map(dynamic_to_rgb)
}

/// [`load_rgb`] for an encoded image held in memory (errors name it [`MEMORY_SOURCE`]).
pub fn load_rgb_from_bytes(bytes: &[u8], limits: &ImageLimits) -> Result<RgbImage, ImageError> {
    let path = Path::new(MEMORY_SOURCE);
    if bytes.len() as u64 > limits.max_bytes {
        return Err(ImageError::FileTooLarge {
            path: path.to_path_buf(),
            bytes: bytes.len() as u64,
            max_bytes: limits.max_bytes,
        });
    }
    decode_bytes(bytes, path, limits).map(dynamic_to_rgb)
}

/// [`load_rgb_from_bytes`] with a name for the errors (e.g. `shard.tar:key.jpg`).
pub fn load_rgb_from_bytes_named(bytes: &[u8], name: &str, limits: &ImageLimits) -> Result<RgbImage, ImageError> {
    decode_bytes(bytes, Path::new(name), limits).map(dynamic_to_rgb)
}

/// Reads a 16-bit grayscale PNG (depth maps, e.g. millimetres) as its raw values 0..=65535,
/// returning `(width, height, values)` in row-major order. Anything other than a 16-bit
/// single-channel image is refused as [`ImageError::Unsupported`]. Uses the default limits.
pub fn load_depth_png16(path: &Path) -> Result<(usize, usize, Vec<f32>), ImageError> {
    load_depth_png16_with_limits(path, &ImageLimits::default())
}

/// [`load_depth_png16`] with explicit limits.
pub fn load_depth_png16_with_limits(path: &Path, limits: &ImageLimits) -> Result<(usize, usize, Vec<f32>), ImageError> {
    match decode_file(path, limits)? {
        DynamicImage::ImageLuma16(b) => {
            let (w, h) = (b.width() as usize, b.height() as usize);
            Ok((w, h, b.into_raw().into_iter().map(f32::from).collect()))
        }
        other => Err(ImageError::Unsupported {
            path: path.to_path_buf(),
            reason: format!("expected a 16-bit grayscale PNG for depth, found {:?}", other.color()),
        }),
    }
}

/// Quantises [0, 1] values to bytes: clamped, rounded to nearest; NaN becomes 0.
pub fn rgb_to_u8(img: &RgbImage) -> Vec<u8> {
    img.data.iter().map(|&v| unit_to_u8(v)).collect()
}

/// Rounds every value to what an 8-bit PNG of the image holds, as [`load_rgb`] reads it back
/// (`rgb_to_u8(v) / 255`): saving the result with [`save_rgb_png`] and loading it gives the same
/// values bit for bit.
pub fn quantize_to_u8(img: &mut RgbImage) {
    for v in &mut img.data {
        *v = f32::from(unit_to_u8(*v)) / 255.0;
    }
}

#[inline]
fn unit_to_u8(v: f32) -> u8 {
    // `as` saturates and maps NaN to 0
    (v.clamp(0.0, 1.0) * 255.0).round() as u8
}

fn check_buffer(
    path: &Path,
    width: usize,
    height: usize,
    channels: usize,
    len: usize,
) -> Result<(u32, u32), ImageError> {
    let bad = |reason: String| ImageError::InvalidInput { path: path.to_path_buf(), reason };
    let (w, h) = match (u32::try_from(width), u32::try_from(height)) {
        (Ok(w), Ok(h)) if w > 0 && h > 0 => (w, h),
        _ => return Err(bad(format!("cannot encode a {width} x {height} image"))),
    };
    let need = width.checked_mul(height).and_then(|n| n.checked_mul(channels));
    if need != Some(len) {
        return Err(bad(format!(
            "{width} x {height} x {channels} needs {} values, the buffer holds {len}",
            width.saturating_mul(height).saturating_mul(channels)
        )));
    }
    Ok((w, h))
}

/// Encodes interleaved 8- or 16-bit samples as a PNG file.
pub(crate) fn write_png(
    path: &Path,
    width: u32,
    height: u32,
    bytes: &[u8],
    color: ExtendedColorType,
) -> Result<(), ImageError> {
    let io_err = |source: io::Error| ImageError::Io { path: path.to_path_buf(), source };
    let mut w = BufWriter::new(File::create(path).map_err(io_err)?);
    PngEncoder::new(&mut w).write_image(bytes, width, height, color).map_err(|e| match e {
        ::image::ImageError::IoError(source) => io_err(source),
        other => ImageError::InvalidInput { path: path.to_path_buf(), reason: other.to_string() },
    })?;
    w.flush().map_err(io_err)
}

/// Writes an RGB image as an 8-bit PNG (values clamped to [0, 1] and rounded, see
/// [`rgb_to_u8`]).
pub fn save_rgb_png(path: &Path, img: &RgbImage) -> Result<(), ImageError> {
    let (w, h) = check_buffer(path, img.width, img.height, 3, img.data.len())?;
    write_png(path, w, h, &rgb_to_u8(img), ExtendedColorType::Rgb8)
}

/// Writes H x W bytes as an 8-bit grayscale PNG.
pub fn save_gray_png(path: &Path, width: usize, height: usize, data: &[u8]) -> Result<(), ImageError> {
    let (w, h) = check_buffer(path, width, height, 1, data.len())?;
    write_png(path, w, h, data, ExtendedColorType::L8)
}

/// Writes H x W 16-bit values as a 16-bit grayscale PNG (the inverse of [`load_depth_png16`]).
pub fn save_gray16_png(path: &Path, width: usize, height: usize, data: &[u16]) -> Result<(), ImageError> {
    let (w, h) = check_buffer(path, width, height, 1, data.len())?;
    // the encoder takes native-endian bytes of the u16 samples
    let bytes: Vec<u8> = data.iter().flat_map(|v| v.to_ne_bytes()).collect();
    write_png(path, w, h, &bytes, ExtendedColorType::L16)
}

#[cfg(test)]
mod tests {
    use super::*;
    use ::image::codecs::jpeg::JpegEncoder;

    fn tmpdir(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("mpiflow-io-image-{}-{name}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    fn png_bytes(width: u32, height: u32, data: &[u8], color: ExtendedColorType) -> Vec<u8> {
        let mut v = Vec::new();
        PngEncoder::new(&mut v).write_image(data, width, height, color).unwrap();
        v
    }

    fn crc32(bytes: &[u8]) -> u32 {
        let mut crc = !0u32;
        for &b in bytes {
            crc ^= u32::from(b);
            for _ in 0..8 {
                crc = if crc & 1 != 0 { (crc >> 1) ^ 0xEDB8_8320 } else { crc >> 1 };
            }
        }
        !crc
    }

    /// A valid PNG (correct CRC) whose header claims `width` x `height` but holds one row.
    fn bomb_png(width: u32, height: u32) -> Vec<u8> {
        let mut v = png_bytes(1, 1, &[0], ExtendedColorType::L8);
        // signature (8) + length (4) + "IHDR" (4) + width + height
        v[16..20].copy_from_slice(&width.to_be_bytes());
        v[20..24].copy_from_slice(&height.to_be_bytes());
        let crc = crc32(&v[12..29]);
        v[29..33].copy_from_slice(&crc.to_be_bytes());
        v
    }

    #[test]
    fn png_8bit_rgb_roundtrip() {
        let data: Vec<u8> = (0..4 * 3 * 3).map(|i| (i * 7) as u8).collect();
        let img =
            load_rgb_from_bytes(&png_bytes(4, 3, &data, ExtendedColorType::Rgb8), &ImageLimits::default()).unwrap();
        assert_eq!((img.width, img.height), (4, 3));
        assert_eq!(rgb_to_u8(&img), data);
        assert_eq!(img.data[1], 7.0 / 255.0);
    }

    #[test]
    fn png_16bit_gray_and_rgba() {
        let vals: [u16; 2] = [0, 65535];
        let bytes: Vec<u8> = vals.iter().flat_map(|v| v.to_ne_bytes()).collect();
        let img =
            load_rgb_from_bytes(&png_bytes(2, 1, &bytes, ExtendedColorType::L16), &ImageLimits::default()).unwrap();
        assert_eq!(img.data, vec![0.0, 0.0, 0.0, 1.0, 1.0, 1.0]);

        let rgba16: Vec<u8> = [1000u16, 2000, 3000, 7].iter().flat_map(|v| v.to_ne_bytes()).collect();
        let img =
            load_rgb_from_bytes(&png_bytes(1, 1, &rgba16, ExtendedColorType::Rgba16), &ImageLimits::default()).unwrap();
        assert_eq!(img.data, vec![1000.0 / 65535.0, 2000.0 / 65535.0, 3000.0 / 65535.0]);

        let rgba8 = [10u8, 20, 30, 0];
        let img =
            load_rgb_from_bytes(&png_bytes(1, 1, &rgba8, ExtendedColorType::Rgba8), &ImageLimits::default()).unwrap();
        assert_eq!(rgb_to_u8(&img), vec![10, 20, 30]);
    }

    #[test]
    fn jpeg_decodes_close() {
        let data = vec![128u8; 16 * 16 * 3];
        let mut jpg = Vec::new();
        JpegEncoder::new_with_quality(&mut jpg, 95).write_image(&data, 16, 16, ExtendedColorType::Rgb8).unwrap();
        let img = load_rgb_from_bytes(&jpg, &ImageLimits::default()).unwrap();
        assert_eq!((img.width, img.height), (16, 16));
        let max = rgb_to_u8(&img).iter().map(|&v| (i32::from(v) - 128).abs()).max().unwrap();
        assert!(max <= 2, "jpeg error {max}");
    }

    #[test]
    fn errors_have_the_right_variants() {
        let lim = ImageLimits::default();
        let good = png_bytes(8, 8, &[50u8; 8 * 8 * 3], ExtendedColorType::Rgb8);

        let e = load_rgb_from_bytes(&good[..good.len() / 2], &lim).unwrap_err();
        assert!(matches!(e, ImageError::Truncated { .. }), "{e}");
        assert_eq!(e.failure_kind(), FailureKind::Truncated);

        let mut garbage_png = good[..8].to_vec();
        garbage_png.extend((0..200u32).map(|i| (i * 37 % 251) as u8));
        let e = load_rgb_from_bytes(&garbage_png, &lim).unwrap_err();
        assert!(matches!(e, ImageError::Corrupt { .. }), "{e}");
        assert_eq!(e.failure_kind(), FailureKind::Decode);

        let garbage: Vec<u8> = (0..300u32).map(|i| (i * 91 % 253) as u8).collect();
        let e = load_rgb_from_bytes(&garbage, &lim).unwrap_err();
        assert!(matches!(e, ImageError::Unsupported { .. }), "{e}");
        assert!(e.to_string().starts_with(MEMORY_SOURCE));

        let e = load_rgb_from_bytes(b"GIF89a\x01\x00\x01\x00\x00\x00\x00;", &lim).unwrap_err();
        assert!(matches!(e, ImageError::Unsupported { .. }), "{e}");
        assert!(e.to_string().contains("Gif"), "{e}");

        let e = load_rgb_from_bytes(&bomb_png(100_000, 100_000), &lim).unwrap_err();
        assert!(matches!(e, ImageError::TooLarge { width: 100_000, height: 100_000, .. }), "{e}");
        assert_eq!(e.failure_kind(), FailureKind::TooLarge);
        assert!(e.to_string().contains("100000 x 100000"), "{e}");

        // within the width and height limits but over the pixel budget
        let e = load_rgb_from_bytes(&bomb_png(8000, 8000), &lim).unwrap_err();
        assert!(matches!(e, ImageError::TooLarge { .. }), "{e}");

        // a small header but no data for it: corrupt, not a panic or a huge allocation
        let e = load_rgb_from_bytes(&bomb_png(4000, 4000), &lim).unwrap_err();
        assert!(matches!(e, ImageError::Corrupt { .. } | ImageError::Truncated { .. }), "{e}");

        let small = ImageLimits { max_pixels: 63, ..lim };
        let e = load_rgb_from_bytes(&good, &small).unwrap_err();
        assert!(matches!(e, ImageError::TooLarge { width: 8, height: 8, .. }), "{e}");

        let tiny = ImageLimits { max_bytes: 10, ..lim };
        let e = load_rgb_from_bytes(&good, &tiny).unwrap_err();
        assert!(matches!(e, ImageError::FileTooLarge { max_bytes: 10, .. }), "{e}");
    }

    #[test]
    fn file_errors_name_the_file() {
        let dir = tmpdir("errors");
        let missing = dir.join("missing.png");
        let e = load_rgb(&missing, &ImageLimits::default()).unwrap_err();
        assert!(matches!(e, ImageError::NotFound { .. }), "{e}");
        assert!(e.to_string().contains("missing.png"), "{e}");

        let big = dir.join("big.png");
        std::fs::write(&big, bomb_png(100_000, 100_000)).unwrap();
        let e = load_rgb(&big, &ImageLimits::default()).unwrap_err();
        assert!(matches!(e, ImageError::TooLarge { .. }), "{e}");
        assert!(e.to_string().contains("big.png"), "{e}");

        let e = load_rgb(&big, &ImageLimits { max_bytes: 10, ..Default::default() }).unwrap_err();
        assert!(matches!(e, ImageError::FileTooLarge { .. }), "{e}");

        let e = load_rgb(&dir, &ImageLimits::default()).unwrap_err();
        assert!(matches!(e, ImageError::Io { .. }), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn save_and_load() {
        let dir = tmpdir("save");
        let img = RgbImage {
            width: 2,
            height: 2,
            data: vec![0.0, 0.5, 1.0, -1.0, 2.0, f32::NAN, 0.2, 0.4, 0.6, 0.998, 0.002, 0.5],
        };
        let p = dir.join("rgb.png");
        save_rgb_png(&p, &img).unwrap();
        let back = load_rgb(&p, &ImageLimits::default()).unwrap();
        assert_eq!(rgb_to_u8(&back), rgb_to_u8(&img));
        assert_eq!(rgb_to_u8(&img), vec![0, 128, 255, 0, 255, 0, 51, 102, 153, 254, 1, 128]);

        let g = dir.join("gray.png");
        save_gray_png(&g, 2, 2, &[0, 85, 170, 255]).unwrap();
        let back = load_rgb(&g, &ImageLimits::default()).unwrap();
        assert_eq!(rgb_to_u8(&back), vec![0, 0, 0, 85, 85, 85, 170, 170, 170, 255, 255, 255]);

        let d = dir.join("depth.png");
        save_gray16_png(&d, 3, 1, &[0, 1234, 65535]).unwrap();
        assert_eq!(load_depth_png16(&d).unwrap(), (3, 1, vec![0.0, 1234.0, 65535.0]));
        let e = load_depth_png16(&g).unwrap_err();
        assert!(matches!(e, ImageError::Unsupported { .. }), "{e}");

        let e = save_gray_png(&g, 2, 2, &[0, 1, 2]).unwrap_err();
        assert!(matches!(e, ImageError::InvalidInput { .. }), "{e}");
        let e = save_rgb_png(&p, &RgbImage { width: 0, height: 0, data: vec![] }).unwrap_err();
        assert!(matches!(e, ImageError::InvalidInput { .. }), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn bundled_photos_decode() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/photos");
        let (chelsea, rocket) = (root.join("chelsea.png"), root.join("rocket.jpg"));
        // reference values from Pillow: (width, height, first pixel, mean over all values / 255)
        let cases = [(&chelsea, 451, 300, [143, 120, 104], 0.452_177), (&rocket, 640, 427, [17, 33, 58], 0.255_988)];
        for (p, w, h, first, mean_ref) in cases {
            let img = load_rgb(p, &ImageLimits::default()).unwrap();
            assert_eq!((img.width, img.height), (w, h), "{}", p.display());
            assert_eq!(img.data.len(), w * h * 3);
            let bytes = rgb_to_u8(&img);
            let mean = bytes.iter().map(|&v| f64::from(v)).sum::<f64>() / bytes.len() as f64 / 255.0;
            // PNG is lossless: exact; JPEG decoders may differ by a level or two on some pixels
            assert!((mean - mean_ref).abs() < 2e-3, "{}: mean {mean} vs {mean_ref}", p.display());
            for c in 0..3 {
                assert!((i32::from(bytes[c]) - first[c]).abs() <= 2, "{}: {:?}", p.display(), &bytes[..3]);
            }
        }
        let png = rgb_to_u8(&load_rgb(&chelsea, &ImageLimits::default()).unwrap());
        assert_eq!(png[..3], [143, 120, 104]);
        assert_eq!(png.iter().map(|&v| u64::from(v)).sum::<u64>(), 46_802_357);
    }
}
