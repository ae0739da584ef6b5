//! Built-in RGB-D layering: builds an MPI from an image and a depth map without a network.
//!
//! # Method
//!
//! 1. **Inputs.** `rgb` is H x W x 3 (row-major, interleaved), `depth` H x W in the unit of the
//!    translation; a depth that is non-finite or <= 0 is *unknown*. Sizes must agree,
//!    `planes` must lie in `1..=`[`MAX_PLANES`], colours must be finite and at least one depth
//!    must be known; anything else is [`MpiError::Invalid`] with a message saying what is wrong.
//! 2. **Unknown depth.** Disparity (1 / depth, in f64) of an unknown pixel is copied from its
//!    nearest known pixel: a multi-source breadth-first search over the 8-neighbourhood from
//!    all known pixels (nearest in the chessboard metric; ties go to the source found first in
//!    row-major scan order, so the result is deterministic). Copying rather than averaging never
//!    invents depths between a foreground and its background.
//! 3. **Planes.** Disparities are uniform in disparity from the nearest plane (largest
//!    disparity) to the farthest: over the scene's own range [min, max] of (filled) disparity,
//!    or over `disparity_range = Some((near, far))` (which must satisfy near > far >= 0, both
//!    finite). When the scene's range is zero or too narrow to separate the planes (`max - min
//!    < `[`MIN_RELATIVE_RANGE`]` * max`, e.g. a single constant depth) the nearest plane stays at
//!    the scene's largest disparity and the farthest is moved back to `max * (1 -
//!    MIN_RELATIVE_RANGE)`, so a constant-depth scene lies exactly on plane 0. One plane sits at
//!    the middle `(near + far) / 2` of the (unwidened) range and is opaque everywhere.
//! 4. **Assignment.** Let `k` be the last plane with `disp_k >= d` (the pixel's disparity) and
//!    `t = (d - disp_{k+1}) / (disp_k - disp_{k+1})` in (0, 1]. Pixels in front of plane 0 go to
//!    plane 0, pixels behind the farthest plane to the farthest plane.
//!    - [`Layering::Hard`]: the pixel goes to the nearer of the two planes in disparity
//!      (`k` when `t >= 1/2`, else `k + 1`) with alpha 1.
//!    - [`Layering::Soft`]: the pixel's opacity is split linearly in disparity: composited
//!      weights `w_k = t`, `w_{k+1} = 1 - t`, so the weight-averaged disparity is exactly `d`.
//!      Front-to-back "over" compositing gives `w_k = a_k` and `w_{k+1} = (1 - a_k) a_{k+1}`;
//!      with the far plane opaque (`a_{k+1} = 1`) this is `w_{k+1} = 1 - a_k`, so the per-plane
//!      alphas that produce the split are simply `a_k = t`, `a_{k+1} = 1`. Both planes carry the
//!      pixel's colour, so the composite `t c + (1 - t) c = c` reproduces it for any `t`.
//!    - [`Layering::TrueDepth`]: as `Soft`, and the MPI keeps every pixel's disparity
//!      ([`super::Surface`]) so that the renderer puts both of the pixel's texels at it: they
//!      move as one under any motion instead of parting by the parallax of the plane spacing.
//!
//!    Every plane in front of a pixel's planes has alpha exactly 0 there, and the farthest plane
//!    is opaque everywhere.
//! 5. **Alpha to density.** The renderer composites `alpha_i = 1 - exp(-sigma_i delta_i |K^-1 p|)`
//!    with `delta_i = depth_{i+1} - depth_i` (capped at [`DELTA_LAST`], the last plane
//!    [`DELTA_LAST`], depths capped at [`DEPTH_MAX`](crate::mpi::planes::DEPTH_MAX): the one
//!    rule of [`crate::mpi::planes`], which the renderer uses too). We store
//!    `sigma_i = -ln(1 - alpha_i) / delta_i` with alpha clamped to at most [`ALPHA_MAX`] (so
//!    sigma stays finite; the 1e-6 of light that passes an "opaque" plane is below any 8-bit
//!    colour step) and sigma capped at [`SIGMA_MAX`]; alpha 0 gives sigma exactly 0 (the renderer
//!    skips exactly-empty tiles). The source-view composite therefore reproduces the alphas
//!    exactly at the principal point, where `|K^-1 p| = 1`. Off-axis rays are longer
//!    (`|K^-1 p| > 1`), which only raises the opacity (`1 - (1 - a)^{|K^-1 p|} >= a`): colours are
//!    still reproduced (both planes of a pixel carry its colour, the far one is opaque anyway),
//!    but Soft's expected disparity leans towards the near plane: at most by
//!    `max_t (1 - (1 - t)^L - t)` of a plane spacing, about 1/6 at the corners of the reference
//!    camera (`L = |K^-1 p| = 1.57`). [`build_mpi_for_camera`] divides by the per-pixel ray
//!    length of a known source camera as well, which makes the source-view alphas exact at every
//!    pixel.
//! 6. **Colours.** Where a plane has alpha > 0 it carries the pixel's own colour. Elsewhere its
//!    colour only shows through bilinear sampling at the plane's edges (non-last planes) or in
//!    disocclusions (last plane), and is filled from *background*:
//!    - plane `i` (not the last): the known set is every pixel with alpha > 0 on plane `i` or with
//!      disparity `<= disp_i` (at or behind the plane; if the plane lies behind all content, the
//!      farthest content); the rest is filled by a push-pull pyramid (2x2 means of known pixels
//!      only, down to 1x1, then bilinear up-sampling into the unknown pixels only). Foreground
//!      in front of the plane never contributes, so the colour a layer edge blends with is the
//!      colour behind it (no foreground halos, and the slight fattening of bilinear density
//!      sampling mixes in background rather than foreground).
//!    - the farthest plane (opaque, what every disocclusion ends on): at each pixel the colour of
//!      the content *behind that pixel*: the fill of plane `f + 1`, where `f` is the farthest
//!      plane holding the pixel, whose known set contains only pixels strictly behind it (or the
//!      pixel's own colour where the pixel lies on the farthest plane or is the farthest content).
//!      For the pixels of the farthest content this is the rule above; for a foreground object in
//!      front of a middle-distance wall in front of a far sky, the strip it uncovers shows the
//!      wall (the local background), not the sky (the globally farthest content) and never the
//!      object itself. (Filling the farthest plane only from the pixels at the farthest depth
//!      would pull the sky into that strip.)
//!
//!    The fills act as a colour dilation of each layer into its surroundings; alphas are never
//!    dilated, which keeps the identity render exact. In terms of the assignment, pixel `p` is a
//!    colour source of plane `i` exactly when `i <= far(p)` (or `p` is the farthest content).
//! 7. **Completed background** (`backdrop`, opt-in). The background behind the object masks
//!    and beside depth steps is completed ([`super::backdrop`]) and put, opaque, on the plane
//!    nearest its disparity at each pixel that hides it, when that plane lies strictly behind the
//!    first plane behind the pixel (what a density cut of the pixel's own planes leaves
//!    standing). The pixel is that plane's colour source with the completed colour; in the source
//!    view the surface is hidden behind the pixel's own opaque plane.
//! 8. **Seams** (hard layering). A pixel within [`SEAM_REACH`] of a pixel on the plane just in
//!    front of its own is also opaque on that plane, whose fill there is the pixel's own colour:
//!    the source view is unchanged in colour, and the two planes overlap so that no crack opens
//!    between them when they part under motion by up to [`SEAM_REACH`] pixels.
//! 9. **Cost.** Planes are processed in parallel with rayon (fill and densities of each plane are
//!    independent). 640 x 480 with 32 planes takes about 110 ms of user CPU time plus the kernel's
//!    zeroing of the 157 MB of plane data on first touch (`build_time_640x480x32` in
//!    `tests/render/layering.rs` prints the median wall time).

use super::{Mpi, MpiError, SIGMA_MAX};
use crate::geometry::Intrinsics;
use crate::mpi::planes::{plane_gaps, DELTA_LAST};
use crate::raster::pushpull::{Known, Pyramid};
use crate::raster::Grid;
use rayon::prelude::*;
use std::collections::VecDeque;

/// Most planes the built-in layering makes.
pub const MAX_PLANES: usize = 256;
/// Alphas are clamped to at most this so that densities stay finite.
pub const ALPHA_MAX: f64 = 1.0 - 1e-6;
/// A scene disparity range narrower than this fraction of its largest disparity is widened
/// (towards the far side) to `MIN_RELATIVE_RANGE * max`.
pub const MIN_RELATIVE_RANGE: f64 = 1e-3;

/// How pixels are assigned to planes.
///
/// `Soft` is the default. Under rotation and forward motion the two copies of a `Soft` pixel
/// reproject to different places and blur image2 (and its labels) by up to a plane spacing's
/// parallax; a `Hard` pixel moves as one and keeps more detail, but a smooth slope becomes
/// stripes whose seams show as thin lines (docs/quality.md, "Layering").
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Layering {
    /// Each pixel goes to its nearest plane (in disparity).
    Hard,
    /// Each pixel is split between the two neighbouring planes, linearly in disparity.
    #[default]
    Soft,
    /// As `Soft`, and every texel keeps the pixel's own disparity ([`super::Surface`]): the
    /// renderer follows it within the plane's slab, so a split pixel's two copies move as one and
    /// the flow is the pixel's own (docs/quality.md, "True-depth layers").
    TrueDepth,
}

impl std::fmt::Display for Layering {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Layering::Hard => "hard",
            Layering::Soft => "soft",
            Layering::TrueDepth => "true-depth",
        })
    }
}

impl std::str::FromStr for Layering {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "hard" => Ok(Layering::Hard),
            "soft" => Ok(Layering::Soft),
            "true-depth" => Ok(Layering::TrueDepth),
            _ => Err(format!("unknown layering `{s}` (expected hard, soft or true-depth)")),
        }
    }
}

/// Where the planes go in disparity between the nearest and the farthest (step 3 of the method).
///
/// `Content` (opt-in, `[models] placement`): with a finite number of planes, a soft pixel is split between the two
/// planes around it and its two copies part under motion by the parallax of their spacing, so
/// planes are best spent where the scene's pixels are. It places plane `i` of `n` (near to far)
/// at the disparity where the mixture CDF `F = (1 - λ) F_pixels + λ F_uniform` (`λ` =
/// [`CONTENT_UNIFORM_SHARE`], `F_pixels` the pixels' disparity distribution in 4,096 bins over the
/// scene's range with linear interpolation in each bin, `F_uniform` uniform over the range)
/// equals `1 - i / (n - 1)`: the uniform share keeps the planes strictly decreasing and every gap
/// at most `1 / (λ (n - 1))` of the range.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Placement {
    /// Uniform in disparity over the range (the default).
    #[default]
    Uniform,
    /// Dense where the scene's pixels are (see the type's documentation).
    Content,
}

/// The uniform share `λ` of [`Placement::Content`].
pub const CONTENT_UNIFORM_SHARE: f64 = 0.25;

impl std::fmt::Display for Placement {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Placement::Uniform => "uniform",
            Placement::Content => "content",
        })
    }
}

impl std::str::FromStr for Placement {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "uniform" => Ok(Placement::Uniform),
            "content" => Ok(Placement::Content),
            _ => Err(format!("unknown plane placement `{s}` (expected content or uniform)")),
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LayeringOptions {
    pub planes: usize,
    pub layering: Layering,
    /// Where the planes go within the range (ignored with `disparity_range`: uniform there).
    pub placement: Placement,
    /// (nearest, farthest) plane disparities; None = the scene's own disparity range.
    pub disparity_range: Option<(f64, f64)>,
    /// Complete the background behind foreground ([`super::backdrop`]) and put it on the planes
    /// behind each pixel that hides it (step 7 of the method; the backdrop adds about 0.4 s to
    /// a 640 x 480 scene on 2 cores).
    pub backdrop: bool,
}

impl Default for LayeringOptions {
    /// 32 planes, soft layering, uniform placement over the scene's own disparity range, no
    /// completed background (the layering's plain form; the commands' defaults are the scene
    /// models' configuration's).
    fn default() -> Self {
        Self {
            planes: 32,
            layering: Layering::default(),
            placement: Placement::Uniform,
            disparity_range: None,
            backdrop: false,
        }
    }
}

/// Builds an MPI from an image (H x W x 3 in [0, 1]) and a depth map (H x W, in the unit of the
/// translation; non-finite or <= 0 means unknown). See the module documentation for the method.
pub fn build_mpi(
    rgb: &[f32],
    depth: &[f32],
    width: usize,
    height: usize,
    opts: &LayeringOptions,
) -> Result<Mpi, MpiError> {
    build(rgb, depth, width, height, opts, None, None)
}

/// As [`build_mpi`], but the densities also divide by each source pixel's ray length
/// `|K^-1 p|`, so the source-view composite reproduces the layering's alphas at every pixel of a
/// camera with intrinsics `k` (not only at the principal point). The intrinsics are not stored
/// in the MPI.
pub fn build_mpi_for_camera(
    rgb: &[f32],
    depth: &[f32],
    width: usize,
    height: usize,
    opts: &LayeringOptions,
    k: &Intrinsics,
) -> Result<Mpi, MpiError> {
    if !k.is_valid() {
        return Err(MpiError::Invalid(format!(
            "layering: invalid intrinsics {k:?}: focal lengths must be finite and non-zero"
        )));
    }
    build(rgb, depth, width, height, opts, Some(k), None)
}

/// As [`build_mpi_for_camera`], with the scene's object masks (H x W, true = an object that may
/// move): with `opts.backdrop` the background behind them is completed as well as behind depth
/// edges ([`super::backdrop`]).
pub fn build_mpi_for_scene(
    rgb: &[f32],
    depth: &[f32],
    width: usize,
    height: usize,
    opts: &LayeringOptions,
    k: &Intrinsics,
    masks: &[bool],
) -> Result<Mpi, MpiError> {
    if !k.is_valid() {
        return Err(MpiError::Invalid(format!(
            "layering: invalid intrinsics {k:?}: focal lengths must be finite and non-zero"
        )));
    }
    if masks.len() != width * height {
        return Err(MpiError::Invalid(format!(
            "layering: masks of {} values for an image of {width}x{height}",
            masks.len()
        )));
    }
    build(rgb, depth, width, height, opts, Some(k), Some(masks))
}

/// How far (chessboard, pixels) a hard plane reaches over the plane just behind it at a seam.
pub const SEAM_REACH: usize = 3;

/// No hidden surface at a pixel.
const NO_HIDDEN: u16 = u16::MAX;

/// The plane disparities the layering uses for a scene whose (known) disparities span
/// `[scene_far, scene_near]`: uniform from near to far, strictly decreasing, >= 0. With
/// `opts.disparity_range` set, that range is used instead of the scene's.
pub fn plane_disparities(scene_near: f64, scene_far: f64, opts: &LayeringOptions) -> Result<Vec<f64>, MpiError> {
    let n = opts.planes;
    check_planes(n)?;
    let (near, far) = match opts.disparity_range {
        Some(r) => check_range(r)?,
        None => {
            if !(scene_near.is_finite() && scene_far.is_finite() && scene_far > 0.0 && scene_near >= scene_far) {
                return Err(MpiError::Invalid(format!(
                    "layering: scene disparity range ({scene_near}, {scene_far}) is not finite, positive and ordered"
                )));
            }
            if n == 1 {
                return Ok(vec![0.5 * (scene_near + scene_far)]);
            }
            if scene_near - scene_far < MIN_RELATIVE_RANGE * scene_near {
                (scene_near, scene_near * (1.0 - MIN_RELATIVE_RANGE))
            } else {
                (scene_near, scene_far)
            }
        }
    };
    if n == 1 {
        return Ok(vec![0.5 * (near + far)]);
    }
    let m = (n - 1) as f64;
    let mut d: Vec<f64> = (0..n).map(|i| near + (far - near) * (i as f64 / m)).collect();
    d[0] = near;
    d[n - 1] = far;
    if d.windows(2).any(|p| p[1] >= p[0]) || d.iter().any(|&v| !(v.is_finite() && v >= 0.0)) {
        return Err(MpiError::Invalid(format!(
            "layering: disparity range ({near}, {far}) is too narrow to hold {n} distinct planes"
        )));
    }
    Ok(d)
}

/// [`Placement::Content`]'s planes: `n >= 3` disparities from `near` down to `far` (both kept)
/// at the quantiles of the mixture of the pixels' disparity distribution (`disp`) and the
/// uniform one (see [`Placement`]). Strictly decreasing because the mixture's density is at least
/// `λ / (near - far)` everywhere.
fn content_planes(disp: &[f64], near: f64, far: f64, n: usize) -> Vec<f64> {
    const BINS: usize = 4096;
    let range = near - far;
    let mut hist = vec![0u64; BINS];
    for &d in disp {
        let b = (((d - far) / range) * BINS as f64).floor();
        hist[(b.max(0.0) as usize).min(BINS - 1)] += 1;
    }
    let total = disp.len().max(1) as f64;
    let lambda = CONTENT_UNIFORM_SHARE;
    // cdf[b] = F at the lower edge of bin b (cdf[BINS] = 1)
    let mut cdf = Vec::with_capacity(BINS + 1);
    let mut acc = 0u64;
    cdf.push(0.0);
    for (b, &c) in hist.iter().enumerate() {
        acc += c;
        cdf.push((1.0 - lambda) * acc as f64 / total + lambda * (b + 1) as f64 / BINS as f64);
    }
    let mut out = Vec::with_capacity(n);
    out.push(near);
    for i in 1..n - 1 {
        let q = 1.0 - i as f64 / (n - 1) as f64;
        // the bin whose [cdf[b], cdf[b + 1]) holds q, then linear within it
        let b = cdf.partition_point(|&c| c <= q).clamp(1, BINS) - 1;
        let t = ((q - cdf[b]) / (cdf[b + 1] - cdf[b])).clamp(0.0, 1.0);
        out.push(far + range * (b as f64 + t) / BINS as f64);
    }
    out.push(far);
    out
}

fn check_planes(n: usize) -> Result<(), MpiError> {
    if !(1..=MAX_PLANES).contains(&n) {
        return Err(MpiError::Invalid(format!(
            "layering: {n} planes requested; the built-in layering makes 1 to {MAX_PLANES}"
        )));
    }
    Ok(())
}

fn check_range((near, far): (f64, f64)) -> Result<(f64, f64), MpiError> {
    if !(near.is_finite() && far.is_finite() && far >= 0.0 && near > far) {
        return Err(MpiError::Invalid(format!(
            "layering: disparity range (near {near}, far {far}) must be finite with near > far >= 0"
        )));
    }
    Ok((near, far))
}

/// Where one pixel goes: composited weight `a_near` on plane `near` and the rest on `far`
/// (`far == near` when the pixel lies wholly on one plane, alpha 1 there). Plane indices fit a
/// `u8` because there are at most [`MAX_PLANES`] planes.
#[derive(Clone, Copy, Debug)]
struct Slot {
    near: u8,
    far: u8,
    a_near: f32,
}

fn assign(d: f64, disp: &[f64], layering: Layering) -> Slot {
    let n = disp.len();
    // planes with disp >= d form a prefix (disparities decrease)
    let j = disp.partition_point(|&p| p >= d);
    let whole = |i: usize| Slot { near: i as u8, far: i as u8, a_near: 1.0 };
    if j == 0 {
        return whole(0);
    }
    if j == n {
        return whole(n - 1);
    }
    let k = j - 1;
    let t = ((d - disp[k + 1]) / (disp[k] - disp[k + 1])).clamp(0.0, 1.0);
    match layering {
        Layering::Hard if t >= 0.5 => whole(k),
        Layering::Hard => whole(k + 1),
        Layering::Soft | Layering::TrueDepth if t >= 1.0 => whole(k),
        Layering::Soft | Layering::TrueDepth => Slot { near: k as u8, far: (k + 1) as u8, a_near: t as f32 },
    }
}

fn build(
    rgb: &[f32],
    depth: &[f32],
    width: usize,
    height: usize,
    opts: &LayeringOptions,
    k: Option<&Intrinsics>,
    masks: Option<&[bool]>,
) -> Result<Mpi, MpiError> {
    let len = check_inputs(rgb, depth, width, height, opts)?;

    // 2. disparities, unknown ones filled from the nearest known pixel
    let (disp, dmin, dmax) = known_disparities(depth, width, height)?;

    // 3. planes, 4. assignment
    let mut planes = plane_disparities(dmax, dmin, opts)?;
    if opts.placement == Placement::Content && opts.disparity_range.is_none() && planes.len() > 2 {
        planes = content_planes(&disp, planes[0], planes[planes.len() - 1], planes.len());
    }
    let n = planes.len();
    let slots: Vec<Slot> = disp.par_iter().map(|&d| assign(d, &planes, opts.layering)).collect();
    // Plane i's colour sources are the pixels on it or behind it: disparity <= disp_i or alpha
    // > 0 on plane i. For every layering above that is exactly `i <= far`; the farthest content
    // is a source for every plane (so that planes behind all content still have sources).
    let lim: Vec<u8> = slots.iter().zip(&disp).map(|(s, &d)| if d <= dmin { (n - 1) as u8 } else { s.far }).collect();
    // 7. the completed background behind what hides it, 8. seam overlaps of hard planes
    let back = opts.backdrop.then(|| {
        let no_masks = vec![false; if masks.is_none() { len } else { 0 }];
        super::backdrop::complete(rgb, &disp, masks.unwrap_or(&no_masks), width, height)
    });
    let hidden = back.as_ref().map_or_else(Vec::new, |b| hidden_planes(b, &disp, &planes));
    let back_rgb: &[f32] = back.as_ref().map_or(&[], |b| &b.rgb);
    let surface = (opts.layering == Layering::TrueDepth)
        .then(|| std::sync::Arc::new(super::Surface { disparity: disp.iter().map(|&d| d as f32).collect() }));
    drop(disp);
    let seam = if opts.layering == Layering::Hard { seams(&slots, width, height) } else { Vec::new() };

    let gap: Vec<f64> = plane_gaps(&planes);
    let ray_len: Option<Vec<f32>> =
        k.map(|k| (0..len).map(|p| k.unproject((p % width) as f64, (p / width) as f64).length() as f32).collect());
    let opaque_last: Vec<f32> = match &ray_len {
        Some(r) => r.iter().map(|&l| density(1.0, DELTA_LAST * l as f64)).collect(),
        None => vec![density(1.0, DELTA_LAST)],
    };

    // every value of the planes is written below (colour by `fill_plane`, density by the loop)
    let mut mpi = Mpi::to_write(width, height, planes);
    mpi.surface = surface;
    let plane_len = len * 4;
    // 6. colours of plane i: own colour where alpha > 0, background fill elsewhere; densities
    let ctx = PlaneCtx { rgb, w: width, h: height, lim: &lim, hidden: &hidden, back: back_rgb };
    mpi.rgba.par_chunks_mut(plane_len).enumerate().for_each_init(Pyramid::default, |pyramid, (i, out)| {
        fill_plane(&ctx, i, pyramid, out);
        let ray = |p: usize| ray_len.as_ref().map_or(1.0, |r| r[p] as f64);
        if i + 1 == n {
            for (p, px) in out.chunks_exact_mut(4).enumerate() {
                px[3] = opaque_last[if opaque_last.len() == 1 { 0 } else { p }];
            }
            return;
        }
        let full = density(1.0, gap[i]);
        for (p, (px, s)) in out.chunks_exact_mut(4).zip(&slots).enumerate() {
            let (near, far) = (s.near as usize, s.far as usize);
            px[3] = if i == far {
                if ray_len.is_some() {
                    density(1.0, gap[i] * ray(p))
                } else {
                    full
                }
            } else if i == near {
                density(s.a_near as f64, gap[i] * ray(p))
            } else if (!seam.is_empty() && seam[p] && i + 1 == far)
                || (!hidden.is_empty() && usize::from(hidden[p]) == i)
            {
                density(1.0, gap[i] * ray(p))
            } else {
                0.0
            };
        }
    });
    // the farthest plane: the colour behind each pixel (the fill of the plane behind its planes)
    if n > 1 {
        let (front, back) = mpi.rgba.split_at_mut((n - 1) * plane_len);
        let front: &[f32] = front;
        let g = Grid::new(width, height);
        back.par_chunks_mut(4 * width).enumerate().for_each(|(y, row)| {
            for (x, px) in row.chunks_exact_mut(4).enumerate() {
                let p = g.index(x, y);
                let behind = hidden.get(p).map_or(0, |&hb| if hb == NO_HIDDEN { 0 } else { hb as usize });
                let j = (lim[p] as usize).max(behind) + 1;
                if j < n - 1 {
                    let q = j * plane_len + 4 * p;
                    px[..3].copy_from_slice(&front[q..q + 3]);
                }
            }
        });
    }
    Ok(mpi)
}

/// Step 1: the inputs' sizes, the options' plane count and range, finite colours; returns the
/// pixel count.
fn check_inputs(
    rgb: &[f32],
    depth: &[f32],
    width: usize,
    height: usize,
    opts: &LayeringOptions,
) -> Result<usize, MpiError> {
    if width == 0 || height == 0 {
        return Err(MpiError::Invalid(format!("layering: empty image size {width}x{height}")));
    }
    let len = width
        .checked_mul(height)
        .filter(|l| l.checked_mul(4 * MAX_PLANES).is_some())
        .ok_or_else(|| MpiError::Invalid(format!("layering: image size {width}x{height} is too large")))?;
    if rgb.len() != len * 3 {
        return Err(MpiError::Invalid(format!(
            "layering: rgb has {} values, expected {width}x{height}x3 = {}",
            rgb.len(),
            len * 3
        )));
    }
    if depth.len() != len {
        return Err(MpiError::Invalid(format!(
            "layering: depth has {} values, expected {width}x{height} = {len}",
            depth.len()
        )));
    }
    check_planes(opts.planes)?;
    if let Some(r) = opts.disparity_range {
        check_range(r)?;
    }
    let bad_colours = rgb.iter().filter(|v| !v.is_finite()).count();
    if bad_colours > 0 {
        return Err(MpiError::Invalid(format!("layering: the image holds {bad_colours} non-finite colour values")));
    }
    Ok(len)
}

/// Step 2: disparities (1 / depth, f64), unknown ones copied from the nearest known pixel, with
/// their smallest and largest value.
fn known_disparities(depth: &[f32], width: usize, height: usize) -> Result<(Vec<f64>, f64, f64), MpiError> {
    let len = width * height;
    let mut disp = vec![0.0f64; len];
    let mut known = vec![false; len];
    for ((o, kn), &z) in disp.iter_mut().zip(known.iter_mut()).zip(depth) {
        if z.is_finite() && z > 0.0 {
            *o = 1.0 / z as f64;
            *kn = true;
        }
    }
    let n_known = known.iter().filter(|&&b| b).count();
    if n_known == 0 {
        return Err(MpiError::Invalid(
            "layering: the depth map has no known value (every depth is non-finite or <= 0)".into(),
        ));
    }
    if n_known < len {
        fill_nearest(&mut disp, &known, width, height);
    }
    let (mut dmin, mut dmax) = (f64::INFINITY, 0.0f64);
    for &d in &disp {
        dmin = dmin.min(d);
        dmax = dmax.max(d);
    }
    Ok((disp, dmin, dmax))
}

/// Step 7: per pixel the plane of its completed background (the plane nearest its disparity),
/// kept only strictly behind the first plane behind the pixel (what a density cut of the
/// pixel's own planes leaves standing); [`NO_HIDDEN`] elsewhere.
fn hidden_planes(b: &super::backdrop::Backdrop, disp: &[f64], planes: &[f64]) -> Vec<u16> {
    (0..disp.len())
        .into_par_iter()
        .map(|p| {
            if !b.behind[p] {
                return NO_HIDDEN;
            }
            let j = planes.partition_point(|&q| q >= disp[p]);
            let hb = assign(b.disparity[p], planes, Layering::Hard).near as usize;
            if hb > j {
                hb as u16
            } else {
                NO_HIDDEN
            }
        })
        .collect()
}

/// Step 8: the hard pixels within [`SEAM_REACH`] of a pixel on the plane just in front of their
/// own, which are also put on that plane (in front: the source view shows the same colour, that
/// plane's fill at the pixel being the pixel's own), so the two planes overlap and no crack opens
/// between them when they part under motion by up to [`SEAM_REACH`] pixels.
fn seams(slots: &[Slot], width: usize, height: usize) -> Vec<bool> {
    let g = Grid::new(width, height);
    (0..g.len())
        .into_par_iter()
        .map(|p| {
            let f = slots[p].far;
            if f == 0 {
                return false;
            }
            let (x, y) = g.xy(p);
            g.window(x, y, SEAM_REACH).pixels().any(|(xx, yy)| slots[g.index(xx, yy)].far == f - 1)
        })
        .collect()
}

/// sigma = -ln(1 - alpha) / delta, alpha clamped to (0, ALPHA_MAX], finite and <= SIGMA_MAX.
#[inline]
fn density(alpha: f64, delta: f64) -> f32 {
    let a = alpha.min(ALPHA_MAX);
    let s = -(-a).ln_1p() / delta;
    if s.is_finite() {
        (s as f32).min(SIGMA_MAX)
    } else {
        SIGMA_MAX
    }
}

/// Copies each unknown value from its nearest known pixel (multi-source BFS, 8-neighbourhood).
fn fill_nearest(v: &mut [f64], known: &[bool], w: usize, h: usize) {
    let g = Grid::new(w, h);
    let mut done = known.to_vec();
    let mut queue: VecDeque<usize> = (0..v.len()).filter(|&p| known[p]).collect();
    while let Some(p) = queue.pop_front() {
        let (x, y) = g.xy(p);
        for (nx, ny) in g.neighbours8(x, y) {
            let q = g.index(nx, ny);
            if !done[q] {
                done[q] = true;
                v[q] = v[p];
                queue.push_back(q);
            }
        }
    }
}

/// What every plane's colour fill reads.
struct PlaneCtx<'a> {
    rgb: &'a [f32],
    w: usize,
    h: usize,
    /// Pixel p is a colour source of plane i when i <= lim[p].
    lim: &'a [u8],
    /// Empty, or per pixel the plane of its hidden surface ([`NO_HIDDEN`]: none): the pixel is
    /// a source of the completed colour `back` for that plane.
    hidden: &'a [u16],
    back: &'a [f32],
}

/// Push-pull fill of plane `i`'s colours into `out` (4 values per pixel, colour in the first
/// three): the image colour at the plane's sources (`i <= lim[p]`), elsewhere a smooth fill from
/// the sources only (means of known pixels down to 1x1, then bilinear up-sampling into the
/// unknown cells, level by level: [`Pyramid`]). Plane i always has a source: the farthest content.
fn fill_plane(ctx: &PlaneCtx, i: usize, pyramid: &mut Pyramid<[f32; 3]>, out: &mut [f32]) {
    let (w, h, rgb, lim) = (ctx.w, ctx.h, ctx.rgb, ctx.lim);
    if lim.iter().all(|&l| l as usize >= i) {
        for (o, c) in out.chunks_exact_mut(4).zip(rgb.chunks_exact(3)) {
            o[..3].copy_from_slice(c);
        }
        return;
    }
    let filled = pyramid.fill(w, h, &PlaneSources { ctx, i }, |p, c| out[4 * p..4 * p + 3].copy_from_slice(&c));
    if !filled {
        // no source at all: black (the plane's buffer may hold an earlier build's values)
        for o in out.chunks_exact_mut(4) {
            o[..3].fill(0.0);
        }
    }
}

/// The colour sources of plane `i` ([`fill_plane`]).
struct PlaneSources<'a, 'b> {
    ctx: &'b PlaneCtx<'a>,
    i: usize,
}

impl Known<[f32; 3]> for PlaneSources<'_, '_> {
    #[inline(always)]
    fn at(&self, p: usize) -> Option<[f32; 3]> {
        let PlaneCtx { rgb, lim, hidden, back, .. } = *self.ctx;
        if lim[p] as usize >= self.i {
            Some([rgb[3 * p], rgb[3 * p + 1], rgb[3 * p + 2]])
        } else if !hidden.is_empty() && usize::from(hidden[p]) == self.i {
            Some([back[3 * p], back[3 * p + 1], back[3 * p + 2]])
        } else {
            None
        }
    }
}

#[cfg(test)]
mod tests;
