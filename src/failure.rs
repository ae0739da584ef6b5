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
}

impl FailureKind {
    /// The reason string (`decode`, `truncated`, `too-large`, `depth`, `mask`, `mpi`, `scene`,
    /// `no-image`, `duplicate`, `unnamed`).
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
