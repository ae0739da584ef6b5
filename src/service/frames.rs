//! The reply body of the sample streams (StreamSamples' batches, GetSamples' samples), written
//! here instead of by tonic's codec: each message is one gRPC frame (the 5-byte prefix and the
//! protobuf encoding, the bytes prost writes) handed to HTTP/2 as a list of pieces in which every
//! tensor's `data` is the sample's own `Bytes`. tonic's codec
//! copies each message into one buffer (a fresh one per sample, since HTTP/2 still holds the last
//! one's frames when the next is encoded: 4.6 MB copied and faulted in per 640x480 sample); here
//! only the small fields around the tensors are written. The call's trailers are tonic's
//! (`grpc-status`, `grpc-message` from the [`Status`]), and so are the size limit and its error.

use std::collections::VecDeque;
use std::pin::Pin;
use std::task::{ready, Context, Poll};

use bytes::{BufMut, Bytes, BytesMut};
use http_body::{Body, Frame};
use prost::encoding::{encode_key, encode_varint, encoded_len_varint, key_len, WireType};
use prost::Message;
use tokio_stream::Stream;
use tonic::Status;

use super::pb;

/// A tensor's data shorter than this is copied in with the small fields around it (a piece of its
/// own would cost HTTP/2 a frame of its own for a few bytes).
pub const OWN_PIECE_BYTES: usize = 4096;

/// The gRPC message prefix: the compressed flag and the length (big-endian u32).
const PREFIX_BYTES: usize = 5;

/// One gRPC message as pieces; concatenated, they are the message's frame.
struct Pieces {
    out: Vec<Bytes>,
    small: BytesMut,
}

impl Pieces {
    fn new() -> Self {
        Pieces { out: Vec::new(), small: BytesMut::with_capacity(1024) }
    }

    /// A length-delimited field's key and length (its bytes follow).
    fn field(&mut self, tag: u32, len: usize) {
        encode_key(tag, WireType::LengthDelimited, &mut self.small);
        encode_varint(len as u64, &mut self.small);
    }

    /// A message's own encoding (a message holding only small fields).
    fn message(&mut self, m: &impl Message) -> Result<(), Status> {
        m.encode(&mut self.small).map_err(|e| Status::internal(format!("encoding: {e}")))
    }

    /// Bytes kept as they are (copied in when shorter than [`OWN_PIECE_BYTES`]).
    fn bytes(&mut self, b: Bytes) {
        if b.len() < OWN_PIECE_BYTES {
            self.small.extend_from_slice(&b);
            return;
        }
        if !self.small.is_empty() {
            self.out.push(self.small.split().freeze());
        }
        self.out.push(b);
    }

    fn finish(mut self) -> Vec<Bytes> {
        if !self.small.is_empty() {
            self.out.push(self.small.freeze());
        }
        self.out
    }
}

/// The encoded length of a length-delimited field holding `len` bytes.
fn field_len(tag: u32, len: usize) -> usize {
    key_len(tag) + encoded_len_varint(len as u64) + len
}

/// A tensor without its data, and the data (`data` is the tensor's last field, so the tensor's
/// encoding is the first's followed by the data's field).
struct TensorParts {
    head: pb::Tensor,
    data: Bytes,
}

impl TensorParts {
    const DATA_TAG: u32 = 6;

    fn new(t: pb::Tensor) -> Self {
        // every field named, so that a new one is placed here by its tag
        let pb::Tensor { name, shape, dtype, compression, raw_size, data } = t;
        TensorParts { head: pb::Tensor { name, shape, dtype, compression, raw_size, data: Bytes::new() }, data }
    }

    fn len(&self) -> usize {
        // an empty bytes field is not written (proto3)
        let data = if self.data.is_empty() { 0 } else { field_len(Self::DATA_TAG, self.data.len()) };
        self.head.encoded_len() + data
    }

    fn write(self, p: &mut Pieces) -> Result<(), Status> {
        p.message(&self.head)?;
        if !self.data.is_empty() {
            p.field(Self::DATA_TAG, self.data.len());
            p.bytes(self.data);
        }
        Ok(())
    }
}

/// A sample as its fields before the tensors, the tensors, and its fields after them (prost writes
/// the fields in the order of their tags and leaves out those at their defaults, so the three
/// encodings in turn are the sample's).
struct SampleParts {
    head: pb::Sample,
    tensors: Vec<TensorParts>,
    tail: pb::Sample,
}

impl SampleParts {
    const TENSORS_TAG: u32 = 8;

    fn new(s: pb::Sample) -> Self {
        // every field named, so that a new one is placed here by its tag
        let pb::Sample {
            index,
            dataset,
            fingerprint,
            seed,
            source_id,
            width,
            height,
            tensors,
            camera,
            objects,
            intrinsics,
            timings,
            skipped_sources,
            crop_x,
            crop_y,
            inpainted_pixels,
            provenance,
            augment,
            frames,
        } = s;
        let head = pb::Sample { index, dataset, fingerprint, seed, source_id, width, height, ..Default::default() };
        let tail = pb::Sample {
            camera,
            objects,
            intrinsics,
            timings,
            skipped_sources,
            crop_x,
            crop_y,
            inpainted_pixels,
            provenance,
            augment,
            frames,
            ..Default::default()
        };
        SampleParts { head, tensors: tensors.into_iter().map(TensorParts::new).collect(), tail }
    }

    fn len(&self) -> usize {
        let tensors: usize = self.tensors.iter().map(|t| field_len(Self::TENSORS_TAG, t.len())).sum();
        self.head.encoded_len() + tensors + self.tail.encoded_len()
    }

    fn write(self, p: &mut Pieces) -> Result<(), Status> {
        p.message(&self.head)?;
        for t in self.tensors {
            p.field(Self::TENSORS_TAG, t.len());
            t.write(p)?;
        }
        p.message(&self.tail)
    }
}

/// A message whose gRPC frame is written as pieces ([`FrameBody`]'s items).
pub trait Framed {
    /// The frame (uncompressed) as pieces, the tensors' data among them as they are:
    /// concatenated, the 5-byte prefix and prost's encoding of the message. A message longer
    /// than `limit` bytes is refused with tonic's error for it (OUT_OF_RANGE).
    fn frame(self, limit: usize) -> Result<Vec<Bytes>, Status>;
}

/// The frame of a message of `len` bytes that `write` writes.
fn frame(
    len: usize,
    limit: usize,
    write: impl FnOnce(&mut Pieces) -> Result<(), Status>,
) -> Result<Vec<Bytes>, Status> {
    if len > limit {
        return Err(Status::out_of_range(format!(
            "Error, encoded message length too large: found {len} bytes, the limit is: {limit} bytes"
        )));
    }
    let len32 = u32::try_from(len).map_err(|_| {
        Status::resource_exhausted(format!("Cannot return body with more than 4GB of data but got {len} bytes"))
    })?;
    let mut p = Pieces::new();
    p.small.put_u8(0);
    p.small.put_u32(len32);
    write(&mut p)?;
    let out = p.finish();
    debug_assert_eq!(out.iter().map(Bytes::len).sum::<usize>(), PREFIX_BYTES + len);
    Ok(out)
}

/// StreamSamples' message.
impl Framed for pb::SampleBatch {
    fn frame(self, limit: usize) -> Result<Vec<Bytes>, Status> {
        const SAMPLES_TAG: u32 = 1;
        let pb::SampleBatch { samples, next_index, resume_start_index } = self;
        let rest = pb::SampleBatch { samples: Vec::new(), next_index, resume_start_index };
        let samples: Vec<SampleParts> = samples.into_iter().map(SampleParts::new).collect();
        let len = samples.iter().map(|s| field_len(SAMPLES_TAG, s.len())).sum::<usize>() + rest.encoded_len();
        frame(len, limit, |p| {
            for s in samples {
                p.field(SAMPLES_TAG, s.len());
                s.write(p)?;
            }
            p.message(&rest)
        })
    }
}

/// GetSamples' message.
impl Framed for pb::Sample {
    fn frame(self, limit: usize) -> Result<Vec<Bytes>, Status> {
        let s = SampleParts::new(self);
        frame(s.len(), limit, |p| s.write(p))
    }
}

/// The reply body of a server-streaming call: each message of `stream` as its [`Framed`] pieces,
/// one HTTP/2 data frame each (at most; the server's reply layer cuts them further), then the
/// call's trailers: OK when the stream ends, the status of the stream's error or of a message
/// over the size limit otherwise (after which nothing more is sent, as with tonic's codec).
pub struct FrameBody<S> {
    stream: S,
    pieces: VecDeque<Bytes>,
    limit: usize,
    done: bool,
}

impl<S> FrameBody<S> {
    /// `limit`: the largest message, in bytes (`max_message_bytes`).
    pub fn new(stream: S, limit: usize) -> Self {
        FrameBody { stream, pieces: VecDeque::new(), limit, done: false }
    }

    fn trailers(&mut self, status: Status) -> Poll<Option<Result<Frame<Bytes>, Status>>> {
        self.done = true;
        let mut trailers = http::HeaderMap::new();
        Poll::Ready(Some(status.add_header(&mut trailers).map(|()| Frame::trailers(trailers))))
    }
}

impl<M: Framed, S: Stream<Item = Result<M, Status>> + Unpin> Body for FrameBody<S> {
    type Data = Bytes;
    type Error = Status;

    fn poll_frame(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Result<Frame<Bytes>, Status>>> {
        if self.done {
            return Poll::Ready(None);
        }
        if let Some(piece) = self.pieces.pop_front() {
            return Poll::Ready(Some(Ok(Frame::data(piece))));
        }
        match ready!(Pin::new(&mut self.stream).poll_next(cx)) {
            Some(Ok(message)) => match message.frame(self.limit) {
                Ok(pieces) => {
                    self.pieces.extend(pieces);
                    let first = self.pieces.pop_front().unwrap_or_default();
                    Poll::Ready(Some(Ok(Frame::data(first))))
                }
                Err(status) => self.trailers(status),
            },
            Some(Err(status)) => self.trailers(status),
            None => self.trailers(Status::ok("")),
        }
    }

    fn is_end_stream(&self) -> bool {
        self.done
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn tensor(name: String, shape: Vec<u32>, dtype: i32, data: Vec<u8>) -> pb::Tensor {
        pb::Tensor { raw_size: data.len() as u64, name, shape, dtype, compression: dtype % 2, data: Bytes::from(data) }
    }

    prop_compose! {
        fn arb_tensor()(name in "[a-z0-9]{0,12}", shape in proptest::collection::vec(0u32..5000, 0..4),
                        dtype in 0i32..4,
                        // empty, small (copied in), at the piece threshold, large (its own piece)
                        len in prop_oneof![Just(0usize), 1usize..64, Just(OWN_PIECE_BYTES - 1), Just(OWN_PIECE_BYTES), 5000usize..70_000],
                        fill in any::<u8>()) -> pb::Tensor {
            let data = (0..len).map(|i| fill.wrapping_add(i as u8)).collect();
            tensor(name, shape, dtype, data)
        }
    }

    prop_compose! {
        fn arb_sample()(index in any::<u64>(), dataset in "[a-z]{0,8}", fingerprint in any::<u64>(), seed in any::<u64>(),
                        width in 0u32..4096, height in 0u32..4096,
                        tensors in proptest::collection::vec(arb_tensor(), 0..5),
                        has_camera in any::<bool>(), law in "[a-z]{0,6}", translation in proptest::collection::vec(-5.0f64..5.0, 0..4),
                        objects in proptest::collection::vec((any::<u32>(), any::<f32>()), 0..3),
                        crop in (0u32..100, 0u32..100), inpainted in any::<u64>(),
                        provenance in proptest::collection::vec("[a-z ]{0,10}", 0..3), augment in "[a-z=,]{0,10}",
                        frames in 0u32..4, skipped in 0u32..3) -> pb::Sample {
            pb::Sample {
                index, dataset, fingerprint, seed, source_id: format!("src-{index}"), width, height, tensors,
                camera: has_camera.then(|| pb::Motion { law, translation, ..Default::default() }),
                objects: objects.into_iter().map(|(label, score)| pb::ObjectMotion { label, score, ..Default::default() }).collect(),
                intrinsics: has_camera.then_some(pb::Intrinsics { fx: 500.0, fy: 510.0, cx: 320.0, cy: 240.0 }),
                timings: Some(pb::Timings { total_ms: 12.5, ..Default::default() }),
                skipped_sources: skipped,
                crop_x: crop.0,
                crop_y: crop.1,
                inpainted_pixels: inpainted,
                provenance,
                augment,
                frames,
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        /// The pieces, concatenated, are the gRPC frame of prost's encoding of the batch (and of
        /// each sample alone), for any batch (no sample, several, tensors empty, small, at the
        /// piece threshold and large), and the large data are the tensors' own buffers.
        #[test]
        fn the_pieces_are_the_frame_of_prosts_encoding(
            samples in proptest::collection::vec(arb_sample(), 0..3),
            next_index in any::<u64>(),
            resume in any::<u64>(),
        ) {
            // each sample alone (GetSamples' message)
            for s in &samples {
                let joined: Vec<u8> = s.clone().frame(usize::MAX).unwrap().iter().flat_map(|p| p.iter().copied()).collect();
                let encoded = s.encode_to_vec();
                prop_assert_eq!(&joined[..5], &[&[0u8][..], &(encoded.len() as u32).to_be_bytes()[..]].concat()[..]);
                prop_assert_eq!(&joined[5..], &encoded[..]);
            }
            let batch = pb::SampleBatch { samples, next_index, resume_start_index: resume };
            let encoded = batch.encode_to_vec();
            let big: Vec<(usize, usize)> = batch.samples.iter().flat_map(|s| &s.tensors)
                .filter(|t| t.data.len() >= OWN_PIECE_BYTES).map(|t| (t.data.as_ptr() as usize, t.data.len())).collect();
            let pieces = batch.frame(usize::MAX).unwrap();
            let joined: Vec<u8> = pieces.iter().flat_map(|p| p.iter().copied()).collect();
            prop_assert_eq!(joined[0], 0);
            prop_assert_eq!(u32::from_be_bytes(joined[1..5].try_into().unwrap()) as usize, encoded.len());
            prop_assert_eq!(&joined[5..], &encoded[..]);
            // each large tensor's data is one piece, the tensor's own bytes (not a copy)
            let pieces_at: Vec<(usize, usize)> = pieces.iter().map(|p| (p.as_ptr() as usize, p.len())).collect();
            for b in &big {
                prop_assert!(pieces_at.contains(b), "tensor data at {:?} copied", b);
            }
            prop_assert!(pieces.iter().all(|p| !p.is_empty()));
        }
    }

    /// A batch over the limit is refused with tonic's error (OUT_OF_RANGE), one at the limit is
    /// sent.
    #[test]
    fn a_batch_over_the_limit_is_refused() {
        let sample =
            pb::Sample { tensors: vec![tensor("image1".into(), vec![2], 1, vec![7; 10_000])], ..Default::default() };
        let batch = pb::SampleBatch { samples: vec![sample], next_index: 1, resume_start_index: 0 };
        let len = batch.encoded_len();
        let err = batch.clone().frame(len - 1).unwrap_err();
        assert_eq!(err.code(), tonic::Code::OutOfRange);
        assert!(err.message().contains(&format!("found {len} bytes")), "{}", err.message());
        let ok = batch.frame(len).unwrap();
        assert_eq!(ok.iter().map(Bytes::len).sum::<usize>(), len + 5);
    }

    /// The body sends each batch's pieces, then trailers: OK when the stream ends, the stream's
    /// error as the status otherwise, and nothing after them.
    #[tokio::test]
    async fn the_body_ends_with_the_streams_status() {
        use http_body_util::BodyExt;
        let batch = |i: u64| pb::SampleBatch {
            samples: vec![pb::Sample {
                index: i,
                tensors: vec![tensor("flow".into(), vec![9], 2, vec![1; 9000])],
                ..Default::default()
            }],
            next_index: i + 1,
            resume_start_index: 0,
        };
        let expected: Vec<u8> = [batch(0), batch(1)]
            .iter()
            .flat_map(|b| {
                let e = b.encode_to_vec();
                let mut f = vec![0];
                f.extend((e.len() as u32).to_be_bytes());
                f.extend(e);
                f
            })
            .collect();
        for (end, code) in [(None, tonic::Code::Ok), (Some(Status::unavailable("draining")), tonic::Code::Unavailable)]
        {
            let items: Vec<Result<pb::SampleBatch, Status>> =
                [Ok(batch(0)), Ok(batch(1))].into_iter().chain(end.map(Err)).collect();
            let mut body = FrameBody::new(tokio_stream::iter(items), usize::MAX);
            let mut data = Vec::new();
            let mut trailers = None;
            while let Some(frame) = body.frame().await {
                let frame = frame.unwrap();
                assert!(trailers.is_none(), "a frame after the trailers");
                match frame.into_data() {
                    Ok(d) => data.extend_from_slice(&d),
                    Err(f) => trailers = Some(f.into_trailers().unwrap()),
                }
            }
            assert!(body.is_end_stream());
            assert_eq!(data, expected);
            let status = Status::from_header_map(&trailers.expect("trailers")).expect("a status");
            assert_eq!(status.code(), code);
        }
    }
}
