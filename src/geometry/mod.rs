//! Camera geometry in f64: pinhole intrinsics, rigid poses (axis-angle), and the plane-induced
//! homographies H_i = K_t (R + t n^T / d_i) K_s^-1 that move a fronto-parallel source plane into
//! the target view. Conventions (docs/design.md): pixel centres at integer coordinates, x = column,
//! y = row, X_tgt = R X_src + t, plane normal n = (0, 0, 1) in the source camera.

use glam::{DMat3, DMat4, DVec3};

/// Pinhole intrinsics in pixels: K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

impl Intrinsics {
    pub fn new(fx: f64, fy: f64, cx: f64, cy: f64) -> Self {
        Self { fx, fy, cx, cy }
    }

    /// The public reference's default: fx = 0.58 W, fy = 0.58 H, cx = 0.5 W, cy = 0.5 H.
    pub fn reference_default(width: usize, height: usize) -> Self {
        let (w, h) = (width as f64, height as f64);
        Self::new(0.58 * w, 0.58 * h, 0.5 * w, 0.5 * h)
    }

    /// Usable intrinsics: finite, non-zero focal lengths, finite principal point.
    pub fn is_valid(&self) -> bool {
        self.fx.is_finite()
            && self.fy.is_finite()
            && self.cx.is_finite()
            && self.cy.is_finite()
            && self.fx.abs() > 1e-12
            && self.fy.abs() > 1e-12
    }

    pub fn matrix(&self) -> DMat3 {
        DMat3::from_cols(
            DVec3::new(self.fx, 0.0, 0.0),
            DVec3::new(0.0, self.fy, 0.0),
            DVec3::new(self.cx, self.cy, 1.0),
        )
    }

    pub fn inverse_matrix(&self) -> DMat3 {
        DMat3::from_cols(
            DVec3::new(1.0 / self.fx, 0.0, 0.0),
            DVec3::new(0.0, 1.0 / self.fy, 0.0),
            DVec3::new(-self.cx / self.fx, -self.cy / self.fy, 1.0),
        )
    }

    /// Reads K from a row-major 3x3 matrix; `None` when it is not of the pinhole form.
    pub fn from_row_major(m: &[f64; 9]) -> Option<Self> {
        let k = Self::new(m[0], m[4], m[2], m[5]);
        let zeros_ok = m[1].abs() < 1e-9 && m[3].abs() < 1e-9 && m[6].abs() < 1e-9 && m[7].abs() < 1e-9;
        ((m[8] - 1.0).abs() < 1e-9 && zeros_ok && k.is_valid()).then_some(k)
    }

    /// Ray direction K^-1 (x, y, 1) of pixel (x, y), with unit z.
    #[inline]
    pub fn unproject(&self, x: f64, y: f64) -> DVec3 {
        DVec3::new((x - self.cx) / self.fx, (y - self.cy) / self.fy, 1.0)
    }
}

/// A rigid motion from the source camera to the target camera: X_tgt = R X_src + t.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pose {
    pub rotation: DMat3,
    pub translation: DVec3,
}

impl Default for Pose {
    fn default() -> Self {
        Self::identity()
    }
}

impl Pose {
    pub fn identity() -> Self {
        Self { rotation: DMat3::IDENTITY, translation: DVec3::ZERO }
    }

    /// Rotation given as an axis-angle vector (direction = axis, length = angle in radians).
    pub fn from_axis_angle(axis_angle: [f64; 3], translation: [f64; 3]) -> Self {
        Self { rotation: rotation_from_axis_angle(DVec3::from(axis_angle)), translation: DVec3::from(translation) }
    }

    /// The upper 3x4 of a row-major 4x4 matrix G = [[R, t], [0, 1]].
    pub fn from_row_major_4x4(g: &[f64; 16]) -> Self {
        let m = DMat4::from_cols_array(g).transpose();
        Self { rotation: DMat3::from_mat4(m), translation: m.w_axis.truncate() }
    }

    pub fn is_finite(&self) -> bool {
        self.rotation.is_finite() && self.translation.is_finite()
    }

    /// `self` after `first`: X -> self(first(X)), the rotation `R_self R_first` and the translation
    /// `R_self t_first + t_self`.
    pub fn compose(&self, first: &Pose) -> Pose {
        Pose {
            rotation: self.rotation * first.rotation,
            translation: self.rotation * first.translation + self.translation,
        }
    }

    /// Inverse motion: X_src = R^T X_tgt - R^T t.
    pub fn inverse(&self) -> Self {
        let rt = self.rotation.transpose();
        Self { rotation: rt, translation: -(rt * self.translation) }
    }

    /// The target camera centre expressed in source coordinates: -R^T t.
    pub fn target_centre_in_source(&self) -> DVec3 {
        -(self.rotation.transpose() * self.translation)
    }

    #[inline]
    pub fn apply(&self, x: DVec3) -> DVec3 {
        self.rotation * x + self.translation
    }
}

/// Rodrigues' formula; exact for angle 0 and stable for tiny angles.
pub fn rotation_from_axis_angle(v: DVec3) -> DMat3 {
    let angle = v.length();
    if !angle.is_finite() || angle < 1e-300 {
        return DMat3::IDENTITY;
    }
    DMat3::from_axis_angle(v / angle, angle)
}

/// `K_t R K_s^-1`: how a rotation moves pixels at infinity, the part of every plane's homography
/// that does not depend on depth. Exactly the identity when the cameras are equal and `R` is the
/// identity, so a pure translation keeps pixel rows and columns exactly (a rectified stereo
/// pair's vertical flow is 0, not the 1e-14 of a rounded `K K^-1`).
pub fn pixel_rotation(k_src: &Intrinsics, k_tgt: &Intrinsics, rotation: &DMat3) -> DMat3 {
    if *rotation == DMat3::IDENTITY && k_src == k_tgt {
        return DMat3::IDENTITY;
    }
    k_tgt.matrix() * *rotation * k_src.inverse_matrix()
}

/// The homography of the plane Z = depth (source camera) from source to target pixels:
/// H = K_t (R + t n^T / depth) K_s^-1, n = (0, 0, 1).
pub fn plane_homography(k_src: &Intrinsics, k_tgt: &Intrinsics, pose: &Pose, depth: f64) -> DMat3 {
    let tn = DMat3::from_cols(DVec3::ZERO, DVec3::ZERO, pose.translation / depth);
    k_tgt.matrix() * (pose.rotation + tn) * k_src.inverse_matrix()
}

/// Applies a homography to a pixel and divides by the third coordinate. Returns the pixel and the
/// homogeneous scale w (w > 0 when the point lies in front of the target camera).
#[inline]
pub fn apply_homography(h: &DMat3, x: f64, y: f64) -> (f64, f64, f64) {
    let p = *h * DVec3::new(x, y, 1.0);
    (p.x / p.z, p.y / p.z, p.z)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identity_pose_gives_identity_homography() {
        let k = Intrinsics::reference_default(64, 48);
        let h = plane_homography(&k, &k, &Pose::identity(), 2.0);
        assert!((h - DMat3::IDENTITY).abs_diff_eq(DMat3::ZERO, 1e-12));
    }

    #[test]
    fn homography_maps_like_the_3d_point() {
        let ks = Intrinsics::new(50.0, 45.0, 31.5, 23.5);
        let kt = Intrinsics::new(60.0, 55.0, 30.0, 20.0);
        let pose = Pose::from_axis_angle([0.05, -0.02, 0.1], [0.1, -0.2, -0.3]);
        let d = 3.0;
        let h = plane_homography(&ks, &kt, &pose, d);
        for &(x, y) in &[(0.0, 0.0), (10.0, 7.0), (63.0, 47.0)] {
            let xs = ks.unproject(x, y) * d;
            let xt = pose.apply(xs);
            let (u, v, w) = apply_homography(&h, x, y);
            assert!((u - (kt.fx * xt.x / xt.z + kt.cx)).abs() < 1e-9);
            assert!((v - (kt.fy * xt.y / xt.z + kt.cy)).abs() < 1e-9);
            assert!((w - xt.z / d).abs() < 1e-12);
        }
        // and its inverse maps back
        let hi = h.inverse();
        let (u, v, _) = apply_homography(&h, 12.0, 9.0);
        let (x, y, _) = apply_homography(&hi, u, v);
        assert!((x - 12.0).abs() < 1e-9 && (y - 9.0).abs() < 1e-9);
    }

    #[test]
    fn axis_angle_matches_reference_vector() {
        // case_cam.npz of the shared reference vectors: G[:3,:3] for (0.021, -0.013, 0.008)
        let r = rotation_from_axis_angle(DVec3::new(0.021, -0.013, 0.008));
        let expect = [
            [0.99988347, -0.00813557, -0.01291449],
            [0.00786257, 0.99974751, -0.02104956],
            [0.01308249, 0.02094556, 0.999695],
        ];
        for (i, row) in expect.iter().enumerate() {
            for (j, &e) in row.iter().enumerate() {
                assert!((r.row(i)[j] - e).abs() < 1e-7, "R[{i}][{j}]");
            }
        }
    }

    #[test]
    fn pose_from_4x4_and_inverse() {
        let p = Pose::from_axis_angle([0.1, 0.2, -0.3], [1.0, 2.0, 3.0]);
        let mut g = [0.0; 16];
        for i in 0..3 {
            for j in 0..3 {
                g[i * 4 + j] = p.rotation.row(i)[j];
            }
            g[i * 4 + 3] = p.translation[i];
        }
        g[15] = 1.0;
        let q = Pose::from_row_major_4x4(&g);
        assert!(q.rotation.abs_diff_eq(p.rotation, 1e-15));
        assert!(q.translation.abs_diff_eq(p.translation, 1e-15));
        let x = DVec3::new(0.3, -0.4, 2.0);
        assert!(p.inverse().apply(p.apply(x)).abs_diff_eq(x, 1e-12));
    }
}
