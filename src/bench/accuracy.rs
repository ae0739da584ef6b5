//! Error against run time (`mpiflow bench accuracy`).
//!
//! Scenes with closed-form depth are layered into MPIs of N planes (hard and soft layering, with
//! the source camera's ray lengths, [`build_mpi_for_camera`]) and rendered under one camera
//! motion. Two errors are measured against the render time:
//!
//! - **Flow EPE**: the rendered forward flow against the exact per-pixel flow of the continuous
//!   scene, `X = depth(p) K^-1 p`, `X' = R X + t`, `flow = pi(K X') - p`, averaged over the pixels
//!   that are valid in the exact sense (X' in front of the target camera, `p + flow` inside the
//!   image) and visible in the target view. Visibility is decided in the continuous scene seen by
//!   the source camera, a height field (everything behind a visible surface is solid): the
//!   segment from the point to the target camera centre is marched in the source image (steps of
//!   half a pixel, depth interpolated perspective-correctly along it) and the point is occluded
//!   when the segment passes behind the surface. MPIs from networks blend flow across depth
//!   discontinuities, so the EPE is also reported without the pixels within 2 px of one.
//! - **Image MAE**: the rendered target image against an f64 render of the same scene with
//!   [`AccuracyConfig::reference_planes`] planes (soft layering, no work skipping), mean absolute
//!   error in [0, 1] units over the pixels where the reference coverage exceeds 0.99 (and PSNR).
//!
//! Everything here is a library function (scenes, exact flow, metrics, the sweep, the markdown
//! and plot writers); the CLI only calls them.

use crate::bench::{time_runs, Timing};
use crate::geometry::{Intrinsics, Pose};
use crate::io::image::{ImageError, RgbImage};
use crate::mpi::layering::{build_mpi_for_camera, Layering, LayeringOptions, ALPHA_MAX};
use crate::mpi::{Mpi, MpiError};
use crate::render::{render, Fields, Mode, Occupancy, Real, RenderError, RenderOutput, RenderParams, Skip, DELTA_LAST};
use glam::DVec3;
use rayon::prelude::*;
use std::fmt::Write as _;
use std::path::Path;

#[derive(Debug, thiserror::Error)]
pub enum AccuracyError {
    #[error(transparent)]
    Mpi(#[from] MpiError),
    #[error(transparent)]
    Render(#[from] RenderError),
    #[error(transparent)]
    Image(#[from] ImageError),
    #[error("{0}")]
    Invalid(String),
    #[error("plot: {0}")]
    Plot(String),
}

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
    let at = |x: usize, y: usize, c: usize| img.data[3 * (y * sw + x) + c];
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
                out[3 * (y * width + x) + c] = top + wy * (bot - top);
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
    let mut jump = vec![false; w * h];
    let big = |a: f32, b: f32| {
        let (a, b) = (a as f64, b as f64);
        !(a.is_finite() && b.is_finite()) || (a - b).abs() > EDGE_JUMP * a.min(b).abs()
    };
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            if x + 1 < w && big(depth[i], depth[i + 1]) {
                jump[i] = true;
                jump[i + 1] = true;
            }
            if y + 1 < h && big(depth[i], depth[i + w]) {
                jump[i] = true;
                jump[i + w] = true;
            }
        }
    }
    let r = EDGE_RADIUS;
    let mut band = vec![false; w * h];
    for y in 0..h {
        for x in 0..w {
            if !jump[y * w + x] {
                continue;
            }
            for yy in y.saturating_sub(r)..=(y + r).min(h - 1) {
                for xx in x.saturating_sub(r)..=(x + r).min(w - 1) {
                    band[yy * w + xx] = true;
                }
            }
        }
    }
    band
}

// ---------------------------------------------------------------------------------------------
// Metrics

/// Mean end-point error of a rendered flow (H x W x 2) against the exact flow over `mask`
/// (NaN when the mask is empty).
pub fn flow_epe(flow: &[f32], exact: &ExactFlow, mask: &[bool]) -> f64 {
    let (mut sum, mut count) = (0.0f64, 0usize);
    for (i, _) in mask.iter().enumerate().filter(|(_, &m)| m) {
        let du = flow[2 * i] as f64 - exact.flow[2 * i];
        let dv = flow[2 * i + 1] as f64 - exact.flow[2 * i + 1];
        sum += (du * du + dv * dv).sqrt();
        count += 1;
    }
    if count == 0 {
        f64::NAN
    } else {
        sum / count as f64
    }
}

/// Mean absolute error and PSNR of an image against a reference over the pixels where the
/// reference coverage exceeds [`COVERAGE_MIN`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImageErr {
    pub mae: f64,
    pub psnr: f64,
    pub pixels: usize,
}

pub const COVERAGE_MIN: f32 = 0.99;

pub fn image_error(image: &[f32], reference: &[f32], ref_coverage: &[f32]) -> ImageErr {
    let (mut abs, mut sq, mut count) = (0.0f64, 0.0f64, 0usize);
    for (i, _) in ref_coverage.iter().enumerate().filter(|(_, &c)| c > COVERAGE_MIN) {
        for c in 0..3 {
            let d = image[3 * i + c] as f64 - reference[3 * i + c] as f64;
            abs += d.abs();
            sq += d * d;
        }
        count += 1;
    }
    if count == 0 {
        return ImageErr { mae: f64::NAN, psnr: f64::NAN, pixels: 0 };
    }
    let m = (3 * count) as f64;
    let mse = sq / m;
    ImageErr { mae: abs / m, psnr: if mse > 0.0 { -10.0 * mse.log10() } else { f64::INFINITY }, pixels: count }
}

/// Largest and mean absolute difference of two equally long buffers.
pub fn abs_diff(a: &[f32], b: &[f32]) -> (f64, f64) {
    if a.is_empty() || a.len() != b.len() {
        return (f64::NAN, f64::NAN);
    }
    let (mut max, mut sum) = (0.0f64, 0.0f64);
    for (x, y) in a.iter().zip(b) {
        let d = (*x as f64 - *y as f64).abs();
        max = max.max(d);
        sum += d;
    }
    (max, sum / a.len() as f64)
}

/// Largest and mean end-point difference of two flows (H x W x 2).
pub fn flow_diff(a: &[f32], b: &[f32]) -> (f64, f64) {
    if a.is_empty() || a.len() != b.len() {
        return (f64::NAN, f64::NAN);
    }
    let (mut max, mut sum) = (0.0f64, 0.0f64);
    for (p, q) in a.chunks_exact(2).zip(b.chunks_exact(2)) {
        let d = ((p[0] as f64 - q[0] as f64).powi(2) + (p[1] as f64 - q[1] as f64).powi(2)).sqrt();
        max = max.max(d);
        sum += d;
    }
    (max, sum / (a.len() / 2) as f64)
}

/// Least-squares slope of ln(y) against ln(x) over the points with finite positive values
/// (NaN with fewer than two).
pub fn log_log_slope(points: &[(f64, f64)]) -> f64 {
    let pts: Vec<(f64, f64)> = points
        .iter()
        .filter(|(x, y)| x.is_finite() && y.is_finite() && *x > 0.0 && *y > 0.0)
        .map(|(x, y)| (x.ln(), y.ln()))
        .collect();
    if pts.len() < 2 {
        return f64::NAN;
    }
    let n = pts.len() as f64;
    let mx = pts.iter().map(|p| p.0).sum::<f64>() / n;
    let my = pts.iter().map(|p| p.1).sum::<f64>() / n;
    let sxy: f64 = pts.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    let sxx: f64 = pts.iter().map(|p| (p.0 - mx).powi(2)).sum();
    if sxx > 0.0 {
        sxy / sxx
    } else {
        f64::NAN
    }
}

// ---------------------------------------------------------------------------------------------
// The sweep

#[derive(Clone, Debug)]
pub struct AccuracyConfig {
    pub width: usize,
    pub height: usize,
    /// Timed runs per configuration (after one warm-up run); the median is reported.
    pub runs: usize,
    /// Plane counts of the main sweep.
    pub planes: Vec<usize>,
    /// Planes of the f64 image reference.
    pub reference_planes: usize,
    /// Plane counts (soft layering) at which the skipping variants, f32 against f64 and the
    /// reference mode are measured.
    pub detail_planes: Vec<usize>,
    pub pose: Pose,
}

impl AccuracyConfig {
    /// N in {4, 8, 16, 32, 64, 128}, a 256-plane reference, details at N = 32 and 64,
    /// [`crate::bench::bench_pose`].
    pub fn new(width: usize, height: usize, runs: usize) -> Self {
        Self {
            width,
            height,
            runs,
            planes: vec![4, 8, 16, 32, 64, 128],
            reference_planes: 256,
            detail_planes: vec![32, 64],
            pose: crate::bench::bench_pose(),
        }
    }
}

/// Time and errors of one render configuration.
#[derive(Clone, Copy, Debug)]
pub struct Measurement {
    /// Image + flow + depth (no occlusion pass), median of the timed runs.
    pub time: Timing,
    /// Flow EPE over valid, visible pixels.
    pub epe: f64,
    /// Flow EPE over valid, visible pixels away from depth discontinuities.
    pub epe_edge_free: f64,
    /// Image error against the f64 reference.
    pub image: ImageErr,
    /// Fraction of the target-view plane samples avoided by skipping.
    pub skipped: f64,
}

#[derive(Clone, Debug)]
pub struct SweepRow {
    pub scene: String,
    pub planes: usize,
    pub layering: Layering,
    pub m: Measurement,
}

#[derive(Clone, Debug)]
pub struct SkipRow {
    pub scene: String,
    pub planes: usize,
    pub name: String,
    pub skip: Skip,
    pub m: Measurement,
    /// (max, mean) |image - image without skipping|.
    pub image_diff: (f64, f64),
    /// (max, mean) end-point difference to the flow without skipping.
    pub flow_diff: (f64, f64),
}

#[derive(Clone, Debug)]
pub struct PrecisionRow {
    pub scene: String,
    pub planes: usize,
    pub f32: Measurement,
    pub f64: Measurement,
    pub image_diff: (f64, f64),
    pub flow_diff: (f64, f64),
}

#[derive(Clone, Debug)]
pub struct ReferenceModeRow {
    pub scene: String,
    pub planes: usize,
    /// Exact mode, default skipping.
    pub exact: Measurement,
    /// [`Mode::Reference`].
    pub reference: Measurement,
}

#[derive(Clone, Debug)]
pub struct SceneInfo {
    pub name: String,
    pub depth_min: f64,
    pub depth_max: f64,
    pub pixels: usize,
    pub valid: usize,
    pub visible: usize,
    pub edge_free: usize,
    /// Mean exact flow magnitude over the visible pixels (px).
    pub mean_flow: f64,
    /// Time of the f64 reference render (target view only, one run).
    pub reference_ms: f64,
}

#[derive(Clone, Debug)]
pub struct AccuracyReport {
    pub width: usize,
    pub height: usize,
    pub runs: usize,
    pub threads: usize,
    pub reference_planes: usize,
    pub pose: Pose,
    pub scenes: Vec<SceneInfo>,
    pub rows: Vec<SweepRow>,
    pub skips: Vec<SkipRow>,
    pub precision: Vec<PrecisionRow>,
    pub reference_mode: Vec<ReferenceModeRow>,
}

/// What a scene's measurements compare against.
struct SceneCtx<'a> {
    scene: &'a Scene,
    exact: ExactFlow,
    visible: Vec<bool>,
    edge_free: Vec<bool>,
    ref_image: Vec<f32>,
    ref_coverage: Vec<f32>,
}

fn layer(scene: &Scene, planes: usize, layering: Layering) -> Result<Mpi, AccuracyError> {
    let opts = LayeringOptions { planes, layering, disparity_range: None };
    Ok(build_mpi_for_camera(&scene.rgb, &scene.depth, scene.width, scene.height, &opts, &scene.k)?)
}

/// Renders image + flow + depth `runs` times (after a warm-up) and measures the last output.
fn measure<T: Real>(
    ctx: &SceneCtx,
    mpi: &Mpi,
    params: &RenderParams,
    occ: Option<&Occupancy>,
    runs: usize,
) -> Result<(Measurement, RenderOutput), AccuracyError> {
    let mut result: Option<Result<RenderOutput, RenderError>> = None;
    let time = time_runs(runs, || result = Some(render::<T>(mpi, params, occ)));
    let out = result.ok_or_else(|| AccuracyError::Invalid("no render ran".into()))??;
    let s = out.stats;
    let total = (s.samples + s.skipped_tile + s.skipped_early) as f64;
    let m = Measurement {
        time,
        epe: flow_epe(&out.flow, &ctx.exact, &ctx.visible),
        epe_edge_free: flow_epe(&out.flow, &ctx.exact, &ctx.edge_free),
        image: image_error(&out.image, &ctx.ref_image, &ctx.ref_coverage),
        skipped: if total > 0.0 { (s.skipped_tile + s.skipped_early) as f64 / total } else { 0.0 },
    };
    Ok((m, out))
}

fn params_for(scene: &Scene, pose: Pose, skip: Skip, mode: Mode) -> RenderParams {
    let mut p = RenderParams::new(scene.k, pose);
    p.mode = mode;
    p.skip = skip;
    p.fields = Fields { target: true, flow: true, occlusion: false };
    p
}

/// The work-skipping variants compared at the detail plane counts.
pub fn skip_variants() -> Vec<(&'static str, Skip)> {
    let t = |eps: f32| Skip { transmittance_eps: eps, ..Skip::NONE };
    vec![
        ("none", Skip::NONE),
        ("tiles", Skip { tiles: true, ..Skip::NONE }),
        ("early stop T<1e-4", t(1e-4)),
        ("early stop T<1e-3", t(1e-3)),
        ("early stop T<1e-2", t(1e-2)),
        ("tiles + T<1e-4 (default)", Skip::DEFAULT),
        ("tiles sigma<=1e-3 + T<1e-4", Skip { tile_sigma_eps: 1e-3, ..Skip::DEFAULT }),
        ("tiles sigma<=0.1 + T<1e-4", Skip { tile_sigma_eps: 0.1, ..Skip::DEFAULT }),
    ]
}

/// Runs the whole measurement over `scenes` in the current rayon pool. `progress` receives one
/// line per finished step.
pub fn run_accuracy(
    cfg: &AccuracyConfig,
    scenes: &[Scene],
    progress: &mut dyn FnMut(&str),
) -> Result<AccuracyReport, AccuracyError> {
    if cfg.width < 2 || cfg.height < 2 || cfg.planes.is_empty() {
        return Err(AccuracyError::Invalid("accuracy bench: the size must be at least 2x2 and N non-empty".into()));
    }
    let mut report = AccuracyReport {
        width: cfg.width,
        height: cfg.height,
        runs: cfg.runs,
        threads: rayon::current_num_threads(),
        reference_planes: cfg.reference_planes,
        pose: cfg.pose,
        scenes: Vec::new(),
        rows: Vec::new(),
        skips: Vec::new(),
        precision: Vec::new(),
        reference_mode: Vec::new(),
    };
    for scene in scenes {
        if scene.width != cfg.width || scene.height != cfg.height {
            return Err(AccuracyError::Invalid(format!(
                "scene `{}` is {}x{}, the bench is {}x{}",
                scene.name, scene.width, scene.height, cfg.width, cfg.height
            )));
        }
        let exact = exact_flow(scene, &cfg.pose);
        let visible = exact.visible();
        let edge_free = exact.edge_free();
        // the image reference: f64, soft, no skipping
        let mpi = layer(scene, cfg.reference_planes, Layering::Soft)?;
        let mut p = params_for(scene, cfg.pose, Skip::NONE, Mode::Exact);
        p.fields = Fields { target: true, flow: false, occlusion: false };
        let t0 = std::time::Instant::now();
        let reference = render::<f64>(&mpi, &p, None)?;
        let reference_ms = t0.elapsed().as_secs_f64() * 1e3;
        drop(mpi);
        let mean_flow = {
            let (mut s, mut c) = (0.0, 0usize);
            for (i, _) in visible.iter().enumerate().filter(|(_, &v)| v) {
                s += exact.flow[2 * i].hypot(exact.flow[2 * i + 1]);
                c += 1;
            }
            s / c.max(1) as f64
        };
        let finite = scene.depth.iter().filter(|z| z.is_finite()).map(|&z| z as f64);
        let (dmin, dmax) = finite.fold((f64::INFINITY, 0.0f64), |(a, b), z| (a.min(z), b.max(z)));
        report.scenes.push(SceneInfo {
            name: scene.name.clone(),
            depth_min: dmin,
            depth_max: dmax,
            pixels: scene.width * scene.height,
            valid: exact.valid.iter().filter(|&&v| v).count(),
            visible: visible.iter().filter(|&&v| v).count(),
            edge_free: edge_free.iter().filter(|&&v| v).count(),
            mean_flow,
            reference_ms,
        });
        progress(&format!(
            "{}: exact flow and {}-plane f64 reference ({reference_ms:.0} ms)",
            scene.name, cfg.reference_planes
        ));
        let ctx =
            SceneCtx { scene, exact, visible, edge_free, ref_image: reference.image, ref_coverage: reference.coverage };
        for &n in &cfg.planes {
            for layering in [Layering::Hard, Layering::Soft] {
                let mpi = layer(scene, n, layering)?;
                let occ = Occupancy::build(&mpi, 0.0);
                let p = params_for(scene, cfg.pose, Skip::DEFAULT, Mode::Exact);
                let (m, _) = measure::<f32>(&ctx, &mpi, &p, Some(&occ), cfg.runs)?;
                progress(&format!(
                    "{}: N={n:<3} {:<4} {:8.2} ms  EPE {:.4}  MAE {:.5}",
                    scene.name,
                    layering_name(layering),
                    m.time.median,
                    m.epe_edge_free,
                    m.image.mae
                ));
                report.rows.push(SweepRow { scene: scene.name.clone(), planes: n, layering, m });
                if layering == Layering::Soft && cfg.detail_planes.contains(&n) {
                    details(cfg, &ctx, &mpi, n, &mut report, progress)?;
                }
            }
        }
    }
    Ok(report)
}

/// Skipping variants, f32 against f64 and the reference mode for one soft MPI.
fn details(
    cfg: &AccuracyConfig,
    ctx: &SceneCtx,
    mpi: &Mpi,
    n: usize,
    report: &mut AccuracyReport,
    progress: &mut dyn FnMut(&str),
) -> Result<(), AccuracyError> {
    let scene = ctx.scene;
    let none_params = params_for(scene, cfg.pose, Skip::NONE, Mode::Exact);
    let (m_none, out_none) = measure::<f32>(ctx, mpi, &none_params, None, cfg.runs)?;
    for (name, skip) in skip_variants() {
        let (m, out) = if skip == Skip::NONE {
            (m_none, None)
        } else {
            let occ = skip.tiles.then(|| Occupancy::build(mpi, skip.tile_sigma_eps));
            let p = params_for(scene, cfg.pose, skip, Mode::Exact);
            let (m, out) = measure::<f32>(ctx, mpi, &p, occ.as_ref(), cfg.runs)?;
            (m, Some(out))
        };
        let o = out.as_ref().unwrap_or(&out_none);
        report.skips.push(SkipRow {
            scene: scene.name.clone(),
            planes: n,
            name: name.into(),
            skip,
            m,
            image_diff: abs_diff(&o.image, &out_none.image),
            flow_diff: flow_diff(&o.flow, &out_none.flow),
        });
    }
    progress(&format!("{}: N={n} skipping variants", scene.name));
    let (m64, out64) = measure::<f64>(ctx, mpi, &none_params, None, cfg.runs)?;
    report.precision.push(PrecisionRow {
        scene: scene.name.clone(),
        planes: n,
        f32: m_none,
        f64: m64,
        image_diff: abs_diff(&out_none.image, &out64.image),
        flow_diff: flow_diff(&out_none.flow, &out64.flow),
    });
    progress(&format!("{}: N={n} f32 against f64", scene.name));
    let p = params_for(scene, cfg.pose, Skip::NONE, Mode::Reference);
    let (m_ref, _) = measure::<f32>(ctx, mpi, &p, None, cfg.runs)?;
    let exact = report
        .rows
        .iter()
        .rev()
        .find(|r| r.scene == scene.name && r.planes == n && r.layering == Layering::Soft)
        .map(|r| r.m)
        .unwrap_or(m_none);
    report.reference_mode.push(ReferenceModeRow { scene: scene.name.clone(), planes: n, exact, reference: m_ref });
    progress(&format!("{}: N={n} reference mode", scene.name));
    Ok(())
}

pub fn layering_name(l: Layering) -> &'static str {
    match l {
        Layering::Hard => "hard",
        Layering::Soft => "soft",
    }
}

// ---------------------------------------------------------------------------------------------
// Convergence orders

/// The observed convergence of one error with the number of planes: error ~ N^slope.
#[derive(Clone, Debug)]
pub struct Order {
    pub scene: String,
    pub layering: Layering,
    pub metric: &'static str,
    pub slope: f64,
    pub n_min: usize,
    pub n_max: usize,
}

/// Flow errors below this are left out of the convergence fits when the report has no f32 against
/// f64 rows to measure the rounding floor from (see [`epe_fit_floor`]).
pub const EPE_FIT_FLOOR: f64 = 1e-4;

/// Flow errors below the floor no longer follow N: ten times the largest mean end-point
/// difference between f32 and f64 renders of the same MPI, or [`EPE_FIT_FLOOR`] without such rows.
pub fn epe_fit_floor(report: &AccuracyReport) -> f64 {
    let m = report.precision.iter().map(|r| r.flow_diff.1).filter(|v| v.is_finite()).fold(f64::NAN, f64::max);
    if m.is_finite() && m > 0.0 {
        10.0 * m
    } else {
        EPE_FIT_FLOOR
    }
}

pub const METRIC_EPE: &str = "flow EPE (edge-free)";
pub const METRIC_EPE_ALL: &str = "flow EPE (visible)";
pub const METRIC_MAE: &str = "image MAE";

/// Reads one error out of a measurement.
type Metric = fn(&Measurement) -> f64;

/// Least-squares slopes of log(error) against log(N), per scene, layering and metric, over the
/// whole sweep, leaving out flow errors below [`epe_fit_floor`]. The image MAE is fitted over
/// N <= reference_planes / 4 only: close to the reference's own N the error to the reference
/// falls faster than the error to the truth.
pub fn convergence_orders(report: &AccuracyReport) -> Vec<Order> {
    let mut out = Vec::new();
    let floor = epe_fit_floor(report);
    for s in &report.scenes {
        for layering in [Layering::Hard, Layering::Soft] {
            let rows: Vec<&SweepRow> =
                report.rows.iter().filter(|r| r.scene == s.name && r.layering == layering).collect();
            if rows.len() < 2 {
                continue;
            }
            let metrics: [(&'static str, Metric, usize, f64); 3] = [
                (METRIC_EPE, |m| m.epe_edge_free, usize::MAX, floor),
                (METRIC_EPE_ALL, |m| m.epe, usize::MAX, floor),
                (METRIC_MAE, |m| m.image.mae, (report.reference_planes / 4).max(2), 0.0),
            ];
            for (metric, f, nmax, floor) in metrics {
                let sel: Vec<&&SweepRow> = rows.iter().filter(|r| r.planes <= nmax && f(&r.m) >= floor).collect();
                let pts: Vec<(f64, f64)> = sel.iter().map(|r| (r.planes as f64, f(&r.m))).collect();
                out.push(Order {
                    scene: s.name.clone(),
                    layering,
                    metric,
                    slope: log_log_slope(&pts),
                    n_min: sel.iter().map(|r| r.planes).min().unwrap_or(0),
                    n_max: sel.iter().map(|r| r.planes).max().unwrap_or(0),
                });
            }
        }
    }
    out
}

// ---------------------------------------------------------------------------------------------
// Markdown

/// Facts about how the report was made, written at its top.
#[derive(Clone, Debug, Default)]
pub struct ReportMeta {
    /// The exact command that generated the report.
    pub command: String,
    /// The machine in words (cores, CPU model).
    pub machine: String,
    /// File name of the plot, relative to the markdown (empty: no plot link).
    pub plot: String,
    /// Wall time of the whole run, seconds (0: not stated).
    pub total_s: f64,
}

/// "N cores (nproc), CPU model" from `/proc/cpuinfo` where available.
pub fn machine_description() -> String {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let model = std::fs::read_to_string("/proc/cpuinfo").ok().and_then(|s| {
        s.lines().find(|l| l.starts_with("model name")).and_then(|l| l.split(':').nth(1)).map(|m| m.trim().to_string())
    });
    match model {
        Some(m) => format!("{cores} cores (nproc) of {m}, {}", std::env::consts::ARCH),
        None => format!("{cores} cores (nproc), {}", std::env::consts::ARCH),
    }
}

/// `digits` significant digits; scientific notation below 1e-3.
fn sig(v: f64, digits: usize) -> String {
    if v == 0.0 {
        "0".into()
    } else if !v.is_finite() {
        f(v, 0)
    } else if v.abs() >= 1e-3 {
        let decimals = (digits as i32 - 1 - v.abs().log10().floor() as i32).max(0) as usize;
        format!("{v:.decimals$}")
    } else {
        format!("{v:.prec$e}", prec = digits.saturating_sub(1))
    }
}

fn f(v: f64, digits: usize) -> String {
    if v.is_finite() {
        format!("{v:.digits$}")
    } else if v.is_nan() {
        "n/a".into()
    } else {
        "inf".into()
    }
}

/// Scientific notation for small differences.
fn e(v: f64) -> String {
    if v == 0.0 {
        "0".into()
    } else if v.is_finite() {
        format!("{v:.1e}")
    } else {
        "n/a".into()
    }
}

fn order_of<'a>(orders: &'a [Order], scene: &str, layering: Layering, metric: &str) -> Option<&'a Order> {
    orders.iter().find(|o| o.scene == scene && o.layering == layering && o.metric == metric)
}

/// The report as markdown: settings, definitions, the main table, the convergence orders, the
/// skipping trade-offs, f32 against f64 and the reference mode.
pub fn markdown(report: &AccuracyReport, meta: &ReportMeta) -> String {
    let mut s = String::new();
    let orders = convergence_orders(report);
    let _ = writeln!(s, "# Error against run time\n");
    let _ = writeln!(s, "Generated by\n\n```\n{}\n```\n", meta.command);
    let t = report.pose.translation;
    let _ = writeln!(
        s,
        "- Machine: {}; renders use {} rayon threads. Times are medians of {} runs after one warm-up, \
         image + flow + depth in one call (`Fields {{ target: true, flow: true, occlusion: false }}`), \
         the occupancy prebuilt per MPI as the service caches it; building the MPI is not timed.",
        meta.machine, report.threads, report.runs
    );
    let _ = writeln!(
        s,
        "- Size {}x{}, K = `Intrinsics::reference_default` (fx = 0.58 W, fy = 0.58 H, principal point at the centre), \
         motion `bench::bench_pose()`: t = ({}, {}, {}), axis-angle (0.021, -0.013, 0.008).",
        report.width, report.height, t.x, t.y, t.z
    );
    let _ = writeln!(
        s,
        "- MPIs are built with `build_mpi_for_camera` (planes uniform in disparity over the scene's own range) and rendered \
         in exact mode, f32, default skipping (`Skip::DEFAULT`: empty tiles, early stop at transmittance 1e-4) unless a \
         table says otherwise."
    );
    if meta.total_s > 0.0 {
        let _ = writeln!(s, "- The whole run took {:.0} s.", meta.total_s);
    }
    let _ = writeln!(s);
    if !meta.plot.is_empty() {
        let _ = writeln!(s, "![flow EPE and image MAE against render time]({})\n", meta.plot);
    }

    let _ = writeln!(s, "## What is measured\n");
    let _ = writeln!(
        s,
        "- **Flow EPE** (px): the rendered forward flow against the exact flow of the continuous scene, \
         X = depth(p) K^-1 p, X' = R X + t, flow = pi(K X') - p, mean over the pixels that are valid in the exact \
         sense (X' in front of the target camera, p + flow inside the image) and visible in the target view. \
         Visibility is decided in the continuous scene as the source camera sees it (a height field: the segment \
         from the point to the target camera is marched in the source image and the point is occluded when it \
         passes behind the surface). *EPE* counts all these pixels; *EPE edge-free* leaves out those within \
         {EDGE_RADIUS} px of a depth discontinuity (a relative depth jump above {EDGE_JUMP} between neighbours). MPIs from \
         networks blend the flows of both sides there; the built-in layering gives every source pixel its own depth \
         (the flow pass reads each pixel's own planes), so here the two columns differ only by the silhouette \
         pixels of the sphere, where the depth changes fastest."
    );
    let _ = writeln!(
        s,
        "- **Image MAE** (mean |difference| over r, g, b, in [0, 1] units) and PSNR (dB) of the rendered target image \
         against an f64 render of the same scene with {} planes, soft layering, no work skipping, over the pixels \
         whose reference coverage exceeds {COVERAGE_MIN}. It measures the error of plane discretisation, not of the \
         layering's colours behind foreground (both renders share those).",
        report.reference_planes
    );
    let _ = writeln!(s, "\n### Scenes\n");
    let _ = writeln!(s, "| scene | depth range | valid px | visible px | edge-free px | mean exact flow (px) | {}-plane f64 reference (ms) |", report.reference_planes);
    let _ = writeln!(s, "|---|---|---|---|---|---|---|");
    for sc in &report.scenes {
        let pct = |v: usize| format!("{v} ({:.0}%)", 100.0 * v as f64 / sc.pixels.max(1) as f64);
        let _ = writeln!(
            s,
            "| {} | {:.2} .. {:.2} | {} | {} | {} | {:.1} | {:.0} |",
            sc.name,
            sc.depth_min,
            sc.depth_max,
            pct(sc.valid),
            pct(sc.visible),
            pct(sc.edge_free),
            sc.mean_flow,
            sc.reference_ms
        );
    }
    let _ = writeln!(
        s,
        "\n(a) a textured plane tilted {:.1} degrees towards the camera (nearer at the bottom right); (b) a textured sphere, \
         radius 0.6 at z = 2, in front of a textured wall at z = 4 (ray-sphere intersection in closed form); (c) the \
         photo resized to the bench size with the smooth synthetic depth of `tools/make_demo_depth.py` (slanted \
         background plus a Gaussian bump).",
        tilted_plane_normal().z.acos().to_degrees()
    );

    let _ = writeln!(s, "\n## Error against planes and time\n");
    let _ = writeln!(s, "| scene | N | layering | ms | EPE (px) | EPE edge-free (px) | image MAE | PSNR (dB) |");
    let _ = writeln!(s, "|---|---:|---|---:|---:|---:|---:|---:|");
    for r in &report.rows {
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {} | {} | {} | {} |",
            r.scene,
            r.planes,
            layering_name(r.layering),
            f(r.m.time.median, 2),
            sig(r.m.epe, 3),
            sig(r.m.epe_edge_free, 3),
            sig(r.m.image.mae, 3),
            f(r.m.image.psnr, 1)
        );
    }

    let _ = writeln!(s, "\n## Convergence order\n");
    let _ = writeln!(
        s,
        "Least-squares slope p of log(error) against log(N) (error ~ N^p), over the N given in brackets. Flow errors \
         below {} px are left out: that is ten times the mean f32 rounding of the flow (the f32 against f64 table \
         below), where the error stops following N. Image MAE is fitted over N <= {} (closer to the {}-plane \
         reference the error to the reference falls faster than the error to the truth).\n",
        sig(epe_fit_floor(report), 2),
        (report.reference_planes / 4).max(2),
        report.reference_planes
    );
    let _ = writeln!(s, "| scene | layering | {METRIC_EPE} | {METRIC_EPE_ALL} | {METRIC_MAE} |");
    let _ = writeln!(s, "|---|---|---:|---:|---:|");
    for sc in &report.scenes {
        for layering in [Layering::Hard, Layering::Soft] {
            let g = |m: &str| {
                order_of(&orders, &sc.name, layering, m).map_or("n/a".into(), |o| {
                    if o.slope.is_finite() {
                        format!("{} (N {}..{})", f(o.slope, 2), o.n_min, o.n_max)
                    } else {
                        "n/a".into()
                    }
                })
            };
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {} |",
                sc.name,
                layering_name(layering),
                g(METRIC_EPE),
                g(METRIC_EPE_ALL),
                g(METRIC_MAE)
            );
        }
    }
    let _ = writeln!(s);
    for sc in &report.scenes {
        let mut parts = Vec::new();
        for layering in [Layering::Soft, Layering::Hard] {
            let (e_, m_) =
                (order_of(&orders, &sc.name, layering, METRIC_EPE), order_of(&orders, &sc.name, layering, METRIC_MAE));
            if let (Some(a), Some(b)) = (e_, m_) {
                parts.push(format!(
                    "with {} layering flow EPE falls as N^{} and image MAE as N^{}",
                    layering_name(layering),
                    f(a.slope, 1),
                    f(b.slope, 1)
                ));
            }
        }
        if !parts.is_empty() {
            let _ = writeln!(s, "- {}: {}.", sc.name, parts.join("; "));
        }
    }
    if let Some(text) = observations(report, &orders) {
        let _ = writeln!(s, "\n{text}");
    }

    if !report.skips.is_empty() {
        let _ = writeln!(s, "\n## Work skipping\n");
        let _ = writeln!(
            s,
            "Soft layering. *saved* is the time saved against no skipping; *skipped* the share of target-view plane \
             samples avoided; the differences are against the render without skipping (image: max / mean |difference|; \
             flow: max / mean end-point difference in px), the EPE and MAE against the exact flow and the reference.\n"
        );
        let _ = writeln!(s, "| scene | N | skipping | ms | saved | skipped | image diff max / mean | flow diff max / mean | EPE edge-free | image MAE |");
        let _ = writeln!(s, "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|");
        for r in &report.skips {
            let none = report
                .skips
                .iter()
                .find(|q| q.scene == r.scene && q.planes == r.planes && q.skip == Skip::NONE)
                .map_or(f64::NAN, |q| q.m.time.median);
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {}% | {}% | {} / {} | {} / {} | {} | {} |",
                r.scene,
                r.planes,
                r.name,
                f(r.m.time.median, 2),
                f(100.0 * (1.0 - r.m.time.median / none), 0),
                f(100.0 * r.m.skipped, 0),
                e(r.image_diff.0),
                e(r.image_diff.1),
                e(r.flow_diff.0),
                e(r.flow_diff.1),
                sig(r.m.epe_edge_free, 3),
                sig(r.m.image.mae, 3)
            );
        }
        let _ = writeln!(s);
        for line in skip_notes(report) {
            let _ = writeln!(s, "- {line}");
        }
    }

    if !report.precision.is_empty() {
        let _ = writeln!(s, "\n## f32 against f64\n");
        let _ = writeln!(
            s,
            "The same soft MPI rendered without skipping in f32 (production) and f64; differences between the two \
             outputs.\n"
        );
        let _ = writeln!(s, "| scene | N | f32 ms | f64 ms | image diff max / mean | flow diff max / mean (px) | EPE f32 / f64 | MAE f32 / f64 |");
        let _ = writeln!(s, "|---|---:|---:|---:|---:|---:|---:|---:|");
        for r in &report.precision {
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {} / {} | {} / {} | {} / {} | {} / {} |",
                r.scene,
                r.planes,
                f(r.f32.time.median, 2),
                f(r.f64.time.median, 2),
                e(r.image_diff.0),
                e(r.image_diff.1),
                e(r.flow_diff.0),
                e(r.flow_diff.1),
                sig(r.f32.epe_edge_free, 4),
                sig(r.f64.epe_edge_free, 4),
                sig(r.f32.image.mae, 4),
                sig(r.f64.image.mae, 4)
            );
        }
    }

    if !report.reference_mode.is_empty() {
        let _ = writeln!(s, "\n## Reference mode\n");
        let _ = writeln!(
            s,
            "The same soft MPI rendered in `Mode::Reference` (the public implementation's formulas: border-clamped \
             sampling, +1e-6 in the transmittance, flow clipped to +-200, no skipping) and in exact mode with default \
             skipping.\n"
        );
        let _ = writeln!(
            s,
            "| scene | N | exact ms | reference ms | EPE edge-free exact / reference | image MAE exact / reference |"
        );
        let _ = writeln!(s, "|---|---:|---:|---:|---:|---:|");
        for r in &report.reference_mode {
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {} / {} | {} / {} |",
                r.scene,
                r.planes,
                f(r.exact.time.median, 2),
                f(r.reference.time.median, 2),
                sig(r.exact.epe_edge_free, 3),
                sig(r.reference.epe_edge_free, 3),
                sig(r.exact.image.mae, 3),
                sig(r.reference.image.mae, 3)
            );
        }
    }
    s
}

/// Sentences about the skipping variants, computed from the numbers.
fn skip_notes(report: &AccuracyReport) -> Vec<String> {
    let mut out = Vec::new();
    let mut names: Vec<&str> = Vec::new();
    for r in &report.skips {
        if !names.contains(&r.name.as_str()) {
            names.push(&r.name);
        }
    }
    // the farthest plane's density: opaque over DELTA_LAST times the ray length
    let k = Intrinsics::reference_default(report.width, report.height);
    let corner =
        k.unproject(0.0, 0.0).length().max(k.unproject((report.width - 1) as f64, (report.height - 1) as f64).length());
    let sigma_last = |l: f64| -(-ALPHA_MAX).ln_1p() / (DELTA_LAST * l);
    for name in names {
        let rows: Vec<&SkipRow> = report.skips.iter().filter(|r| r.name == name).collect();
        let skip = rows[0].skip;
        if skip == Skip::NONE {
            continue;
        }
        let mut saved: Vec<f64> = rows
            .iter()
            .filter_map(|r| {
                let none =
                    report.skips.iter().find(|q| q.scene == r.scene && q.planes == r.planes && q.skip == Skip::NONE)?;
                Some(100.0 * (1.0 - r.m.time.median / none.m.time.median))
            })
            .collect();
        saved.sort_by(f64::total_cmp);
        let img = rows.iter().map(|r| r.image_diff.0).fold(0.0f64, f64::max);
        let flow = rows.iter().map(|r| r.flow_diff.0).fold(0.0f64, f64::max);
        let (lo, hi) = (saved.first().copied().unwrap_or(f64::NAN), saved.last().copied().unwrap_or(f64::NAN));
        let mut line = if img == 0.0 && flow == 0.0 {
            format!("`{name}` saves {}% to {}% of the time; image and flow are bit-identical.", f(lo, 0), f(hi, 0))
        } else {
            format!(
                "`{name}` saves {}% to {}% of the time and changes the image by at most {} and the flow by at most {} px.",
                f(lo, 0),
                f(hi, 0),
                e(img),
                e(flow)
            )
        };
        if skip.tile_sigma_eps > 0.0 && (img > 0.01 || flow > 0.1) {
            let _ = write!(
                line,
                " Not usable: `tile_sigma_eps` is an absolute density, and the farthest plane of a built MPI is opaque \
                 with density only -ln(1 - ALPHA_MAX) / (DELTA_LAST |K^-1 p|) = {} .. {} (it is opaque over DELTA_LAST = {}), \
                 so a threshold of {} drops that plane over whole tiles where nothing else is in front; a density threshold \
                 would have to be relative to each plane's gap (an alpha threshold).",
                sig(sigma_last(corner), 2),
                sig(sigma_last(1.0), 2),
                DELTA_LAST,
                skip.tile_sigma_eps
            );
        }
        out.push(line);
    }
    out
}

/// A few sentences computed from the numbers (never written by hand, so they stay true when the
/// numbers change).
fn observations(report: &AccuracyReport, orders: &[Order]) -> Option<String> {
    let mut lines = Vec::new();
    let mean_slope = |layering: Layering, metric: &str| {
        let v: Vec<f64> = orders
            .iter()
            .filter(|o| o.layering == layering && o.metric == metric && o.slope.is_finite())
            .map(|o| o.slope)
            .collect();
        (!v.is_empty()).then(|| {
            (
                v.iter().sum::<f64>() / v.len() as f64,
                v.iter().cloned().fold(f64::MAX, f64::min),
                v.iter().cloned().fold(f64::MIN, f64::max),
            )
        })
    };
    for layering in [Layering::Soft, Layering::Hard] {
        for metric in [METRIC_EPE, METRIC_MAE] {
            if let Some((m, lo, hi)) = mean_slope(layering, metric) {
                lines.push(format!(
                    "- Over the scenes, {} with {} layering converges with order {} on average (slopes {} .. {}).",
                    metric,
                    layering_name(layering),
                    f(-m, 2),
                    f(lo, 2),
                    f(hi, 2)
                ));
            }
        }
    }
    // soft against hard at equal N
    let mut ratios = Vec::new();
    for r in report.rows.iter().filter(|r| r.layering == Layering::Soft) {
        if let Some(h) =
            report.rows.iter().find(|q| q.scene == r.scene && q.planes == r.planes && q.layering == Layering::Hard)
        {
            if r.m.epe_edge_free > 0.0 && h.m.epe_edge_free.is_finite() {
                ratios.push(h.m.epe_edge_free / r.m.epe_edge_free);
            }
        }
    }
    if !ratios.is_empty() {
        ratios.sort_by(f64::total_cmp);
        lines.push(format!(
            "- At equal N, hard layering's edge-free flow EPE is {}x to {}x that of soft layering (median {}x), for \
             about the same render time.",
            f(ratios[0], 1),
            f(ratios[ratios.len() - 1], 1),
            f(ratios[ratios.len() / 2], 1)
        ));
    }
    (!lines.is_empty()).then(|| lines.join("\n"))
}

// ---------------------------------------------------------------------------------------------
// Plot

static FONT: std::sync::OnceLock<bool> = std::sync::OnceLock::new();

fn ensure_font() -> Result<(), AccuracyError> {
    let ok = *FONT.get_or_init(|| {
        plotters::style::register_font("sans-serif", plotters::style::FontStyle::Normal, dejavu::sans::regular())
            .is_ok()
    });
    if ok {
        Ok(())
    } else {
        Err(AccuracyError::Plot("cannot load the DejaVu Sans font".into()))
    }
}

const SCENE_COLOURS: [(u8, u8, u8); 6] =
    [(31, 119, 180), (214, 39, 40), (44, 160, 44), (148, 103, 189), (255, 127, 14), (23, 190, 207)];

/// Draws the two log-log panels (flow EPE and image MAE against milliseconds) into an RGB
/// buffer of `width` x `height` (3 bytes per pixel).
pub fn plot_rgb(report: &AccuracyReport, width: u32, height: u32) -> Result<Vec<u8>, AccuracyError> {
    use plotters::prelude::*;
    ensure_font()?;
    let perr = |e: &dyn std::fmt::Display| AccuracyError::Plot(e.to_string());
    let mut buf = vec![255u8; width as usize * height as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (width, height)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| perr(&e))?;
        let root = root
            .titled(
                &format!("Error against render time, {}x{}, N = {}", report.width, report.height, n_list(report)),
                ("sans-serif", 22),
            )
            .map_err(|e| perr(&e))?;
        let panels = root.split_evenly((1, 2));
        let metrics: [(&str, Metric); 2] =
            [("flow EPE, edge-free (px)", |m| m.epe_edge_free), ("image MAE against the reference", |m| m.image.mae)];
        let xs: Vec<f64> = report.rows.iter().map(|r| r.m.time.median).filter(|v| v.is_finite() && *v > 0.0).collect();
        let (xmin, xmax) = bounds(&xs);
        for (panel, (label, metric)) in panels.iter().zip(metrics) {
            let ys: Vec<f64> = report.rows.iter().map(|r| metric(&r.m)).filter(|v| v.is_finite() && *v > 0.0).collect();
            let (ymin, ymax) = bounds(&ys);
            let mut chart = ChartBuilder::on(panel)
                .margin(12)
                .x_label_area_size(48)
                .y_label_area_size(72)
                .build_cartesian_2d(
                    (xmin..xmax)
                        .log_scale()
                        .with_key_points(log_ticks(xmin, xmax).0)
                        .with_light_points(log_ticks(xmin, xmax).1),
                    (ymin..ymax)
                        .log_scale()
                        .with_key_points(log_ticks(ymin, ymax).0)
                        .with_light_points(log_ticks(ymin, ymax).1),
                )
                .map_err(|e| perr(&e))?;
            chart
                .configure_mesh()
                .x_desc("render time, image + flow + depth (ms, median)")
                .y_desc(label)
                .label_style(("sans-serif", 14))
                .axis_desc_style(("sans-serif", 16))
                .x_label_formatter(&|v| fmt_tick(*v))
                .y_label_formatter(&|v| fmt_tick(*v))
                .draw()
                .map_err(|e| perr(&e))?;
            for (si, sc) in report.scenes.iter().enumerate() {
                let (r, g, b) = SCENE_COLOURS[si % SCENE_COLOURS.len()];
                let colour = RGBColor(r, g, b);
                for layering in [Layering::Soft, Layering::Hard] {
                    let pts: Vec<(f64, f64, usize)> = report
                        .rows
                        .iter()
                        .filter(|q| q.scene == sc.name && q.layering == layering)
                        .map(|q| (q.m.time.median, metric(&q.m), q.planes))
                        .filter(|(x, y, _)| x.is_finite() && y.is_finite() && *x > 0.0 && *y > 0.0)
                        .collect();
                    let name = format!("{}, {}", sc.name, layering_name(layering));
                    let line: Vec<(f64, f64)> = pts.iter().map(|p| (p.0, p.1)).collect();
                    let soft = layering == Layering::Soft;
                    let style = colour.stroke_width(if soft { 2 } else { 1 });
                    if soft {
                        chart
                            .draw_series(LineSeries::new(line.clone(), style))
                            .map_err(|e| perr(&e))?
                            .label(name)
                            .legend(move |(x, y)| {
                                EmptyElement::at((x, y))
                                    + PathElement::new(vec![(0, 0), (22, 0)], colour.stroke_width(2))
                                    + Circle::new((11, 0), 4, colour.filled())
                            });
                        chart
                            .draw_series(line.iter().map(|&p| Circle::new(p, 4, colour.filled())))
                            .map_err(|e| perr(&e))?;
                    } else {
                        chart
                            .draw_series(DashedLineSeries::new(line.clone(), 6, 4, style))
                            .map_err(|e| perr(&e))?
                            .label(name)
                            .legend(move |(x, y)| {
                                EmptyElement::at((x, y))
                                    + PathElement::new(vec![(0, 0), (22, 0)], colour.stroke_width(1))
                                    + TriangleMarker::new((11, 0), 5, colour.filled())
                            });
                        chart
                            .draw_series(line.iter().map(|&p| TriangleMarker::new(p, 5, colour.filled())))
                            .map_err(|e| perr(&e))?;
                    }
                    if soft {
                        // N next to each soft point (hard points share the abscissa)
                        chart
                            .draw_series(pts.iter().map(|&(x, y, n)| {
                                EmptyElement::at((x, y))
                                    + Text::new(format!("{n}"), (6, -16), ("sans-serif", 12).into_font().color(&colour))
                            }))
                            .map_err(|e| perr(&e))?;
                    }
                }
            }
            chart
                .configure_series_labels()
                .position(SeriesLabelPosition::UpperRight)
                .background_style(WHITE.mix(0.85))
                .border_style(BLACK)
                .label_font(("sans-serif", 13))
                .draw()
                .map_err(|e| perr(&e))?;
        }
        root.present().map_err(|e| perr(&e))?;
    }
    Ok(buf)
}

fn n_list(report: &AccuracyReport) -> String {
    let mut ns: Vec<usize> = report.rows.iter().map(|r| r.planes).collect();
    ns.sort_unstable();
    ns.dedup();
    ns.iter().map(|n| n.to_string()).collect::<Vec<_>>().join(", ")
}

/// A log axis range covering `v` with some room (a decade around 1 when empty).
fn bounds(v: &[f64]) -> (f64, f64) {
    let lo = v.iter().cloned().fold(f64::INFINITY, f64::min);
    let hi = v.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
    if !(lo.is_finite() && hi.is_finite()) {
        return (0.1, 10.0);
    }
    let (lo, hi) = if hi / lo < 1.5 { (lo / 1.5, hi * 1.5) } else { (lo, hi) };
    (lo / 1.6, hi * 1.6)
}

/// Labelled ticks (1, 2, 5 per decade; decades only over more than three decades) and light
/// mesh lines (1..9 per decade) of a log axis over [lo, hi].
fn log_ticks(lo: f64, hi: f64) -> (Vec<f64>, Vec<f64>) {
    let (mut bold, mut light) = (Vec::new(), Vec::new());
    if !(lo.is_finite() && hi.is_finite() && lo > 0.0 && hi > lo) {
        return (bold, light);
    }
    let steps: &[f64] = if hi / lo > 1e3 { &[1.0] } else { &[1.0, 2.0, 5.0] };
    for e in (lo.log10().floor() as i32)..=(hi.log10().ceil() as i32) {
        let d = 10f64.powi(e);
        for m in 1..10 {
            let v = m as f64 * d;
            if v >= lo && v <= hi {
                light.push(v);
                if steps.contains(&(m as f64)) {
                    bold.push(v);
                }
            }
        }
    }
    (bold, light)
}

fn fmt_tick(v: f64) -> String {
    if v == 0.0 {
        "0".into()
    } else if (1e-3..1e4).contains(&v.abs()) {
        let s = format!("{v:.4}");
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        format!("{v:.0e}")
    }
}

/// Writes the plot as a PNG file.
pub fn write_plot(report: &AccuracyReport, path: &Path, width: u32, height: u32) -> Result<(), AccuracyError> {
    let buf = plot_rgb(report, width, height)?;
    crate::io::image::write_png(path, width, height, &buf, ::image::ExtendedColorType::Rgb8)?;
    Ok(())
}
