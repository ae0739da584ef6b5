//! Zero-filled buffers for the per-sample paths, allocated plainly and then written.
//!
//! `vec![0; n]` asks the allocator for zeroed memory, and jemalloc (the binary's allocator)
//! zeroes a reused large block by handing its pages back to the kernel (`MADV_DONTNEED`), so
//! each page faults in afresh on its first write: about 3,900 page faults per 640x480 sample
//! (docs/performance.md). [`zeros`] takes a plain allocation (a reused block keeps its pages)
//! and writes the zeros itself.
//!
//! A scene build's dense planes (32 x 4 values per pixel: 157 MB at 640 x 480) live only until
//! the planes are packed into blocks, and jemalloc hands a freed block over 8 MiB back to the
//! kernel at once, so every build faulted its planes in afresh (about 38,000 faults). They are
//! handed back here instead ([`give_back`]) and the next build of the same size takes them
//! ([`reused_zeros`]; the layering, which writes every value, takes them as they are:
//! [`reused_to_write`]): at most [`POOL_BYTES`] in all are kept.

use std::sync::Mutex;

/// The most bytes of buffers kept for reuse ([`give_back`]): two 640 x 480 builds' dense planes.
pub const POOL_BYTES: usize = 320 << 20;

/// Buffers handed back, for [`reused_zeros`].
static POOL: Mutex<Vec<Vec<f32>>> = Mutex::new(Vec::new());

fn pool() -> std::sync::MutexGuard<'static, Vec<Vec<f32>>> {
    POOL.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// A buffer handed back earlier that fits `n` values (at least `n` and at most `2 n`), taken out
/// of the pool.
fn fitting(n: usize) -> Option<Vec<f32>> {
    let mut pool = pool();
    pool.iter().position(|v| (n..=2 * n).contains(&v.capacity())).map(|k| pool.swap_remove(k))
}

/// `n` zeros in a buffer handed back earlier when one fits (at least `n` and at most `2 n`
/// values, so a small request does not hold a large buffer; its pages stay mapped), else a new one asked for zeroed (fresh pages are zero already: they fault in where they
/// are first written, by the threads that fill them, rather than all in one `memset`).
#[must_use]
pub fn reused_zeros(n: usize) -> Vec<f32> {
    match fitting(n) {
        Some(mut v) => {
            v.clear();
            v.resize(n, 0.0);
            v
        }
        None => vec![0.0; n],
    }
}

/// `n` values for a caller that writes every one of them: a buffer handed back earlier when one
/// fits, as it is (only a part beyond its old length is zeroed), else a new zeroed one. A build
/// of the size before skips the 157 MB `memset` of [`reused_zeros`].
#[must_use]
pub fn reused_to_write(n: usize) -> Vec<f32> {
    match fitting(n) {
        Some(mut v) => {
            v.truncate(n);
            v.resize(n, 0.0);
            v
        }
        None => vec![0.0; n],
    }
}

/// Keeps `v` for a later [`reused_zeros`] if the buffers kept stay within [`POOL_BYTES`];
/// otherwise frees it.
pub fn give_back(v: Vec<f32>) {
    let bytes = v.capacity() * size_of::<f32>();
    let mut pool = pool();
    let held: usize = pool.iter().map(|v| v.capacity() * size_of::<f32>()).sum();
    if bytes > 0 && held + bytes <= POOL_BYTES {
        pool.push(v);
    }
}

/// `n` copies of `T::default()` (zero for the numeric types), written rather than requested
/// zeroed from the allocator.
#[must_use]
pub fn zeros<T: Clone + Default>(n: usize) -> Vec<T> {
    let mut v = Vec::with_capacity(n);
    v.resize(n, T::default());
    v
}

#[cfg(test)]
mod tests {
    use super::{give_back, pool, reused_zeros, zeros, POOL_BYTES};

    #[test]
    fn reused_buffers_come_back_as_zeros_and_the_pool_is_bounded() {
        let mut v = reused_zeros(1000);
        assert!(v.len() == 1000 && v.iter().all(|&x| x.to_bits() == 0));
        v.fill(f32::NAN);
        give_back(v);
        for n in [10, 1000, 3000] {
            let w = reused_zeros(n);
            assert!(w.len() == n && w.iter().all(|&x| x.to_bits() == 0), "{n}");
            give_back(w);
        }
        // a buffer larger than the bound is not kept
        give_back(Vec::with_capacity(POOL_BYTES / 4 + 1));
        let held: usize = pool().iter().map(|v| v.capacity() * 4).sum();
        assert!(held <= POOL_BYTES, "{held}");
    }

    #[test]
    fn zeros_are_zero_and_of_the_length_asked() {
        for n in [0usize, 1, 17, 1 << 20] {
            let f: Vec<f32> = zeros(n);
            assert_eq!(f.len(), n);
            assert!(f.iter().all(|&x| x.to_bits() == 0));
            let b: Vec<u8> = zeros(n);
            assert!(b.len() == n && b.iter().all(|&x| x == 0));
        }
    }
}
