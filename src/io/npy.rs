//! NumPy `.npy` arrays: reading any real or integer dtype as f64 (with its shape), from files or
//! from members of an `.npz`, and writing f32 / u8 arrays.

use npyz::{DType, NpyFile, TypeChar, WriterBuilder};
use std::io::{self, Read, Write};
use std::path::Path;

/// Refuse arrays with more elements than this (about 4 GiB of f32); a guard against headers
/// that promise absurd sizes.
pub const MAX_ELEMENTS: u64 = 1 << 30;

/// A dense array in C order.
#[derive(Clone, Debug, PartialEq)]
pub struct Array {
    pub shape: Vec<u64>,
    pub data: Vec<f64>,
}

impl Array {
    /// The shape with a leading dimension of 1 removed, if present and the rank exceeds `min_rank`.
    pub fn squeeze_leading(mut self, min_rank: usize) -> Self {
        if self.shape.len() > min_rank && self.shape[0] == 1 {
            self.shape.remove(0);
        }
        self
    }
}

fn bad(msg: String) -> io::Error {
    io::Error::new(io::ErrorKind::InvalidData, msg)
}

/// Longest `.npy` header accepted: 64 KiB (NumPy itself reads at most 10,000 bytes by default;
/// every version 1 header, whose length is a u16, fits).
pub const MAX_HEADER_LEN: u64 = 64 << 10;

/// Deepest nesting of brackets (`{`, `(`, `[` together) accepted in an `.npy` header. A NumPy
/// header is one dict holding a tuple (the shape), 2 levels; a structured dtype's list of tuples
/// adds 2 more. The header parser (`npyz`) backtracks over nested brackets: 13 nested `{` in a
/// 176-byte file made it allocate 100 MB (fuzz `npy_depth` case 985645), and every further level
/// multiplies that, so deeper headers are refused before it sees them.
pub const MAX_HEADER_NESTING: usize = 4;

/// Checks an `.npy` header before a parser reads it, from the stream's start (`r` is left
/// after the header): refuses a header that claims more bytes than the whole file holds
/// (`total_len`) or more than [`MAX_HEADER_LEN`] (a version 2/3 header length is a u32: a parser
/// would allocate 4 GiB for a 100-byte file), and one nested deeper than
/// [`MAX_HEADER_NESTING`] or holding more than one dict. Streams that do not start like an
/// `.npy` pass: the parser says what is wrong with them.
pub fn check_header<R: Read>(r: &mut R, total_len: u64) -> io::Result<()> {
    let mut prefix = [0u8; 12];
    let got = read_up_to(r, &mut prefix)?;
    let prefix = &prefix[..got];
    if !prefix.starts_with(b"\x93NUMPY") || got < 10 {
        return Ok(());
    }
    let (n, start) = match prefix[6] {
        1 => (u64::from(u16::from_le_bytes([prefix[8], prefix[9]])), 10),
        2 | 3 if got >= 12 => (u64::from(u32::from_le_bytes([prefix[8], prefix[9], prefix[10], prefix[11]])), 12),
        _ => return Ok(()),
    };
    if start as u64 + n > total_len {
        return Err(bad(format!("header of {n} bytes is longer than the {total_len} bytes of the file")));
    }
    if n > MAX_HEADER_LEN {
        return Err(bad(format!("header of {n} bytes is longer than the limit of {MAX_HEADER_LEN} bytes")));
    }
    let mut header = prefix[start..].to_vec();
    r.take(n - header.len() as u64).read_to_end(&mut header)?;
    header.truncate(n as usize);
    let (mut depth, mut dicts) = (0usize, 0usize);
    for &c in &header {
        match c {
            b'{' | b'(' | b'[' => {
                depth += 1;
                dicts += usize::from(c == b'{');
                if depth > MAX_HEADER_NESTING {
                    return Err(bad(format!("header nests brackets deeper than {MAX_HEADER_NESTING} levels")));
                }
                if dicts > 1 {
                    return Err(bad("header holds more than one dict".into()));
                }
            }
            b'}' | b')' | b']' => depth = depth.saturating_sub(1),
            _ => {}
        }
    }
    Ok(())
}

/// Reads until `buf` is full or the stream ends; the bytes read.
fn read_up_to<R: Read>(r: &mut R, buf: &mut [u8]) -> io::Result<usize> {
    let mut got = 0;
    while got < buf.len() {
        match r.read(&mut buf[got..]) {
            Ok(0) => break,
            Ok(k) => got += k,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(got)
}

/// Reads an npy stream of any float (f4, f8), integer or bool dtype as f64.
pub fn read_array<R: Read>(npy: NpyFile<R>) -> io::Result<Array> {
    let shape = npy.shape().to_vec();
    let count = shape.iter().try_fold(1u64, |a, &d| a.checked_mul(d)).unwrap_or(u64::MAX);
    if count > MAX_ELEMENTS {
        return Err(bad(format!("array of shape {shape:?} is larger than the limit of {MAX_ELEMENTS} elements")));
    }
    if npy.order() == npyz::Order::Fortran && shape.len() > 1 {
        return Err(bad("Fortran-ordered arrays are not supported; save with np.ascontiguousarray".into()));
    }
    let ts = match npy.dtype() {
        DType::Plain(ts) => ts,
        other => return Err(bad(format!("unsupported dtype {}", other.descr()))),
    };
    let data: Vec<f64> = match (ts.type_char(), ts.size_field()) {
        (TypeChar::Float, 8) => npy.into_vec::<f64>()?,
        (TypeChar::Float, 4) => npy.into_vec::<f32>()?.into_iter().map(f64::from).collect(),
        (TypeChar::Float, 2) => npy.into_vec::<half::f16>()?.into_iter().map(f64::from).collect(),
        (TypeChar::Uint, 1) | (TypeChar::Bool, 1) => npy.into_vec::<u8>()?.into_iter().map(f64::from).collect(),
        (TypeChar::Uint, 2) => npy.into_vec::<u16>()?.into_iter().map(f64::from).collect(),
        (TypeChar::Uint, 4) => npy.into_vec::<u32>()?.into_iter().map(f64::from).collect(),
        (TypeChar::Int, 1) => npy.into_vec::<i8>()?.into_iter().map(f64::from).collect(),
        (TypeChar::Int, 2) => npy.into_vec::<i16>()?.into_iter().map(f64::from).collect(),
        (TypeChar::Int, 4) => npy.into_vec::<i32>()?.into_iter().map(f64::from).collect(),
        (TypeChar::Int, 8) => npy.into_vec::<i64>()?.into_iter().map(|v| v as f64).collect(),
        _ => return Err(bad(format!("unsupported dtype {ts}; expected a float, integer or bool array"))),
    };
    if data.len() as u64 != count {
        return Err(bad(format!("array data holds {} values, its shape {shape:?} needs {count}", data.len())));
    }
    Ok(Array { shape, data })
}

/// Reads a `.npy` file.
pub fn read_npy_file(path: &Path) -> io::Result<Array> {
    let mut f = std::fs::File::open(path)?;
    let len = f.metadata()?.len();
    check_header(&mut f, len)?;
    io::Seek::rewind(&mut f)?;
    read_array(NpyFile::new(io::BufReader::new(f))?)
}

fn write_with<T: npyz::AutoSerialize + Copy>(path: &Path, shape: &[u64], data: &[T]) -> io::Result<()> {
    let f = io::BufWriter::new(std::fs::File::create(path)?);
    let mut w = npyz::WriteOptions::new().default_dtype().shape(shape).writer(f).begin_nd()?;
    w.extend(data.iter().copied())?;
    w.finish()
}

/// Writes a float32 array.
pub fn write_f32(path: &Path, shape: &[u64], data: &[f32]) -> io::Result<()> {
    write_with(path, shape, data)
}

/// Writes a uint8 array.
pub fn write_u8(path: &Path, shape: &[u64], data: &[u8]) -> io::Result<()> {
    write_with(path, shape, data)
}

/// Writes a float32 array into any writer (used to build `.npz` test files).
pub fn write_f32_to<W: Write>(w: W, shape: &[u64], data: &[f32]) -> io::Result<()> {
    let mut npy = npyz::WriteOptions::new().default_dtype().shape(shape).writer(w).begin_nd()?;
    npy.extend(data.iter().copied())?;
    npy.finish()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_f32_and_u8() {
        let dir = std::env::temp_dir().join(format!("mpiflow-npy-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("a.npy");
        write_f32(&p, &[2, 3], &[0.0, 1.5, -2.0, 3.0, 4.0, 5.0]).unwrap();
        let a = read_npy_file(&p).unwrap();
        assert_eq!(a.shape, vec![2, 3]);
        assert_eq!(a.data, vec![0.0, 1.5, -2.0, 3.0, 4.0, 5.0]);
        write_u8(&p, &[3], &[0, 1, 255]).unwrap();
        assert_eq!(read_npy_file(&p).unwrap().data, vec![0.0, 1.0, 255.0]);
        std::fs::write(&p, b"\x93NUMPY garbage").unwrap();
        assert!(read_npy_file(&p).is_err());
        std::fs::remove_dir_all(&dir).ok();
    }

    /// A header per NumPy (2 levels), one with a structured dtype (4 levels) pass; 5 levels, a
    /// second dict, and lengths over the file or the limit are refused; the stream is left after
    /// the header.
    #[test]
    fn headers_are_checked_for_length_and_nesting() {
        let npy = |v: u8, h: &str| {
            let mut b = b"\x93NUMPY".to_vec();
            b.extend([v, 0]);
            if v == 1 {
                b.extend((h.len() as u16).to_le_bytes());
            } else {
                b.extend((h.len() as u32).to_le_bytes());
            }
            b.extend(h.as_bytes());
            b.extend([7u8; 8]);
            b
        };
        let check = |b: &[u8]| check_header(&mut &b[..], b.len() as u64);
        let plain = "{'descr': '<f4', 'fortran_order': False, 'shape': (3, 2), }\n";
        let structured = "{'descr': [('a', '<f4'), ('b', '<f4', (2,))], 'shape': (3,), }\n";
        for v in [1, 2, 3] {
            check(&npy(v, plain)).unwrap();
            check(&npy(v, structured)).unwrap();
        }
        let b = npy(1, plain);
        let mut r = &b[..];
        check_header(&mut r, b.len() as u64).unwrap();
        assert_eq!(r, &[7u8; 8], "left after the header");
        let deep = "{'descr': '<f4', 'shape': ((((3,),),),), }";
        assert!(check(&npy(1, deep)).unwrap_err().to_string().contains("deeper than 4"));
        let two = "{'descr': '<f4', 'shape': {}, }";
        assert!(check(&npy(2, two)).unwrap_err().to_string().contains("more than one dict"));
        let mut long = npy(2, plain);
        long.truncate(40);
        assert!(check(&long).unwrap_err().to_string().contains("longer than the 40 bytes"));
        let mut huge = b"\x93NUMPY\x02\x00".to_vec();
        huge.extend(((MAX_HEADER_LEN + 1) as u32).to_le_bytes());
        assert!(check_header(&mut &huge[..], u64::MAX).unwrap_err().to_string().contains("limit of"));
        check(b"not an npy at all").unwrap();
    }
}
