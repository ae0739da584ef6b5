//! A tensor's bytes for the wire, made from a sample's own buffers without intermediate copies:
//! u8 buffers are moved in, f32 buffers are lent as their little-endian bytes (no copy on a
//! little-endian machine), and the f16 and lz4 conversions write straight into the tensor's own,
//! exactly sized buffer. The bytes are those of the plain per-value encoding (raw little-endian,
//! C order; lz4 block with the size prepended), checked by the tests here and in `encode`.

use bytes::Bytes;
use half::f16;

use super::pb;

/// A tensor from its raw little-endian bytes, lz4-compressed on request (the compressed block is
/// written into its own buffer, which the tensor then holds).
pub fn tensor(name: &str, shape: &[usize], dtype: pb::DType, raw: Bytes, lz4: bool) -> pb::Tensor {
    let raw_size = raw.len() as u64;
    let (data, compression) = if lz4 {
        (Bytes::from(lz4_flex::block::compress_prepend_size(&raw)), pb::Compression::Lz4)
    } else {
        (raw, pb::Compression::None)
    };
    pb::Tensor {
        name: name.into(),
        shape: shape.iter().map(|&d| d as u32).collect(),
        dtype: dtype as i32,
        compression: compression as i32,
        raw_size,
        data,
    }
}

/// f32 values held as their little-endian bytes: the vector itself, lent as bytes.
#[cfg(target_endian = "little")]
struct LeF32(Vec<f32>);

#[cfg(target_endian = "little")]
impl AsRef<[u8]> for LeF32 {
    fn as_ref(&self) -> &[u8] {
        bytemuck::cast_slice(&self.0)
    }
}

/// The little-endian bytes of `v`, taking the vector over (no copy on a little-endian machine).
pub fn f32_le(v: Vec<f32>) -> Bytes {
    #[cfg(target_endian = "little")]
    {
        Bytes::from_owner(LeF32(v))
    }
    #[cfg(not(target_endian = "little"))]
    {
        let mut out = vec![0u8; v.len() * 4];
        for (o, x) in out.chunks_exact_mut(4).zip(&v) {
            o.copy_from_slice(&x.to_le_bytes());
        }
        Bytes::from(out)
    }
}

/// The little-endian float16 bytes of `v` (round to nearest even), written into one buffer of
/// exactly their size.
pub fn f16_le(v: &[f32]) -> Bytes {
    let mut out = crate::buf::zeros::<u8>(v.len() * 2);
    for (o, &x) in out.chunks_exact_mut(2).zip(v) {
        o.copy_from_slice(&f16::from_f32(x).to_le_bytes());
    }
    Bytes::from(out)
}

/// A flow (or other float) tensor: f16 on request, else f32.
pub fn float_tensor(name: &str, shape: &[usize], v: Vec<f32>, f16: bool, lz4: bool) -> pb::Tensor {
    if f16 {
        tensor(name, shape, pb::DType::DtypeF16, f16_le(&v), lz4)
    } else {
        tensor(name, shape, pb::DType::DtypeF32, f32_le(v), lz4)
    }
}

/// A u8 tensor that takes its buffer over.
pub fn u8_tensor(name: &str, shape: &[usize], v: Vec<u8>, lz4: bool) -> pb::Tensor {
    tensor(name, shape, pb::DType::DtypeU8, Bytes::from(v), lz4)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// The plain per-value encodings the wire format is defined by.
    fn f32_plain(v: &[f32]) -> Vec<u8> {
        v.iter().flat_map(|x| x.to_le_bytes()).collect()
    }

    fn f16_plain(v: &[f32]) -> Vec<u8> {
        v.iter().flat_map(|&x| f16::from_f32(x).to_le_bytes()).collect()
    }

    proptest! {
        #[test]
        fn float_bytes_are_the_plain_encoding(bits in prop::collection::vec(any::<u32>(), 0..300), lz4: bool) {
            // every bit pattern, NaNs and infinities included
            let v: Vec<f32> = bits.iter().map(|&b| f32::from_bits(b)).collect();
            prop_assert_eq!(&f32_le(v.clone())[..], &f32_plain(&v)[..]);
            prop_assert_eq!(&f16_le(&v)[..], &f16_plain(&v)[..]);
            let t = float_tensor("flow", &[v.len()], v.clone(), false, lz4);
            prop_assert_eq!(t.raw_size, v.len() as u64 * 4);
            let raw = if lz4 { lz4_flex::block::decompress_size_prepended(&t.data).unwrap() } else { t.data.to_vec() };
            prop_assert_eq!(raw, f32_plain(&v));
        }

        #[test]
        fn u8_tensors_keep_their_bytes(v in prop::collection::vec(any::<u8>(), 0..2000), lz4: bool) {
            let t = u8_tensor("valid", &[v.len()], v.clone(), lz4);
            let expected = if lz4 { lz4_flex::block::compress_prepend_size(&v) } else { v.clone() };
            prop_assert_eq!(&t.data[..], &expected[..]);
            prop_assert_eq!(t.compression, if lz4 { pb::Compression::Lz4 } else { pb::Compression::None } as i32);
        }
    }
}
