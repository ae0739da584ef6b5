//! Reading a small text file (a configuration, a token, a registry) with a size bound: a file
//! over the bound (or an endless one such as `/dev/zero`) is refused after reading one byte more
//! than the bound, never read whole.

use std::io::{Error, ErrorKind, Read};
use std::path::Path;

/// The contents of `path` as UTF-8 text, at most `limit` bytes; a longer file is an error of kind
/// [`ErrorKind::FileTooLarge`] that names the limit.
pub fn read_to_string(path: &Path, limit: u64) -> std::io::Result<String> {
    let file = std::fs::File::open(path)?;
    let mut bytes = Vec::new();
    file.take(limit.saturating_add(1)).read_to_end(&mut bytes)?;
    if bytes.len() as u64 > limit {
        return Err(Error::new(ErrorKind::FileTooLarge, format!("larger than {limit} bytes")));
    }
    String::from_utf8(bytes).map_err(|_| Error::new(ErrorKind::InvalidData, "not UTF-8 text"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_file_over_the_bound_is_refused_and_one_within_it_read() {
        let dir = std::env::temp_dir().join(format!("mpiflow-bounded-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("t");
        std::fs::write(&p, "0123456789").unwrap();
        assert_eq!(read_to_string(&p, 10).unwrap(), "0123456789");
        let e = read_to_string(&p, 9).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::FileTooLarge);
        assert!(e.to_string().contains("larger than 9 bytes"), "{e}");
        std::fs::write(&p, [0xff, 0xfe]).unwrap();
        assert_eq!(read_to_string(&p, 10).unwrap_err().kind(), ErrorKind::InvalidData);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[cfg(unix)]
    #[test]
    fn an_endless_file_is_refused_at_the_bound() {
        let e = read_to_string(Path::new("/dev/zero"), 1 << 16).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::FileTooLarge);
    }
}
