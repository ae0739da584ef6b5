//! Where an encoded file ends: the byte length of the PNG, JPEG or `.npy` at the start of a
//! buffer, read from its structure (chunks, markers, header), so that bytes after a complete
//! file can be refused instead of silently ignored.

/// The length of the PNG, JPEG or `.npy` file that `bytes` starts with, when its structure can
/// be followed to its end; `None` for other formats or a structure that ends early or is
/// malformed (the decoder reports those).
pub fn encoded_len(bytes: &[u8]) -> Option<usize> {
    if bytes.starts_with(&[0x89, b'P', b'N', b'G', 0x0d, 0x0a, 0x1a, 0x0a]) {
        png_len(bytes)
    } else if bytes.starts_with(&[0xff, 0xd8]) {
        jpeg_len(bytes)
    } else if bytes.starts_with(b"\x93NUMPY") {
        npy_len(bytes)
    } else {
        None
    }
}

/// Bytes after the end of the file `bytes` starts with (0 when it ends exactly there), when the
/// end can be found.
pub fn trailing_bytes(bytes: &[u8]) -> Option<usize> {
    encoded_len(bytes).map(|n| bytes.len() - n)
}

/// PNG: the signature, then chunks (length, type, data, CRC) up to and including `IEND`.
fn png_len(b: &[u8]) -> Option<usize> {
    let mut at = 8usize;
    loop {
        let len = u32::from_be_bytes(b.get(at..at + 4)?.try_into().ok()?) as usize;
        let kind = b.get(at + 4..at + 8)?;
        let end = at.checked_add(12)?.checked_add(len)?;
        if end > b.len() {
            return None;
        }
        if kind == b"IEND" {
            return Some(end);
        }
        at = end;
    }
}

/// JPEG: marker segments, entropy-coded data after each SOS (where `FF 00` is a stuffed byte and
/// `FF D0..D7` restart markers), up to and including the first EOI (`FF D9`).
fn jpeg_len(b: &[u8]) -> Option<usize> {
    let mut at = 2usize;
    loop {
        // a marker: FF (fill bytes FF allowed) then the code
        if *b.get(at)? != 0xff {
            return None;
        }
        while *b.get(at + 1)? == 0xff {
            at += 1;
        }
        let code = *b.get(at + 1)?;
        at += 2;
        match code {
            0xd9 => return Some(at),
            0x01 | 0xd0..=0xd7 => continue,
            _ => {}
        }
        let len = u16::from_be_bytes(b.get(at..at + 2)?.try_into().ok()?) as usize;
        if len < 2 {
            return None;
        }
        at = at.checked_add(len)?;
        if code == 0xda {
            // scan data: to the next marker that is not a stuffed byte or a restart
            loop {
                let x = *b.get(at)?;
                if x == 0xff {
                    let y = *b.get(at + 1)?;
                    if y == 0x00 || (0xd0..=0xd7).contains(&y) {
                        at += 2;
                        continue;
                    }
                    break;
                }
                at += 1;
            }
        }
    }
}

/// `.npy`: magic, version, header length (u16 in version 1, u32 in 2 and 3), the header's
/// `descr` and `shape`, then the data.
fn npy_len(b: &[u8]) -> Option<usize> {
    let major = *b.get(6)?;
    let (header_len, start): (usize, usize) = match major {
        1 => (u16::from_le_bytes(b.get(8..10)?.try_into().ok()?) as usize, 10),
        2 | 3 => (u32::from_le_bytes(b.get(8..12)?.try_into().ok()?) as usize, 12),
        _ => return None,
    };
    let data_start = start.checked_add(header_len)?;
    let header = std::str::from_utf8(b.get(start..data_start)?).ok()?;
    let item = {
        let d = header.split("'descr'").nth(1)?;
        let q = d.split('\'').nth(1)?;
        let digits: String = q.chars().filter(char::is_ascii_digit).collect();
        digits.parse::<usize>().ok()?
    };
    let shape = header.split("'shape'").nth(1)?;
    let inside = shape.split('(').nth(1)?.split(')').next()?;
    let mut count = 1usize;
    for part in inside.split(',').map(str::trim).filter(|p| !p.is_empty()) {
        count = count.checked_mul(part.parse::<usize>().ok()?)?;
    }
    let end = data_start.checked_add(count.checked_mul(item)?)?;
    (end <= b.len()).then_some(end)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn png() -> Vec<u8> {
        let mut out = std::io::Cursor::new(Vec::new());
        ::image::RgbImage::from_fn(9, 7, |x, y| ::image::Rgb([x as u8 * 20, y as u8 * 30, 7]))
            .write_to(&mut out, ::image::ImageFormat::Png)
            .unwrap();
        out.into_inner()
    }

    fn jpeg() -> Vec<u8> {
        let mut out = std::io::Cursor::new(Vec::new());
        ::image::RgbImage::from_fn(33, 17, |x, y| ::image::Rgb([(x * 7) as u8, (y * 13) as u8, ((x * y) % 255) as u8]))
            .write_to(&mut out, ::image::ImageFormat::Jpeg)
            .unwrap();
        out.into_inner()
    }

    fn npy() -> Vec<u8> {
        let mut out = Vec::new();
        crate::io::npy::write_f32_to(&mut out, &[3, 5], &[1.5; 15]).unwrap();
        out
    }

    #[test]
    fn complete_files_end_where_they_end_and_junk_is_counted() {
        for (name, f) in [("png", png()), ("jpeg", jpeg()), ("npy", npy())] {
            assert_eq!(encoded_len(&f), Some(f.len()), "{name}");
            let mut junk = f.clone();
            junk.extend_from_slice(b"trailing junk");
            assert_eq!(trailing_bytes(&junk), Some(13), "{name}");
            // cut short: no end found
            assert_eq!(encoded_len(&f[..f.len() - 3]), None, "{name}");
        }
        assert_eq!(encoded_len(b"not a file"), None);
    }
}
