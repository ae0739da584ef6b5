//! The reveal budget: how much of image2 an object's motion relative to the scene may uncover.
//!
//! A moving object uncovers the background it stood in front of; in a real clip between two
//! consecutive frames that is a sliver, while a motion law drawn independently of the object's
//! size can uncover a quarter of the frame for a large mask, all of it left to the background
//! fill and 2-D inpainting. A law with a budget ([`MotionRanges::reveal_budget`](super::motion::MotionRanges::reveal_budget)) draws a
//! budget `b` per object (from the object's own `Purpose::ObjectMotion(slot)` stream, after its
//! motion) and, when the drawn motion would uncover more than `b` of the frame, moves the object
//! by less:
//!
//! 1. **Relative motion.** With `C` the camera's pose and `P` the object's (image2 shows the
//!    object's pixels under `P`, the scene under `C`), the object's motion relative to the scene
//!    is `D = P C^-1`. `D_s` is `D` scaled by `s` in `[0, 1]` (axis-angle rotation and
//!    translation times `s`) and `P(s) = D_s C`: `P(1) = P`, and `P(0) = C` moves the object
//!    with the scene, which uncovers nothing.
//! 2. **Uncovered share** ([`uncovered_share`]). Every second pixel of the mask (value at
//!    least 0.5) in both directions (sparser for masks over 4 x [`MAX_SAMPLES`] pixels) is
//!    carried, at its disparity, into image2 under `C` (where the background it hid goes) and
//!    under `P(s)` (where the object goes); each marks the cell of the frame it lands in (cells
//!    of twice the sampling step, 4 x 4 pixels for every second pixel). The share is the area of the cells
//!    the background reaches and the object does not, over the frame's area: an estimate of the
//!    `revealed` share that `mpiflow bench quality --realism` measures on the rendered sample.
//! 3. **Fit** ([`fit_scale`]). `s = 1` when its share is within the budget; otherwise the
//!    largest `s` found by [`BISECTIONS`] halvings of `[0, 1]` whose share is within it (0 at
//!    worst). The sample records the motion actually applied.
//!
//! Everything is a pure function of the drawn numbers, the mask and the disparity: the same
//! address gives the same motion on every machine and thread count.

use glam::{DMat3, DVec3};

use super::motion::axis_angle_from_matrix;
use crate::geometry::{rotation_from_axis_angle, Intrinsics, Pose};
use crate::raster::Grid;

/// Most mask samples carried: larger masks are sampled more sparsely.
pub const MAX_SAMPLES: usize = 16_384;
/// Halvings of the scale interval when the drawn motion is over budget.
pub const BISECTIONS: usize = 8;

/// The pose `P(s) = D_s C` of module step 1.
pub fn scaled_pose(camera: &Pose, object: &Pose, s: f64) -> Pose {
    let d = object.compose(&camera.inverse());
    let aa = axis_angle_from_matrix(&d.rotation) * s;
    let ds = Pose { rotation: rotation_from_axis_angle(aa), translation: d.translation * s };
    ds.compose(camera)
}

/// The mask's samples of step 2: each a ray direction `K^-1 p` (unit z) and its disparity.
pub struct MaskSamples {
    rays: Vec<(DVec3, f64)>,
    width: usize,
    height: usize,
    k: Intrinsics,
    /// side of the counting cells: twice the sampling step, so that no cell a moved mask
    /// covers (unless magnified twofold) is left without a sample
    cell: usize,
}

impl MaskSamples {
    /// Every `step`-th pixel of `mask` (W x H, value at least 0.5) in x and y with its disparity
    /// (non-finite or negative disparities count as 0: very far); `step` is 2, or more when
    /// needed to keep at most [`MAX_SAMPLES`].
    pub fn new(mask: &[f32], disparity: &[f32], width: usize, height: usize, k: Intrinsics) -> Self {
        let area = mask.iter().filter(|&&m| m >= 0.5).count();
        let step = ((area as f64 / MAX_SAMPLES as f64).sqrt().ceil() as usize).max(2);
        let frame = Grid::new(width, height);
        let mut rays = Vec::new();
        for y in (0..height).step_by(step) {
            for x in (0..width).step_by(step) {
                let i = frame.index(x, y);
                if mask[i] >= 0.5 {
                    let d = f64::from(disparity[i]);
                    let d = if d.is_finite() && d > 0.0 { d } else { 0.0 };
                    rays.push((k.unproject(x as f64, y as f64), d));
                }
            }
        }
        Self { rays, width, height, k, cell: 2 * step }
    }

    /// The grid of the frame's cells.
    fn cells_grid(&self) -> Grid {
        Grid::new(self.width.div_ceil(self.cell), self.height.div_ceil(self.cell))
    }

    /// The cells the samples land in under `pose` (`K R ray + K t disp`, homogeneous; points
    /// behind the camera mark nothing).
    fn cells(&self, pose: &Pose) -> Vec<bool> {
        let cells = self.cells_grid();
        let mut out = vec![false; cells.len()];
        let k: DMat3 = self.k.matrix();
        let (kr, kt) = (k * pose.rotation, k * pose.translation);
        let (w, h) = (self.width as f64, self.height as f64);
        for &(ray, disp) in &self.rays {
            let p = kr * ray + kt * disp;
            // behind the camera or NaN: marks nothing
            if p.z.is_nan() || p.z <= 1e-9 {
                continue;
            }
            let (x, y) = (p.x / p.z + 0.5, p.y / p.z + 0.5);
            if x >= 0.0 && y >= 0.0 && x < w && y < h {
                let (cx, cy) = (x as usize / self.cell, y as usize / self.cell);
                if cx < cells.w && cy < cells.h {
                    out[cells.index(cx, cy)] = true;
                }
            }
        }
        out
    }

    /// The share of the frame in the cells of `behind` that the samples under `object` miss.
    fn share_missed(&self, behind: &[bool], object: &Pose) -> f64 {
        let covered = self.cells(object);
        let cells = behind.iter().zip(&covered).filter(|(&b, &c)| b && !c).count();
        let area = (self.width * self.height) as f64;
        ((cells * self.cell * self.cell) as f64 / area).min(1.0)
    }
}

/// Module step 2: the share of the frame the background behind the mask reaches under `camera`
/// and the object under `object` does not cover.
pub fn uncovered_share(samples: &MaskSamples, camera: &Pose, object: &Pose) -> f64 {
    samples.share_missed(&samples.cells(camera), object)
}

/// Module step 3: the scale of the object's relative motion that keeps its uncovered share
/// within `budget`.
pub fn fit_scale(samples: &MaskSamples, camera: &Pose, object: &Pose, budget: f64) -> f64 {
    let behind = samples.cells(camera);
    let within = |s: f64| samples.share_missed(&behind, &scaled_pose(camera, object, s)) <= budget;
    if within(1.0) {
        return 1.0;
    }
    let (mut lo, mut hi) = (0.0, 1.0);
    for _ in 0..BISECTIONS {
        let mid = 0.5 * (lo + hi);
        if within(mid) {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    lo
}

#[cfg(test)]
mod tests {
    use super::*;

    fn square(w: usize, h: usize, x0: usize, x1: usize) -> Vec<f32> {
        (0..w * h).map(|i| if (x0..x1).contains(&(i % w)) && (x0..x1).contains(&(i / w)) { 1.0 } else { 0.0 }).collect()
    }

    #[test]
    fn scaled_pose_interpolates_between_the_scene_and_the_object() {
        let camera = Pose::from_axis_angle([0.01, -0.02, 0.005], [0.1, -0.05, -0.2]);
        let object = Pose::from_axis_angle([-0.03, 0.01, 0.02], [-0.04, 0.03, 0.05]);
        let close = |a: &Pose, b: &Pose| {
            a.rotation.abs_diff_eq(b.rotation, 1e-12) && a.translation.abs_diff_eq(b.translation, 1e-12)
        };
        assert!(close(&scaled_pose(&camera, &object, 1.0), &object));
        assert!(close(&scaled_pose(&camera, &object, 0.0), &camera));
    }

    #[test]
    fn the_share_is_zero_with_the_scene_and_grows_with_the_motion() {
        let (w, h) = (128, 96);
        let k = Intrinsics::reference_default(w, h);
        let mask = square(w, h, 40, 72);
        let disp = vec![0.5f32; w * h];
        let s = MaskSamples::new(&mask, &disp, w, h, k);
        let camera = Pose::from_axis_angle([0.0; 3], [0.02, 0.0, 0.0]);
        assert_eq!(uncovered_share(&s, &camera, &camera), 0.0);
        let small = Pose::from_axis_angle([0.0; 3], [0.1, 0.0, 0.0]);
        let large = Pose::from_axis_angle([0.0; 3], [0.4, 0.0, 0.0]);
        let (a, b) = (uncovered_share(&s, &camera, &small), uncovered_share(&s, &camera, &large));
        assert!(a > 0.0 && b > a, "{a} {b}");
        // the mask is 32 x 32 of 128 x 96: it can uncover at most its own area (plus cell rounding)
        assert!(b <= (36.0 * 36.0) / (128.0 * 96.0), "{b}");
    }

    #[test]
    fn fitting_keeps_the_share_within_the_budget_and_leaves_small_motions_alone() {
        let (w, h) = (128, 96);
        let k = Intrinsics::reference_default(w, h);
        let s = MaskSamples::new(&square(w, h, 30, 80), &vec![1.0f32; w * h], w, h, k);
        let camera = Pose::identity();
        let object = Pose::from_axis_angle([0.0, 0.05, 0.0], [0.3, -0.1, 0.1]);
        let full = uncovered_share(&s, &camera, &object);
        assert!(full > 0.05, "{full}");
        let scale = fit_scale(&s, &camera, &object, 0.02);
        assert!(scale > 0.0 && scale < 1.0, "{scale}");
        assert!(uncovered_share(&s, &camera, &scaled_pose(&camera, &object, scale)) <= 0.02);
        assert_eq!(fit_scale(&s, &camera, &object, full), 1.0);
        // an empty mask uncovers nothing
        let none = MaskSamples::new(&vec![0.0; w * h], &vec![1.0f32; w * h], w, h, k);
        assert_eq!(fit_scale(&none, &camera, &object, 0.0), 1.0);
    }
}
