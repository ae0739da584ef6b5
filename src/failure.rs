//! The kinds of data failure a source item can have ([`FailureKind`]), set where the failure
//! happens (decoders, depth and mask readers, shards) and carried by the errors up to the skip
//! counts; never derived from message text.

/// Why a source item is bad (or was left out of its collection): the reason class of a skip, set
/// where the failure happens. [`as_str`](Self::as_str) is the `reason` of the skip counts in
/// `GetInfo` and of the `mpiflow_skipped_sources{dataset,reason}` metric.
#[non_exhaustive]
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum FailureKind {
    /// `decode`: a corrupt or unsupported image, a missing or unreadable file, bad JSON.
    Decode,
    /// `truncated`: the data ends early (a truncated JPEG, PNG or PFM, a shard member or a shard
    /// cut short).
    Truncated,
    /// `too-large`: over a byte or dimension limit.
    TooLarge,
    /// `depth`: a depth or disparity file that is malformed, or depth that is missing (no depth
    /// and no depth model) or cannot be brought to the scene scale.
    Depth,
    /// `mask`: a malformed instance-mask file.
    Mask,
    /// `mpi`: a malformed given MPI (or one of the wrong size).
    Mpi,
    /// `scene`: a scene that does not fit the recipe (sizes, intrinsics).
    Scene,
    /// `no-image`: a shard sample without an image field (left out when opened).
    NoImage,
    /// `duplicate`: a shard key whose members are not adjacent (the later run is left out).
    Duplicate,
    /// `unnamed`: a shard member without a key or field.
    Unnamed,
    /// `not-a-file`: a folder entry with a source file's name that is not a regular file (a
    /// FIFO, a device, a directory named `x.png`), left out when the folder is listed.
    NotAFile,
    /// `dangling-link`: a symbolic link whose target does not exist.
    DanglingLink,
    /// `outside-root`: a symbolic link that leads out of the source folder (not followed).
    OutsideRoot,
    /// `unsupported`: a file in a photo folder that is not a photo mpiflow reads (HEIC/HEIF,
    /// which has no maintained pure-Rust decoder, GIF, TIFF, a text file), counted when the
    /// folder is listed.
    Unsupported,
}

impl FailureKind {
    /// The reason string (`decode`, `truncated`, `too-large`, `depth`, `mask`, `mpi`, `scene`,
    /// `no-image`, `duplicate`, `unnamed`, `not-a-file`, `dangling-link`, `outside-root`,
    /// `unsupported`).
    pub const fn as_str(self) -> &'static str {
        match self {
            FailureKind::Decode => "decode",
            FailureKind::Truncated => "truncated",
            FailureKind::TooLarge => "too-large",
            FailureKind::Depth => "depth",
            FailureKind::Mask => "mask",
            FailureKind::Mpi => "mpi",
            FailureKind::Scene => "scene",
            FailureKind::NoImage => "no-image",
            FailureKind::Duplicate => "duplicate",
            FailureKind::Unnamed => "unnamed",
            FailureKind::NotAFile => "not-a-file",
            FailureKind::DanglingLink => "dangling-link",
            FailureKind::OutsideRoot => "outside-root",
            FailureKind::Unsupported => "unsupported",
        }
    }

    /// The kind of this failure in a file that plays `part` ([`Depth`](Self::Depth),
    /// [`Mask`](Self::Mask), [`Mpi`](Self::Mpi)): a file that does not decode is the part's
    /// failure; too large and truncated stay what they are.
    pub fn in_part(self, part: FailureKind) -> FailureKind {
        match self {
            FailureKind::Decode => part,
            other => other,
        }
    }
}

impl std::fmt::Display for FailureKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// Most characters of user input repeated in an error message ([`echo`]).
pub const ECHO_CHARS: usize = 200;

/// User input as an error message repeats it: quoted, escaped (control characters and
/// non-printable bytes as `\n`, `\u{1b}`, ...) and cut to [`ECHO_CHARS`] characters with the
/// number of characters left out, so an error never grows with the input or prints raw bytes.
pub fn echo(input: &str) -> String {
    // cut by the escaped length: one control character escapes to up to 10
    let (shown, rest) = cut_escaped(input, ECHO_CHARS, |c| {
        let q = format!("{:?}", c.to_string());
        q[1..q.len() - 1].to_string()
    });
    if rest > 0 {
        format!("\"{shown}\"... ({rest} more characters)")
    } else {
        format!("\"{shown}\"")
    }
}

/// The longest prefix of `input` whose escaped form (`escape` of each character) has at most
/// `max_chars` characters, escaped, and the number of input characters left out.
fn cut_escaped(input: &str, max_chars: usize, escape: impl Fn(char) -> String) -> (String, usize) {
    let mut out = String::with_capacity(input.len().min(max_chars + 32));
    let mut len = 0usize;
    let mut chars = input.chars();
    while let Some(c) = chars.next() {
        let piece = escape(c);
        let n = piece.chars().count();
        if len + n > max_chars {
            return (out, 1 + chars.count());
        }
        len += n;
        out.push_str(&piece);
    }
    (out, 0)
}

/// A whole message made safe to print or send: control characters escaped (newlines and tabs
/// too: one line), cut to `max_chars` characters with the number left out.
pub fn printable(message: &str, max_chars: usize) -> String {
    // cut by the escaped length (fuzz `npz_mpi` case 28955: 300 characters of control bytes
    // escaped to 910)
    let (mut out, rest) =
        cut_escaped(message, max_chars, |c| if c.is_control() { c.escape_debug().to_string() } else { c.to_string() });
    if rest > 0 {
        out.push_str(&format!("... ({rest} more characters)"));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn echo_is_short_quoted_and_escaped() {
        assert_eq!(echo("ab"), "\"ab\"");
        assert_eq!(echo("a\nb\u{1b}"), "\"a\\nb\\u{1b}\"");
        let long = "x".repeat(15_000);
        let e = echo(&long);
        assert!(e.len() < 260 && e.ends_with("(14800 more characters)"), "{e}");
    }

    #[test]
    fn escaped_messages_are_cut_by_their_escaped_length() {
        let controls = "\u{10}".repeat(1000);
        let p = printable(&controls, 300);
        assert!(p.chars().count() <= 300 + 32 && p.ends_with("(950 more characters)"), "{p}");
        let e = echo(&controls);
        assert!(e.chars().count() <= ECHO_CHARS + 40, "{} characters", e.chars().count());
        assert_eq!(echo("a\"b"), "\"a\\\"b\"");
    }

    #[test]
    fn printable_escapes_controls_and_cuts() {
        assert_eq!(printable("one\ntwo\u{0}", 100), "one\\ntwo\\0");
        assert_eq!(printable("abcdef", 3), "abc... (3 more characters)");
        let raw = String::from_utf8_lossy(&[0x7f, 0x1b, b'[', b'2', b'J', 0xff, 0xfe]).into_owned();
        let p = printable(&raw, 100);
        assert!(!p.chars().any(char::is_control), "{p:?}");
    }
}
