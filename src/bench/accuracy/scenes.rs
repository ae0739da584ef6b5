//! The accuracy sweep's scenes with closed-form depth and the exact flow of the continuous scene.

#[allow(clippy::wildcard_imports)]
use super::*;
use crate::raster::morph::dilate;
use crate::raster::Grid;

// ---------------------------------------------------------------------------------------------
// Scenes

/// The closed-form depth of a scene, in the source camera. Depth is the z coordinate (the
/// distance along the unit-z ray `K^-1 p`), as the layering and the renderer use it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SceneGeometry {
    /// The plane `n . X = offset` (`n` unit, `offset > 0`).
    Plane { normal: DVec3, offset: f64 },
    /// A sphere in front of the fronto-parallel wall `Z = wall_z`.
    SphereWall { centre: DVec3, radius: f64, wall_z: f64 },
    /// The smooth synthetic depth of `tools/make_demo_depth.py` on a `width` x `height` grid:
    /// disparity `0.25 + 0.35 t + 0.35 exp(-(((s - 0.52) / 0.22)^2 + ((t - 0.42) / 0.3)^2))`,
    /// `s = x / (W - 1)`, `t = y / (H - 1)`.
    SmoothBump { width: usize, height: usize },
}

impl SceneGeometry {
    /// Depth at the (continuous) source pixel (x, y); +inf where the ray meets nothing.
    pub fn depth_at(&self, k: &Intrinsics, x: f64, y: f64) -> f64 {
        match *self {
            SceneGeometry::Plane { normal, offset } => {
                let nu = normal.dot(k.unproject(x, y));
                if nu > 1e-12 {
                    offset / nu
                } else {
                    f64::INFINITY
                }
            }
            SceneGeometry::SphereWall { centre, radius, wall_z } => {
                sphere_hit(k.unproject(x, y), centre, radius).map_or(wall_z, |z| z.min(wall_z))
            }
            SceneGeometry::SmoothBump { width, height } => {
                let s = x / (width.max(2) - 1) as f64;
                let t = y / (height.max(2) - 1) as f64;
                let disp = 0.25 + 0.35 * t + 0.35 * (-(((s - 0.52) / 0.22).powi(2) + ((t - 0.42) / 0.3).powi(2))).exp();
                if disp > 1e-9 {
                    1.0 / disp
                } else {
                    f64::INFINITY
                }
            }
        }
    }
}

/// Depth (z) of the first intersection of the ray `z u` (unit-z direction u, z > 0) with a sphere.
fn sphere_hit(u: DVec3, centre: DVec3, radius: f64) -> Option<f64> {
    let a = u.length_squared();
    let b = u.dot(centre);
    let disc = b * b - a * (centre.length_squared() - radius * radius);
    if disc < 0.0 {
        return None;
    }
    let z = (b - disc.sqrt()) / a;
    (z > 0.0).then_some(z)
}

/// A scene in the source camera: its image, its depth at the pixel centres and the closed form.
#[derive(Clone, Debug)]
pub struct Scene {
    pub name: String,
    pub width: usize,
    pub height: usize,
    /// `Intrinsics::reference_default(width, height)`.
    pub k: Intrinsics,
    pub geometry: SceneGeometry,
    /// H x W x 3 in [0, 1].
    pub rgb: Vec<f32>,
    /// H x W depth at the pixel centres (z, source camera).
    pub depth: Vec<f32>,
}

impl Scene {
    fn from_fn(
        name: &str,
        width: usize,
        height: usize,
        geometry: SceneGeometry,
        colour: impl Fn(DVec3) -> [f64; 3] + Sync,
    ) -> Scene {
        let k = Intrinsics::reference_default(width, height);
        let mut rgb = vec![0.0f32; width * height * 3];
        let mut depth = vec![0.0f32; width * height];
        rgb.par_chunks_mut(3 * width.max(1)).zip(depth.par_chunks_mut(width.max(1))).enumerate().for_each(
            |(y, (crow, drow))| {
                for x in 0..width {
                    let z = geometry.depth_at(&k, x as f64, y as f64);
                    drow[x] = z as f32;
                    let c = colour(k.unproject(x as f64, y as f64) * z);
                    for ch in 0..3 {
                        crow[3 * x + ch] = c[ch].clamp(0.0, 1.0) as f32;
                    }
                }
            },
        );
        Scene { name: name.into(), width, height, k, geometry, rgb, depth }
    }

    /// Closed-form depth at the continuous source pixel (x, y).
    pub fn depth_at(&self, x: f64, y: f64) -> f64 {
        self.geometry.depth_at(&self.k, x, y)
    }
}

/// A smooth checker: +-1 plateaus with soft edges of about a tenth of a period.
fn soft_checker(a: f64, b: f64, period: f64) -> f64 {
    let tau = std::f64::consts::TAU;
    (3.0 * (tau * a / period).sin() * (tau * b / period).sin()).tanh()
}

/// Normal of the tilted plane: 24 degrees about the x axis (ground-like, nearer at the bottom)
/// and 4 degrees about the y axis (nearer on the right); the normal is 24.6 degrees off the
/// optical axis.
pub fn tilted_plane_normal() -> DVec3 {
    let t = 24f64.to_radians();
    DVec3::new(0.07, t.sin(), t.cos()).normalize()
}

/// (a) A textured plane tilted towards the camera, depth from 1.5 (nearest pixel) to about 4 at
/// the reference intrinsics.
pub fn tilted_plane_scene(width: usize, height: usize) -> Scene {
    let k = Intrinsics::reference_default(width, height);
    let n = tilted_plane_normal();
    let (w1, h1) = ((width.max(1) - 1) as f64, (height.max(1) - 1) as f64);
    let max_nu = [(0.0, 0.0), (w1, 0.0), (0.0, h1), (w1, h1)]
        .iter()
        .map(|&(x, y)| n.dot(k.unproject(x, y)))
        .fold(f64::MIN, f64::max);
    let offset = 1.5 * max_nu;
    // in-plane axes for the texture
    let e1 = (DVec3::X - n * n.x).normalize();
    let e2 = n.cross(e1);
    Scene::from_fn("tilted plane", width, height, SceneGeometry::Plane { normal: n, offset }, move |p| {
        let (a, b) = (p.dot(e1), p.dot(e2));
        let tau = std::f64::consts::TAU;
        [
            0.5 + 0.4 * soft_checker(a, b, 0.3),
            0.5 + 0.3 * (tau * (a + b) / 0.45).cos(),
            0.5 + 0.35 * (tau * a / 0.7 + 1.0).sin() * (tau * b / 0.9).cos(),
        ]
    })
}

/// (b) A textured sphere (radius 0.6, centre at z = 2) in front of a textured wall at z = 4.
pub fn sphere_scene(width: usize, height: usize) -> Scene {
    let (centre, radius, wall_z) = (DVec3::new(0.12, 0.05, 2.0), 0.6, 4.0);
    Scene::from_fn("sphere + wall", width, height, SceneGeometry::SphereWall { centre, radius, wall_z }, move |p| {
        let tau = std::f64::consts::TAU;
        if p.z < wall_z - 1e-9 {
            let d = (p - centre) / radius;
            let lon = d.x.atan2(-d.z);
            let lat = d.y.clamp(-1.0, 1.0).asin();
            [
                0.55 + 0.4 * soft_checker(lon, lat, 0.55),
                0.45 + 0.3 * (5.0 * lat).sin(),
                0.5 + 0.3 * (7.0 * lon + 2.0 * lat).cos(),
            ]
        } else {
            [
                0.5 + 0.3 * (tau * p.x / 0.5).sin() * (tau * p.y / 0.6).sin(),
                0.5 + 0.4 * soft_checker(p.x, p.y, 0.4),
                0.5 + 0.3 * (tau * (p.x - p.y) / 0.8).cos(),
            ]
        }
    })
}

/// (c) A photo with the smooth synthetic depth of `tools/make_demo_depth.py`; the photo is
/// resampled (bilinear) to `width` x `height`.
pub fn photo_scene(name: &str, photo: &RgbImage, width: usize, height: usize) -> Scene {
    let k = Intrinsics::reference_default(width, height);
    let geometry = SceneGeometry::SmoothBump { width, height };
    let rgb = resize_bilinear(photo, width, height);
    let depth =
        (0..width * height).map(|p| geometry.depth_at(&k, (p % width) as f64, (p / width) as f64) as f32).collect();
    Scene { name: name.into(), width, height, k, geometry, rgb, depth }
}

/// Loads a photo (PNG or JPEG) and makes the photo scene of it.
pub fn load_photo_scene(path: &Path, width: usize, height: usize) -> Result<Scene, AccuracyError> {
    let img = crate::io::image::load_rgb(path, &crate::io::image::ImageLimits::default())?;
    let name = path.file_stem().map_or_else(|| "photo".to_string(), |n| format!("photo ({})", n.to_string_lossy()));
    Ok(photo_scene(&name, &img, width, height))
}

/// Bilinear resampling with pixel-centre alignment (edge pixels clamped).
pub fn resize_bilinear(img: &RgbImage, width: usize, height: usize) -> Vec<f32> {
    let (sw, sh) = (img.width.max(1), img.height.max(1));
    let mut out = vec![0.0f32; width * height * 3];
    if img.data.len() < sw * sh * 3 {
        return out;
    }
    let (src, dst) = (Grid::new(sw, sh), Grid::new(width, height));
    let at = |x: usize, y: usize, c: usize| img.data[3 * src.index(x, y) + c];
    for y in 0..height {
        let fy = ((y as f64 + 0.5) * sh as f64 / height as f64 - 0.5).clamp(0.0, (sh - 1) as f64);
        let (y0, wy) = (fy.floor() as usize, (fy - fy.floor()) as f32);
        let y1 = (y0 + 1).min(sh - 1);
        for x in 0..width {
            let fx = ((x as f64 + 0.5) * sw as f64 / width as f64 - 0.5).clamp(0.0, (sw - 1) as f64);
            let (x0, wx) = (fx.floor() as usize, (fx - fx.floor()) as f32);
            let x1 = (x0 + 1).min(sw - 1);
            for c in 0..3 {
                let top = at(x0, y0, c) + wx * (at(x1, y0, c) - at(x0, y0, c));
                let bot = at(x0, y1, c) + wx * (at(x1, y1, c) - at(x0, y1, c));
                out[3 * dst.index(x, y) + c] = top + wy * (bot - top);
            }
        }
    }
    out
}

// ---------------------------------------------------------------------------------------------
// Exact flow of the continuous scene

/// The exact forward flow of a scene and the masks its errors are measured over.
#[derive(Clone, Debug)]
pub struct ExactFlow {
    pub width: usize,
    pub height: usize,
    /// H x W x 2 (u, v); 0 where not valid.
    pub flow: Vec<f64>,
    /// X' in front of the target camera and p + flow inside [0, W-1] x [0, H-1].
    pub valid: Vec<bool>,
    /// Hidden in the target view by the continuous scene (height field seen by the source).
    pub occluded: Vec<bool>,
    /// Within [`EDGE_RADIUS`] px (chessboard) of a depth discontinuity.
    pub near_edge: Vec<bool>,
}

/// Relative depth jump between 4-neighbours that counts as a discontinuity.
pub const EDGE_JUMP: f64 = 0.05;
/// Pixels this close (chessboard distance) to a discontinuity are left out of the edge-free EPE.
pub const EDGE_RADIUS: usize = 2;

impl ExactFlow {
    /// Valid and not occluded.
    pub fn visible(&self) -> Vec<bool> {
        self.valid.iter().zip(&self.occluded).map(|(&v, &o)| v && !o).collect()
    }

    /// Valid, not occluded and away from depth discontinuities.
    pub fn edge_free(&self) -> Vec<bool> {
        (0..self.valid.len()).map(|i| self.valid[i] && !self.occluded[i] && !self.near_edge[i]).collect()
    }
}

/// The exact flow of source pixel (x, y) at depth z: `pi(K (R z K^-1 p + t)) - p`, or `None`
/// when the point is not in front of the target camera.
pub fn exact_flow_at(k: &Intrinsics, pose: &Pose, x: f64, y: f64, z: f64) -> Option<(f64, f64)> {
    if !(z.is_finite() && z > 0.0) {
        return None;
    }
    let xt = pose.apply(k.unproject(x, y) * z);
    if xt.z.is_nan() || xt.z <= 1e-9 {
        return None;
    }
    Some((k.fx * xt.x / xt.z + k.cx - x, k.fy * xt.y / xt.z + k.cy - y))
}

/// Exact flow, validity, occlusion and discontinuity masks of a scene under a motion.
pub fn exact_flow(scene: &Scene, pose: &Pose) -> ExactFlow {
    let (w, h, k) = (scene.width, scene.height, scene.k);
    let n = w * h;
    let mut flow = vec![0.0f64; 2 * n];
    let mut valid = vec![false; n];
    let mut occluded = vec![false; n];
    let zmin = scene.depth.iter().filter(|z| z.is_finite() && **z > 0.0).fold(f64::INFINITY, |a, &z| a.min(z as f64));
    let centre = pose.target_centre_in_source();
    flow.par_chunks_mut(2 * w).zip(valid.par_chunks_mut(w)).zip(occluded.par_chunks_mut(w)).enumerate().for_each(
        |(y, ((frow, vrow), orow))| {
            for x in 0..w {
                let (xf, yf) = (x as f64, y as f64);
                let z = scene.depth_at(xf, yf);
                let Some((u, v)) = exact_flow_at(&k, pose, xf, yf, z) else { continue };
                let (tx, ty) = (xf + u, yf + v);
                // (a rounding tolerance: the identity motion keeps border pixels inside)
                let tol = 1e-9 * (w + h) as f64;
                if !(tx >= -tol && tx <= (w - 1) as f64 + tol && ty >= -tol && ty <= (h - 1) as f64 + tol) {
                    continue;
                }
                frow[2 * x] = u;
                frow[2 * x + 1] = v;
                vrow[x] = true;
                orow[x] = occluded_in_heightfield(scene, k.unproject(xf, yf) * z, centre, zmin);
            }
        },
    );
    let near_edge = discontinuity_band(&scene.depth, w, h);
    ExactFlow { width: w, height: h, flow, valid, occluded, near_edge }
}

/// Whether the segment from the surface point `p` (source coordinates) to the target camera
/// centre passes behind the height field `depth_at` inside the source image.
fn occluded_in_heightfield(scene: &Scene, p: DVec3, centre: DVec3, zmin: f64) -> bool {
    let k = &scene.k;
    // the segment can only pass behind the surface while its depth exceeds the nearest depth
    let floor = 0.999 * zmin;
    let s_end = if centre.z >= floor { 1.0 } else { (p.z - floor) / (p.z - centre.z) };
    if s_end.is_nan() || s_end <= 0.0 {
        return false;
    }
    let q = p + (centre - p) * s_end.min(1.0);
    if q.z.is_nan() || q.z <= 0.0 {
        return false;
    }
    let proj = |v: DVec3| (k.fx * v.x / v.z + k.cx, k.fy * v.y / v.z + k.cy);
    let (a, b) = (proj(p), proj(q));
    let len = ((b.0 - a.0).powi(2) + (b.1 - a.1).powi(2)).sqrt();
    let steps = ((len / 0.5).ceil() as usize).clamp(1, 100_000);
    let (inv0, inv1) = (1.0 / p.z, 1.0 / q.z);
    let (lo, hx, hy) = (-0.5, scene.width as f64 - 0.5, scene.height as f64 - 0.5);
    for i in 1..=steps {
        let tau = i as f64 / steps as f64;
        let (x, y) = (a.0 + tau * (b.0 - a.0), a.1 + tau * (b.1 - a.1));
        if !(x >= lo && x < hx && y >= lo && y < hy) {
            break; // outside the source frustum the scene holds nothing
        }
        // 1/z is affine along the projected line
        let zs = 1.0 / (inv0 + tau * (inv1 - inv0));
        let zsurf = scene.depth_at(x, y);
        if zsurf.is_finite() && zs > zsurf * (1.0 + 1e-3) {
            return true;
        }
    }
    false
}

/// Pixels within [`EDGE_RADIUS`] of a 4-neighbour depth jump larger than [`EDGE_JUMP`].
pub fn discontinuity_band(depth: &[f32], w: usize, h: usize) -> Vec<bool> {
    let g = Grid::new(w, h);
    let mut jump = vec![false; g.len()];
    let big = |a: f32, b: f32| {
        let (a, b) = (a as f64, b as f64);
        !(a.is_finite() && b.is_finite()) || (a - b).abs() > EDGE_JUMP * a.min(b).abs()
    };
    for (x, y) in g.pixels() {
        let i = g.index(x, y);
        if x + 1 < w && big(depth[i], depth[i + 1]) {
            jump[i] = true;
            jump[i + 1] = true;
        }
        if y + 1 < h && big(depth[i], depth[i + w]) {
            jump[i] = true;
            jump[i + w] = true;
        }
    }
    dilate(w, h, &jump, EDGE_RADIUS)
}
