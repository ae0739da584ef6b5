//! Plane spacing: the depth of a plane and the gap between consecutive planes along a ray of
//! unit `z` direction, the one rule every compositor of an MPI uses (the exact renderer's source
//! view and its target-view cap, the layering's densities, the pre-blend, the scene stage's
//! composite disparity).
//!
//! - `depth_i = min(1 / disp_i, DEPTH_MAX)` (a plane at disparity 0 is very far, not infinite);
//! - `gap_i = min(depth_{i+1} - depth_i, DELTA_LAST)` for `i < N - 1`, `gap_{N-1} = DELTA_LAST`.
//!
//! Everything is f64 and evaluated in this order, so that each caller's results stay
//! bit-identical to the copies this module replaced. This module sits at the bottom of the
//! layering (it depends on nothing in the crate); `render` re-exports the constants.

/// Distance given to the last plane along a ray (the reference's 1e3), and the cap on any
/// plane gap so that infinite depths never reach the exponent.
pub const DELTA_LAST: f64 = 1e3;
/// Depths written to outputs are capped here (a plane at disparity 0 is infinitely far).
pub const DEPTH_MAX: f64 = 1e12;

/// The depth of a plane at disparity `disp`: `min(1 / disp, DEPTH_MAX)`.
#[inline]
pub fn plane_depth(disp: f64) -> f64 {
    (1.0 / disp).min(DEPTH_MAX)
}

/// The gap from every plane to the next one (`disparity` near to far) along a ray of unit `z`
/// direction, the last one [`DELTA_LAST`]; see the module documentation.
pub fn plane_gaps(disparity: &[f64]) -> Vec<f64> {
    let depth: Vec<f64> = disparity.iter().map(|&d| plane_depth(d)).collect();
    let n = depth.len();
    (0..n).map(|i| if i + 1 < n { (depth[i + 1] - depth[i]).min(DELTA_LAST) } else { DELTA_LAST }).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gaps_follow_the_rule() {
        let g = plane_gaps(&[1.0, 0.5, 0.0]);
        assert_eq!(g, vec![1.0, DELTA_LAST, DELTA_LAST]);
        assert_eq!(plane_depth(0.0), DEPTH_MAX);
        assert_eq!(plane_depth(0.25), 4.0);
        assert!(plane_gaps(&[]).is_empty());
        assert_eq!(plane_gaps(&[0.5]), vec![DELTA_LAST]);
    }
}
