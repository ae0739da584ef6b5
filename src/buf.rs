//! Zero-filled buffers for the per-sample paths, allocated plainly and then written.
//!
//! `vec![0; n]` asks the allocator for zeroed memory, and jemalloc (the binary's allocator)
//! zeroes a reused large block by handing its pages back to the kernel (`MADV_DONTNEED`), so
//! each page faults in afresh on its first write: about 3,900 page faults per 640x480 sample
//! (docs/performance.md). [`zeros`] takes a plain allocation (a reused block keeps its pages)
//! and writes the zeros itself.

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
    use super::zeros;

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
