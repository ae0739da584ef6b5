//! The gRPC codec of `mpiflow.v1` (named in `build.rs`): prost messages, with each outgoing
//! message's buffer reserved at its encoded length before the first byte is written, so a
//! multi-megabyte sample is copied into the transport's buffer once instead of through a chain of
//! doubling reallocations. Decoding is prost's; with `Tensor.data` a `bytes::Bytes`, a received
//! tensor is a view of the received message, not a copy.

use std::marker::PhantomData;

use prost::Message;
use tonic::codec::{BufferSettings, Codec, EncodeBuf, Encoder};
use tonic::Status;
use tonic_prost::ProstDecoder;

/// The codec of the generated client and server: `T` is encoded, `U` decoded.
#[derive(Debug, Clone, Copy)]
pub struct WireCodec<T, U> {
    _pd: PhantomData<(T, U)>,
}

impl<T, U> Default for WireCodec<T, U> {
    fn default() -> Self {
        Self { _pd: PhantomData }
    }
}

impl<T, U> Codec for WireCodec<T, U>
where
    T: Message + Send + 'static,
    U: Message + Default + Send + 'static,
{
    type Encode = T;
    type Decode = U;
    type Encoder = WireEncoder<T>;
    type Decoder = ProstDecoder<U>;

    fn encoder(&mut self) -> Self::Encoder {
        WireEncoder { _pd: PhantomData }
    }

    fn decoder(&mut self) -> Self::Decoder {
        ProstDecoder::new(BufferSettings::default())
    }
}

/// Encodes a prost message into a buffer reserved at the message's encoded length.
#[derive(Debug, Clone, Copy)]
pub struct WireEncoder<T> {
    _pd: PhantomData<T>,
}

impl<T: Message> Encoder for WireEncoder<T> {
    type Item = T;
    type Error = Status;

    fn encode(&mut self, item: T, buf: &mut EncodeBuf<'_>) -> Result<(), Status> {
        buf.reserve(item.encoded_len());
        item.encode(buf).map_err(|e| Status::internal(format!("encoding: {e}")))
    }

    fn buffer_settings(&self) -> BufferSettings {
        BufferSettings::default()
    }
}
