//! Object masks aligned with their depth edges, once per scene: a segmentation model's (or a
//! hand-made) mask edge rarely falls exactly on the depth edge of the object, and every pixel
//! of disagreement becomes a streak when the object moves (object colour left behind in the
//! scene, or background colour carried along with the object).
//!
//! # Rule
//!
//! For each instance (mask value >= 1/2 inside), in the band of pixels within [`BAND`]
//! (chessboard) of its edge, on either side: the object's disparity `d_in` is pulled from the
//! mask's core (inside pixels farther than [`BAND`] from the edge) and the background's `d_out`
//! from the pixels farther than [`BAND`] outside, each by the push-pull fill of
//! [`crate::raster::pushpull`]. Where the object stands out (`d_in > (1 + `[`EDGE_STEP`]`) d_out`) a
//! band pixel belongs to the object (mask 1) when its own disparity is nearer `d_in` than
//! `d_out` (in ratio), else to the background (mask 0). Elsewhere (no depth step: the object
//! touches what is around it) the mask is kept as it is. Pixels of other instances are left
//! alone.

use crate::mpi::backdrop::EDGE_STEP;
use crate::raster::morph::dilate;
use crate::raster::pushpull::push_pull;
use crate::raster::InstanceMasks;

/// Half-width of the band around a mask's edge that is re-decided by depth, in pixels.
pub const BAND: usize = 3;

/// Aligns every mask of `masks` with the depth edges of `disparity` (H x W, > 0), in place.
/// Returns the number of pixels that changed side.
pub fn align_to_depth(masks: &mut InstanceMasks, disparity: &[f32]) -> usize {
    let (w, h) = (masks.width, masks.height);
    let n = w * h;
    if disparity.len() != n || n == 0 {
        return 0;
    }
    let disp: Vec<f64> = disparity.iter().map(|&d| f64::from(d)).collect();
    let owner: Vec<usize> = (0..n)
        .map(|p| masks.masks.iter().position(|m| m.mask.get(p).is_some_and(|&v| v >= 0.5)).unwrap_or(usize::MAX))
        .collect();
    let mut changed = 0;
    for (k, inst) in masks.masks.iter_mut().enumerate() {
        if inst.mask.len() != n {
            continue;
        }
        let inside: Vec<bool> = inst.mask.iter().map(|&v| v >= 0.5).collect();
        let outside: Vec<bool> = inside.iter().map(|&i| !i).collect();
        let near_out = dilate(w, h, &outside, BAND); // inside pixels within BAND of the edge, and outside
        let near_in = dilate(w, h, &inside, BAND);
        let core: Vec<bool> = near_out.iter().map(|&b| !b).collect();
        let far_out: Vec<bool> = near_in.iter().map(|&b| !b).collect();
        if !core.iter().any(|&c| c) || !far_out.iter().any(|&c| c) {
            continue;
        }
        let d_in = push_pull(&disp, &core, w, h);
        let d_out = push_pull(&disp, &far_out, w, h);
        for p in 0..n {
            let band = near_in[p] && near_out[p];
            if !band || (owner[p] != k && owner[p] != usize::MAX) {
                continue;
            }
            if !(d_in[p] > (1.0 + EDGE_STEP) * d_out[p] && d_out[p] > 0.0) {
                continue;
            }
            let d = disp[p].max(1e-12);
            let object = (d / d_in[p]).ln().abs() < (d / d_out[p]).ln().abs();
            let v = if object { 1.0 } else { 0.0 };
            if (inst.mask[p] >= 0.5) != object {
                changed += 1;
            }
            inst.mask[p] = v;
        }
    }
    changed
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raster::Instance;

    #[test]
    fn a_mask_two_pixels_short_of_its_object_grows_to_the_depth_edge_and_no_further() {
        let (w, h) = (40, 30);
        // object (disparity 1) on x in 10..30, background 0.25; the mask stops 2 px short on the
        // left and overshoots by 2 px on the right
        let disp: Vec<f32> = (0..w * h).map(|p| if (10..30).contains(&(p % w)) { 1.0 } else { 0.25 }).collect();
        let mask: Vec<f32> = (0..w * h).map(|p| if (12..32).contains(&(p % w)) { 1.0 } else { 0.0 }).collect();
        let mut m = InstanceMasks { width: w, height: h, masks: vec![Instance::new(1, 1.0, mask)] };
        let changed = align_to_depth(&mut m, &disp);
        assert_eq!(changed, 4 * h);
        for p in 0..w * h {
            assert_eq!(m.masks[0].mask[p] >= 0.5, (10..30).contains(&(p % w)), "pixel {p}");
        }
        // no depth step: nothing changes
        let flat = vec![0.5f32; w * h];
        let mask: Vec<f32> = (0..w * h).map(|p| if (12..32).contains(&(p % w)) { 1.0 } else { 0.0 }).collect();
        let mut m = InstanceMasks { width: w, height: h, masks: vec![Instance::new(1, 1.0, mask.clone())] };
        assert_eq!(align_to_depth(&mut m, &flat), 0);
        assert_eq!(m.masks[0].mask, mask);
    }
}
