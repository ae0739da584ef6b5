//! COCO run-length encodings: the compressed string form, decoding, encoding, area and boxes.

#[allow(clippy::wildcard_imports)]
use super::*;

// ---------------------------------------------------------------------------------------------
// COCO RLE

/// The counts of a COCO RLE, as they appear in annotation JSON.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum RleCounts {
    /// pycocotools' compressed string (`rleToString`).
    Compressed(String),
    /// Plain run lengths (COCO "uncompressed RLE", e.g. crowd annotations).
    Uncompressed(Vec<u32>),
}

impl RleCounts {
    /// The run lengths.
    pub fn to_counts(&self) -> Result<Vec<u32>, MaskError> {
        match self {
            RleCounts::Compressed(s) => rle_from_string(s),
            RleCounts::Uncompressed(c) => Ok(c.clone()),
        }
    }
}

/// Decodes pycocotools' compressed RLE string (`rleFrString`) to run lengths.
pub fn rle_from_string(s: &str) -> Result<Vec<u32>, MaskError> {
    let bytes = s.as_bytes();
    let mut counts: Vec<u32> = Vec::with_capacity(bytes.len());
    let mut p = 0;
    while p < bytes.len() {
        let start = p;
        let mut x: i64 = 0;
        let mut k = 0;
        loop {
            let Some(&b) = bytes.get(p) else {
                return Err(rle_err(format!("the string ends inside the count that starts at byte {start}")));
            };
            if !(48..=111).contains(&b) {
                let shown =
                    s.get(p..).and_then(|r| r.chars().next()).map_or(format!("byte 0x{b:02x}"), |c| format!("{c:?}"));
                return Err(rle_err(format!("{shown} at byte {p} is not a compressed-RLE character ('0'..='o')")));
            }
            if k == 7 {
                return Err(rle_err(format!("the count at byte {start} has more than 7 groups (35 bits)")));
            }
            let c = i64::from(b - 48);
            x |= (c & 0x1f) << (5 * k);
            p += 1;
            k += 1;
            if c & 0x20 == 0 {
                if c & 0x10 != 0 {
                    x |= -1i64 << (5 * k);
                }
                break;
            }
        }
        let m = counts.len();
        if m > 2 {
            x += i64::from(counts[m - 2]);
        }
        let v = u32::try_from(x)
            .map_err(|_| rle_err(format!("count {} (at byte {start}) is {x}, outside 0..=4294967295", counts.len())))?;
        counts.push(v);
    }
    Ok(counts)
}

/// Encodes run lengths as pycocotools' compressed string (`rleToString`).
pub fn rle_to_string(counts: &[u32]) -> String {
    let mut s = String::with_capacity(counts.len() * 2);
    for (i, &c) in counts.iter().enumerate() {
        let mut x = i64::from(c);
        if i > 2 {
            x -= i64::from(counts[i - 2]);
        }
        loop {
            let mut c = (x & 0x1f) as u8;
            x >>= 5;
            let more = if c & 0x10 != 0 { x != -1 } else { x != 0 };
            if more {
                c |= 0x20;
            }
            s.push(char::from(c + 48));
            if !more {
                break;
            }
        }
    }
    s
}

/// Decodes an RLE to a row-major `h x w` mask of 0 and 1.
pub fn rle_decode(counts: &RleCounts, h: usize, w: usize) -> Result<Vec<u8>, MaskError> {
    rle_decode_counts(&counts.to_counts()?, h, w)
}

/// Decodes run lengths (column-major, zeros first) to a row-major `h x w` mask of 0 and 1; the
/// counts must sum to `h * w`.
pub fn rle_decode_counts(counts: &[u32], h: usize, w: usize) -> Result<Vec<u8>, MaskError> {
    let n = pixel_count(h, w)? as u64;
    let total: u64 = counts.iter().map(|&c| u64::from(c)).sum();
    if total != n {
        return Err(rle_err(format!("the counts sum to {total}, a {h} x {w} mask needs {n}")));
    }
    let mut mask = vec![0u8; n as usize];
    let mut k = 0usize;
    for (j, &c) in counts.iter().enumerate() {
        let c = c as usize;
        if j % 2 == 1 {
            for idx in k..k + c {
                mask[(idx % h) * w + idx / h] = 1;
            }
        }
        k += c;
    }
    Ok(mask)
}

/// Encodes a row-major `h x w` mask (non-zero = 1) as COCO run lengths (pycocotools'
/// `rleEncode`: column-major, zeros first; `[0]` for an empty mask).
///
/// # Panics
/// If `mask.len() != h * w` or `h * w` exceeds `u32::MAX`.
pub fn rle_encode(mask: &[u8], h: usize, w: usize) -> Vec<u32> {
    assert_eq!(
        Some(mask.len()),
        h.checked_mul(w),
        "rle_encode: mask holds {} values, {h} x {w} needs more",
        mask.len()
    );
    assert!(u32::try_from(mask.len()).is_ok(), "rle_encode: {h} x {w} does not fit in 32-bit counts");
    let mut counts = Vec::new();
    let g = Grid::new(w, h);
    let (mut prev, mut run) = (false, 0u32);
    for x in 0..w {
        for y in 0..h {
            let v = mask[g.index(x, y)] != 0;
            if v != prev {
                counts.push(run);
                run = 0;
                prev = v;
            }
            run += 1;
        }
    }
    counts.push(run);
    counts
}

/// The number of ones of an RLE (pycocotools' `area`).
pub fn rle_area(counts: &[u32]) -> u64 {
    counts.iter().skip(1).step_by(2).map(|&c| u64::from(c)).sum()
}

/// The bounding box `[x, y, width, height]` of an RLE, as pycocotools' `toBbox` (`rleToBbox`):
/// all zeros for an empty mask; a run of ones that wraps from one column into the next makes the
/// box span the full height, as in pycocotools.
pub fn rle_bbox(counts: &[u32], h: usize, w: usize) -> [f64; 4] {
    let m = counts.len() / 2 * 2;
    if m == 0 || h == 0 {
        return [0.0; 4];
    }
    let hh = h as u64;
    let (mut xs, mut ys, mut xe, mut ye) = (w as u64, hh, 0u64, 0u64);
    let (mut cc, mut xp) = (0u64, 0u64);
    for (j, &c) in counts[..m].iter().enumerate() {
        cc += u64::from(c);
        // pycocotools' uint arithmetic would wrap for an empty first ones-run; saturate instead
        let t = cc.saturating_sub((j % 2) as u64);
        let y = t % hh;
        let x = (t - y) / hh;
        if j % 2 == 0 {
            xp = x;
        } else if xp < x {
            ys = 0;
            ye = hh - 1;
        }
        xs = xs.min(x);
        xe = xe.max(x);
        ys = ys.min(y);
        ye = ye.max(y);
    }
    [xs as f64, ys as f64, (xe + 1).saturating_sub(xs) as f64, (ye + 1).saturating_sub(ys) as f64]
}

/// [`rle_bbox`] of a row-major mask.
///
/// # Panics
/// As [`rle_encode`].
pub fn mask_bbox(mask: &[u8], h: usize, w: usize) -> [f64; 4] {
    rle_bbox(&rle_encode(mask, h, w), h, w)
}
