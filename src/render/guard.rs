//! The guards of every render: the checks of its inputs (a valid MPI, valid intrinsics, a
//! finite pose) and the non-finite guard of its outputs (no NaN or Inf leaves the renderer).

use super::types::{RenderError, RenderOutput, RenderParams};
use crate::mpi::Mpi;

/// The checks every render makes of its inputs: a valid MPI, valid intrinsics, a finite pose.
pub(crate) fn check_inputs(mpi: &Mpi, params: &RenderParams) -> Result<(), RenderError> {
    mpi.validate()?;
    if !params.k_src.is_valid() {
        return Err(RenderError::Intrinsics { which: "source", k: params.k_src });
    }
    if !params.k_tgt.is_valid() {
        return Err(RenderError::Intrinsics { which: "target", k: params.k_tgt });
    }
    if !params.pose.is_finite() {
        return Err(RenderError::Pose);
    }
    Ok(())
}

/// The last line of defence of the numerics rule (docs/design.md §4): no NaN or Inf leaves the
/// renderer (full frame or window). Returns how many
/// values had to be replaced (0 in every tested case; the count is reported, not hidden).
pub(crate) fn repair_nonfinite(out: &mut RenderOutput) -> u64 {
    use rayon::prelude::*;
    let mut n = 0u64;
    for buf in [
        &mut out.image,
        &mut out.depth,
        &mut out.coverage,
        &mut out.extras,
        &mut out.flow,
        &mut out.source_depth_in_target,
        &mut out.source_depth,
    ]
    .into_iter()
    .chain(out.links.iter_mut().flat_map(|l| [&mut l.flow, &mut l.depth]))
    {
        n += buf
            .par_chunks_mut(1 << 16)
            .map(|chunk| {
                // a branch-free scan first (vectorised): a repair is the rare case
                if chunk.iter().fold(true, |all, v| all & v.is_finite()) {
                    return 0;
                }
                let mut k = 0u64;
                for v in chunk.iter_mut().filter(|v| !v.is_finite()) {
                    *v = 0.0;
                    k += 1;
                }
                k
            })
            .sum::<u64>();
    }
    n
}
