//! Alias-free minification of the target view: where the view shrinks a
//! plane (the camera moves back, a zoom-out), sampling the plane's colour at the target's pixel
//! spacing skips source pixels, and detail finer than the target's grid aliases into patterns
//! image1 does not have. With [`RenderParams::minify`], each plane whose local
//! scale `s` (source pixels per target pixel, the larger of the two axes of the plane's mapping
//! at the frame's centre, so the same for every window) exceeds 1 is sampled from a pyramid of
//! prefiltered levels at the level of detail `lod = log2 s`: between level `floor(lod)` and the
//! next, blended linearly ("trilinear"), level 0 being the render's own kernel and the others
//! bilinear. Level `l + 1` is level `l` filtered by the binomial `[1 3 3 1] / 8` in x and y and
//! decimated by 2 (its pixel `x` is centred on `2 x + 0.5` of level `l`; frequency response
//! `cos^3(pi f)`: 3% left at 0.4 cycles per pixel, 96% at 0.05), edges replicated. The colour
//! is averaged weighted by the density (so empty parts of a plane do not tint its edges),
//! plainly where a footprint holds no density. The levels do not depend on the view: a scene
//! prepared for the option keeps them with its MPI ([`crate::mpi::Mpi::mip`], levels 1 to
//! [`CACHED_LEVELS`], about a third of the colour's size), so a sample only samples them; a
//! render of an MPI without them builds the levels its minified planes need. Only colour: density, masks, depth and flow stay
//! the kernel's, so the labels do not depend on this option; planes at scale <= 1 are sampled
//! exactly as without it.

use rayon::prelude::*;

use super::real::Real;
use super::types::RenderParams;
use crate::mpi::{MipLevel, MipLevels, Mpi};

/// Levels kept with a prepared scene (1 to 4: planes shrunk up to 16 times get exact levels;
/// beyond, the top level is used).
pub const CACHED_LEVELS: usize = 4;

/// Largest level of detail used (a plane shrunk more than 256 times covers a few pixels).
const MAX_LOD: f64 = 8.0;

/// The binomial `[1 3 3 1] / 8` filter and decimation by 2 along x of an `w` x `h` image of `ch`
/// values per pixel (output pixel `x` centred on input `2 x + 0.5`, edges replicated).
fn down_x(src: &[f32], w: usize, h: usize, ch: usize) -> (Vec<f32>, usize) {
    const K: [f32; 4] = [0.125, 0.375, 0.375, 0.125];
    let w2 = w.div_ceil(2);
    let mut out = vec![0.0f32; w2 * h * ch];
    for (row_out, row_in) in out.chunks_exact_mut(w2 * ch).zip(src.chunks_exact(w * ch)) {
        for x in 0..w2 {
            let o = &mut row_out[ch * x..ch * x + ch];
            for (k, &wk) in K.iter().enumerate() {
                let sx = (2 * x + k).saturating_sub(1).min(w - 1);
                for (oc, &v) in o.iter_mut().zip(&row_in[ch * sx..ch * sx + ch]) {
                    *oc += wk * v;
                }
            }
        }
    }
    (out, w2)
}

/// The same along y.
fn down_y(src: &[f32], w: usize, h: usize, ch: usize) -> (Vec<f32>, usize) {
    const K: [f32; 4] = [0.125, 0.375, 0.375, 0.125];
    let h2 = h.div_ceil(2);
    let stride = w * ch;
    let mut out = vec![0.0f32; stride * h2];
    for (y, row_out) in out.chunks_exact_mut(stride).enumerate() {
        for (k, &wk) in K.iter().enumerate() {
            let sy = (2 * y + k).saturating_sub(1).min(h - 1);
            for (o, &v) in row_out.iter_mut().zip(&src[sy * stride..sy * stride + stride]) {
                *o += wk * v;
            }
        }
    }
    (out, h2)
}

/// Density below which a footprint counts as empty (its colour is then the plain mean; the
/// density-weighted mean is taken with this added to every density, so the two join smoothly).
const EMPTY: f32 = 1e-6;

/// The next level of a level given as premultiplied values: (colour x (density + EMPTY),
/// density + EMPTY) per pixel, 4 values.
fn down(pre: &[f32], w: usize, h: usize) -> (Vec<f32>, usize, usize) {
    let (hx, w2) = down_x(pre, w, h, 4);
    let (both, h2) = down_y(&hx, w2, h, 4);
    (both, w2, h2)
}

fn level_of(pre: &[f32], w: usize, h: usize) -> MipLevel {
    let mut rgb = Vec::with_capacity(3 * w * h);
    let mut sigma = Vec::with_capacity(w * h);
    for px in pre.chunks_exact(4) {
        let s = px[3];
        rgb.extend_from_slice(&[px[0] / s, px[1] / s, px[2] / s]);
        sigma.push((s - EMPTY).max(0.0));
    }
    MipLevel { rgb, sigma, width: w, height: h }
}

/// Levels 1 to `levels` (fewer when the plane reaches 1 x 1) of one plane's RGBA.
pub fn plane_levels(rgba: &[f32], w: usize, h: usize, levels: usize) -> Vec<MipLevel> {
    let mut pre: Vec<f32> = Vec::with_capacity(rgba.len());
    for px in rgba.chunks_exact(4) {
        let s = px[3].max(0.0) + EMPTY;
        pre.extend_from_slice(&[px[0] * s, px[1] * s, px[2] * s, s]);
    }
    let (mut cw, mut chh) = (w, h);
    let mut out = Vec::with_capacity(levels);
    for _ in 0..levels {
        if cw == 1 && chh == 1 {
            break;
        }
        let (next, w2, h2) = down(&pre, cw, chh);
        out.push(level_of(&next, w2, h2));
        (pre, cw, chh) = (next, w2, h2);
    }
    out
}

/// Levels 1 to [`CACHED_LEVELS`] of every plane of `mpi`.
pub fn mip_levels(mpi: &Mpi) -> MipLevels {
    let mpi = &*mpi.unpacked();
    let planes = (0..mpi.planes())
        .into_par_iter()
        .map(|i| plane_levels(mpi.plane_rgba(i), mpi.width, mpi.height, CACHED_LEVELS))
        .collect();
    MipLevels { planes }
}

/// Computes the levels (if the shared `mpi` does not hold them) and keeps them in
/// [`Mpi::mip`] (copying the MPI first only when others hold it).
pub fn prefilter_arc(mpi: &mut std::sync::Arc<Mpi>) {
    if mpi.mip.is_none() {
        let levels = std::sync::Arc::new(mip_levels(mpi));
        std::sync::Arc::make_mut(mpi).mip = Some(levels);
    }
}

/// Bilinear colour of a level at level-0 coordinates `(qx, qy)`, the level's pixels being
/// `scale` level-0 pixels wide.
fn sample_level(l: &MipLevel, qx: f32, qy: f32, scale: f32) -> [f32; 3] {
    let x = ((qx + 0.5) / scale - 0.5).clamp(0.0, (l.width - 1) as f32);
    let y = ((qy + 0.5) / scale - 0.5).clamp(0.0, (l.height - 1) as f32);
    let (x0, y0) = (x as usize, y as usize);
    let (x1, y1) = ((x0 + 1).min(l.width - 1), (y0 + 1).min(l.height - 1));
    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
    let at = |xx: usize, yy: usize, c: usize| l.rgb[3 * (yy * l.width + xx) + c];
    [0, 1, 2].map(|c| {
        let top = at(x0, y0, c) + fx * (at(x1, y0, c) - at(x0, y0, c));
        let bottom = at(x0, y1, c) + fx * (at(x1, y1, c) - at(x0, y1, c));
        (top + fy * (bottom - top)).clamp(0.0, 1.0)
    })
}

/// A minified plane of one render: its level of detail and its levels 1, 2, ...
pub(crate) struct MipPlane<'a> {
    lod: f32,
    levels: &'a [MipLevel],
}

impl MipPlane<'_> {
    /// The colour at `(qx, qy)` (level-0 coordinates): level 0 (`base`, the render's kernel)
    /// blended with level 1 below lod 1, levels `l` and `l + 1` above (the top level beyond the
    /// levels held).
    #[inline]
    pub(crate) fn colour<T: Real>(&self, qx: T, qy: T, base: impl FnOnce() -> [T; 3]) -> [T; 3] {
        let (x, y) = (qx.f32(), qy.f32());
        let n = self.levels.len();
        let l = (self.lod.floor() as usize).min(n);
        let f = if l == n { 0.0 } else { self.lod - l as f32 };
        let sample = |level: usize| sample_level(&self.levels[level - 1], x, y, (1u32 << level) as f32);
        let a: [f32; 3] = if l == 0 { base().map(Real::f32) } else { sample(l) };
        if f <= 0.0 {
            return a.map(T::of32);
        }
        let b = sample(l + 1);
        [0, 1, 2].map(|c| T::of32(a[c] + f * (b[c] - a[c])))
    }
}

/// The level of detail of the plane at disparity `disp` in the target view of `p`: `log2` of
/// the larger axis scale (source pixels per target pixel) of the plane's mapping at the target
/// frame's principal point; `None` where the mapping is degenerate there (the plane is behind
/// the target camera or seen edge-on).
pub fn plane_lod(p: &RenderParams, disp: f64) -> Option<f64> {
    let (ks, kt) = (p.k_src, p.k_tgt);
    let rt = p.pose.rotation.transpose();
    let c = p.pose.target_centre_in_source();
    let k = -c.z;
    let q = |x: f64, y: f64| -> Option<(f64, f64)> {
        let u = glam::DVec3::new((x - kt.cx) / kt.fx, (y - kt.cy) / kt.fy, 1.0);
        let v = rt * u;
        if v.z.abs() < 1e-12 {
            return None;
        }
        let g = (1.0 + k * disp) / v.z;
        (g > 0.0 && g.is_finite())
            .then_some((ks.fx * (c.x * disp + v.x * g) + ks.cx, ks.fy * (c.y * disp + v.y * g) + ks.cy))
    };
    let (x, y) = (kt.cx, kt.cy);
    let (q0, qx, qy) = (q(x, y)?, q(x + 1.0, y)?, q(x, y + 1.0)?);
    let sx = (qx.0 - q0.0).hypot(qx.1 - q0.1);
    let sy = (qy.0 - q0.0).hypot(qy.1 - q0.1);
    let s = sx.max(sy);
    (s.is_finite() && s > 0.0).then(|| s.log2())
}

/// The levels of detail of the planes of `mpi` in the view of `p` (`None` for a plane the view
/// does not shrink), or an empty list when `p.minify` is off or no plane is shrunk.
pub(crate) fn plane_lods(mpi: &Mpi, p: &RenderParams) -> Vec<Option<f32>> {
    if !p.minify {
        return Vec::new();
    }
    let lods: Vec<Option<f32>> =
        mpi.disparity.iter().map(|&d| plane_lod(p, d).filter(|&l| l > 0.0).map(|l| l.min(MAX_LOD) as f32)).collect();
    if lods.iter().all(Option::is_none) {
        return Vec::new();
    }
    lods
}

/// The levels a render with `lods` needs that `mpi` does not hold: each minified plane's up to
/// its lod, at most [`CACHED_LEVELS`] (so a render samples the same levels whether the MPI held
/// them or not); None when the MPI holds its levels, or nothing is minified.
pub(crate) fn missing_levels(mpi: &Mpi, lods: &[Option<f32>]) -> Option<MipLevels> {
    if lods.is_empty() || mpi.mip.as_ref().is_some_and(|m| m.planes.len() == mpi.planes()) {
        return None;
    }
    let mpi = &*mpi.unpacked();
    let planes = lods
        .par_iter()
        .enumerate()
        .map(|(i, lod)| match lod {
            Some(l) => {
                let n = (l.floor() as usize + 1).min(CACHED_LEVELS);
                plane_levels(mpi.plane_rgba(i), mpi.width, mpi.height, n)
            }
            None => Vec::new(),
        })
        .collect();
    Some(MipLevels { planes })
}

/// The minified planes of a render: `lods` with the levels of `levels`.
pub(crate) fn mip_planes<'a>(lods: &[Option<f32>], levels: &'a MipLevels) -> Vec<Option<MipPlane<'a>>> {
    lods.iter()
        .zip(&levels.planes)
        .map(|(lod, lv)| lod.filter(|_| !lv.is_empty()).map(|lod| MipPlane { lod, levels: lv }))
        .collect()
}
