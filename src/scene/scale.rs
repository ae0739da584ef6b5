//! The scene scale, and how every kind of depth input is brought to it.
//!
//! # The scene scale
//!
//! A scene's [`Disparity`] holds values in `[DISPARITY_FLOOR, 1]`: `1` is the nearest content,
//! at depth 1; depth = 1 / disparity. This is the scale of the public reference generator (its
//! disparity PNGs hold min-max normalised inverse depth, its MPI planes sit at
//! `linspace(1, 0.001, N + 2)[1:-1]`), and every motion preset (translations of 0.1 to 0.35,
//! object shifts of 0.05) is defined in it: a translation of 0.1 is a tenth of the distance to the
//! nearest content.
//!
//! # Inputs
//!
//! | input | conversion | geometry |
//! |---|---|---|
//! | metric (or any linear unit) depth `d` ([`GivenDepth::Depth`]: `.npy`, `.pfm`, 16-bit PNG, the bundled scenes) | `disparity = d_min / d`, `d_min` = the smallest known depth | exact, up to one global scale (the nearest known content is put at depth 1) |
//! | disparity in `[0, 1]` ([`GivenDepth::Disparity`]: 8-bit PNG / 255, 16-bit PNG / 65535) | as is (clamped to `[0, 1]`) | whatever the file holds; the reference reads its `disps/` this way |
//! | relative inverse depth from a network (MiDaS/DPT style, unknown shift and scale) | min-max normalised: `(v - min) / (max - min)` ([`normalise_relative`]) | affine-invariant output, so only the order and the rough shape of depth are meaningful; this is what the reference's disparity PNGs hold |
//!
//! Metric depth is scale-invariant under this rule: multiplying every depth by any `s > 0` gives
//! the same disparity (tested). Min-max normalisation is invariant under any positive affine map
//! of its input.
//!
//! # Unknown pixels and the floor
//!
//! A depth that is non-finite or `<= 0`, and a disparity or relative value that is non-finite,
//! is *unknown*. Unknown pixels are filled from their nearest known pixel ([`fill_nearest`]: a
//! multi-source breadth-first search over the 8-neighbourhood, nearest in the chessboard metric,
//! ties to the source found first in row-major order, so the result is deterministic; the same
//! rule as the built-in layering). Copying a neighbour's value never invents a depth between a
//! foreground and its background. A map with no known pixel at all is an error.
//!
//! Finally every value is clamped to `[DISPARITY_FLOOR, 1]`: the floor (the reference's farthest
//! plane, 0.001) keeps depth finite (at most 1000) for sky and other far content; metric depths
//! more than 1000 times the nearest depth are pulled in to that distance.

use super::{Disparity, SceneError};
use crate::raster::Grid;
use crate::source::{FailureKind, GivenDepth};

/// A depth problem of the item's data.
fn depth_err(message: String) -> SceneError {
    SceneError::Data { kind: FailureKind::Depth, message }
}
use std::collections::VecDeque;

/// The smallest disparity of a scene (depth 1000 times the nearest content), the reference's
/// farthest plane.
pub const DISPARITY_FLOOR: f32 = 0.001;

/// Brings depth shipped with a source to the scene scale (see the module documentation).
/// `width * height` must equal the map's length.
pub fn disparity_from_given(given: &GivenDepth, width: usize, height: usize) -> Result<Disparity, SceneError> {
    match given {
        GivenDepth::Depth(d) => disparity_from_depth(d, width, height).map(|(disp, _)| disp),
        GivenDepth::Disparity(d) => disparity_from_unit(d, width, height),
    }
}

/// Metric (any linear unit) depth to the scene scale: `d_min / d`, unknown pixels (non-finite or
/// `<= 0`) filled, floored. Returns the disparity and `d_min` (the depth that became 1).
pub fn disparity_from_depth(depth: &[f32], width: usize, height: usize) -> Result<(Disparity, f32), SceneError> {
    check_len(depth.len(), width, height, "depth")?;
    let known: Vec<bool> = depth.iter().map(|&d| d.is_finite() && d > 0.0).collect();
    let d_min = depth.iter().zip(&known).filter(|(_, &k)| k).map(|(&d, _)| d).fold(f32::INFINITY, f32::min);
    if !d_min.is_finite() {
        return Err(depth_err(format!(
            "depth map of {width} x {height} has no known pixel (every value is non-finite or <= 0)"
        )));
    }
    let dm = f64::from(d_min);
    let mut data: Vec<f32> =
        depth.iter().zip(&known).map(|(&d, &k)| if k { (dm / f64::from(d)) as f32 } else { 0.0 }).collect();
    fill_nearest(&mut data, &known, width, height);
    clamp_to_scale(&mut data);
    Ok((Disparity { width, height, data }, d_min))
}

/// Disparity already in `[0, 1]` (as the reference reads its disparity PNGs): kept as is,
/// non-finite values filled from their neighbours, then clamped to `[DISPARITY_FLOOR, 1]`.
pub fn disparity_from_unit(disp: &[f32], width: usize, height: usize) -> Result<Disparity, SceneError> {
    check_len(disp.len(), width, height, "disparity")?;
    let known: Vec<bool> = disp.iter().map(|d| d.is_finite()).collect();
    if !known.iter().any(|&k| k) {
        return Err(depth_err(format!("disparity map of {width} x {height} has no finite value")));
    }
    let mut data: Vec<f32> = disp.iter().map(|&d| if d.is_finite() { d } else { 0.0 }).collect();
    fill_nearest(&mut data, &known, width, height);
    clamp_to_scale(&mut data);
    Ok(Disparity { width, height, data })
}

/// Relative inverse depth (a depth network's output, larger = nearer, unknown shift and scale) to
/// the scene scale: min-max normalised over the finite values, so the nearest content gets 1 and
/// the farthest 0 (then the floor); non-finite values are filled from their neighbours. A
/// constant map puts everything at disparity 1.
pub fn normalise_relative(values: &[f32], width: usize, height: usize) -> Result<Disparity, SceneError> {
    check_len(values.len(), width, height, "relative depth")?;
    let known: Vec<bool> = values.iter().map(|v| v.is_finite()).collect();
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for (&v, _) in values.iter().zip(&known).filter(|(_, &k)| k) {
        lo = lo.min(f64::from(v));
        hi = hi.max(f64::from(v));
    }
    if lo > hi {
        return Err(depth_err(format!("relative depth of {width} x {height} has no finite value")));
    }
    let range = hi - lo;
    let mut data: Vec<f32> = values
        .iter()
        .zip(&known)
        .map(|(&v, &k)| match (k, range > 0.0) {
            (false, _) => 0.0,
            (true, true) => ((f64::from(v) - lo) / range) as f32,
            (true, false) => 1.0,
        })
        .collect();
    fill_nearest(&mut data, &known, width, height);
    clamp_to_scale(&mut data);
    Ok(Disparity { width, height, data })
}

/// Depth of a scene-scale disparity: `1 / max(disparity, DISPARITY_FLOOR)`, so always finite and
/// in `[1, 1000]` for values in the scene scale.
pub fn depth_from_disparity(disparity: &Disparity) -> Vec<f32> {
    disparity.data.iter().map(|&d| depth_of_disparity(d)).collect()
}

/// The depth of one scene-scale disparity value, as [`depth_from_disparity`].
#[inline]
pub fn depth_of_disparity(d: f32) -> f32 {
    1.0 / sanitize(d)
}

/// Checks that a disparity map claims to be in the scene scale: the right size and every value
/// finite in `[0, 1]` (values below the floor are allowed, they are floored when used).
pub fn check_scene_scale(d: &Disparity) -> Result<(), String> {
    if Some(d.data.len()) != d.width.checked_mul(d.height) {
        return Err(format!("{} values for {} x {} pixels", d.data.len(), d.width, d.height));
    }
    if let Some((i, v)) = d.data.iter().enumerate().find(|(_, v)| !(v.is_finite() && (0.0..=1.0).contains(*v))) {
        return Err(format!(
            "value {v} at pixel ({}, {}) is outside the scene scale [0, 1]",
            i % d.width.max(1),
            i / d.width.max(1)
        ));
    }
    Ok(())
}

/// Clamps every value to `[DISPARITY_FLOOR, 1]` (non-finite values become the floor).
pub fn clamp_to_scale(data: &mut [f32]) {
    for v in data.iter_mut() {
        *v = sanitize(*v);
    }
}

#[inline]
fn sanitize(d: f32) -> f32 {
    if d.is_nan() {
        DISPARITY_FLOOR
    } else {
        d.clamp(DISPARITY_FLOOR, 1.0)
    }
}

fn check_len(len: usize, width: usize, height: usize, what: &str) -> Result<(), SceneError> {
    if width == 0 || height == 0 || Some(len) != width.checked_mul(height) {
        return Err(depth_err(format!(
            "{what} map holds {len} values, its size {width} x {height} needs {}",
            width.saturating_mul(height)
        )));
    }
    Ok(())
}

/// Fills every pixel with `known[i] == false` with the value of its nearest known pixel: a
/// multi-source breadth-first search over the 8-neighbourhood seeded with all known pixels in
/// row-major order (nearest in the chessboard metric; ties go to the source found first in that
/// order), so the result is deterministic. Nothing changes when no pixel (or every pixel) is
/// known.
///
/// # Panics
/// If the lengths do not match `width * height`.
pub fn fill_nearest(values: &mut [f32], known: &[bool], width: usize, height: usize) {
    let n = width * height;
    assert!(values.len() == n && known.len() == n, "fill_nearest: sizes do not match {width} x {height}");
    if known.iter().all(|&k| k) || !known.iter().any(|&k| k) {
        return;
    }
    let g = Grid::new(width, height);
    let mut done = known.to_vec();
    let mut queue: VecDeque<usize> = (0..n).filter(|&i| known[i]).collect();
    while let Some(i) = queue.pop_front() {
        let (x, y) = g.xy(i);
        let v = values[i];
        for (nx, ny) in g.neighbours8(x, y) {
            let j = g.index(nx, ny);
            if !done[j] {
                done[j] = true;
                values[j] = v;
                queue.push_back(j);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fill_copies_nearest_known() {
        let mut v = vec![0.5, 0.0, 0.0, 0.0, 0.0, 0.9];
        let known = [true, false, false, false, false, true];
        fill_nearest(&mut v, &known, 3, 2);
        // (1, 0) and (1, 1) are 1 from (0, 0) and 1 from (2, 1): the first source in row-major
        // order wins; (2, 0) is only next to (2, 1)
        assert_eq!(v, vec![0.5, 0.5, 0.9, 0.5, 0.5, 0.9]);
    }

    #[test]
    fn relative_constant_and_nan() {
        let d = normalise_relative(&[3.0, f32::NAN, 3.0, 3.0], 2, 2).unwrap();
        assert_eq!(d.data, vec![1.0; 4]);
        assert!(normalise_relative(&[f32::NAN; 4], 2, 2).is_err());
        assert!(normalise_relative(&[1.0; 3], 2, 2).is_err());
    }
}
