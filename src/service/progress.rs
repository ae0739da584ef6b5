//! What a client took of a connection's writes: the DATA payload among the HTTP/2 frames the
//! server writes in the clear, told apart from PING ACKs, SETTINGS, WINDOW_UPDATE, HEADERS and
//! the other control frames. Only DATA moves when the client grants window (or its socket takes
//! bytes) for what it was sent; a PING answered every few milliseconds moves nothing, so a
//! client that withholds its window while it pings is seen as taking nothing.

/// HTTP/2's frame header: 24-bit length, type, flags, 31-bit stream id.
const HEADER_BYTES: usize = 9;

/// The type of a DATA frame.
const DATA: u8 = 0x0;

/// Follows the frames of the bytes a server writes on one HTTP/2 connection (a server writes no
/// preface string: its first bytes are a frame).
#[derive(Debug, Default)]
pub struct FrameScan {
    header: [u8; HEADER_BYTES],
    /// Bytes of the current frame's header seen so far.
    have: usize,
    /// Payload bytes of the current frame still to come (once its header is whole).
    left: u32,
    /// Whether the current frame is DATA.
    data: bool,
}

impl FrameScan {
    /// Follows `bytes`, the next bytes written: how many of them are DATA payload.
    pub fn feed(&mut self, mut bytes: &[u8]) -> usize {
        let mut payload = 0;
        while !bytes.is_empty() {
            if self.have < HEADER_BYTES {
                let n = (HEADER_BYTES - self.have).min(bytes.len());
                self.header[self.have..self.have + n].copy_from_slice(&bytes[..n]);
                self.have += n;
                bytes = &bytes[n..];
                if self.have == HEADER_BYTES {
                    let [a, b, c, kind, ..] = self.header;
                    self.left = u32::from_be_bytes([0, a, b, c]);
                    self.data = kind == DATA;
                    if self.left == 0 {
                        self.have = 0;
                    }
                }
            } else {
                let n = (self.left as usize).min(bytes.len());
                if self.data {
                    payload += n;
                }
                // n <= left
                self.left -= n as u32;
                bytes = &bytes[n..];
                if self.left == 0 {
                    self.have = 0;
                }
            }
        }
        payload
    }

    /// [`FrameScan::feed`] over the first `n` bytes of `bufs` (what a vectored write wrote).
    pub fn feed_vectored(&mut self, bufs: &[std::io::IoSlice<'_>], mut n: usize) -> usize {
        let mut payload = 0;
        for b in bufs {
            if n == 0 {
                break;
            }
            let k = n.min(b.len());
            payload += self.feed(&b[..k]);
            n -= k;
        }
        payload
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(kind: u8, payload: &[u8]) -> Vec<u8> {
        let len = (payload.len() as u32).to_be_bytes();
        let mut f = vec![len[1], len[2], len[3], kind, 0, 0, 0, 0, 1];
        f.extend_from_slice(payload);
        f
    }

    /// PING ACKs, SETTINGS, WINDOW_UPDATE and HEADERS carry no DATA payload; DATA frames do,
    /// however the writes cut the frames.
    #[test]
    fn only_data_payload_counts_however_the_writes_are_cut() {
        let mut bytes = Vec::new();
        bytes.extend(frame(0x4, &[0; 6])); // SETTINGS
        bytes.extend(frame(0x6, &[7; 8])); // PING (ACK)
        bytes.extend(frame(0x1, &[1; 40])); // HEADERS
        bytes.extend(frame(DATA, &[2; 1000]));
        bytes.extend(frame(0x8, &[0, 0, 1, 0])); // WINDOW_UPDATE
        bytes.extend(frame(DATA, &[]));
        bytes.extend(frame(DATA, &[3; 77]));
        bytes.extend(frame(0x6, &[7; 8]));
        for cut in [1, 2, 5, 9, 10, 17, 64, 4096] {
            let mut scan = FrameScan::default();
            let total: usize = bytes.chunks(cut).map(|c| scan.feed(c)).sum();
            assert_eq!(total, 1077, "writes of {cut} bytes");
        }
        let mut pings = FrameScan::default();
        let only_pings: Vec<u8> = (0..100).flat_map(|_| frame(0x6, &[9; 8])).collect();
        assert_eq!(pings.feed(&only_pings), 0);
    }

    /// A vectored write counts only the bytes it wrote.
    #[test]
    fn a_vectored_write_counts_what_it_wrote() {
        let head = frame(DATA, &[5; 100]);
        let (a, b) = head.split_at(30);
        let bufs = [std::io::IoSlice::new(a), std::io::IoSlice::new(b)];
        let mut scan = FrameScan::default();
        assert_eq!(scan.feed_vectored(&bufs, 40), 31);
        assert_eq!(scan.feed(&head[40..]), 69);
    }
}
