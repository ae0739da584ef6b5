//! The scene's completed background: what lies behind foreground, made once per scene (never
//! per sample) so that what motion reveals is the photo's own texture at the right depth, not a
//! smear.
//!
//! # Where
//!
//! The **region** is every pixel that can hide background:
//! - the pixels of the instance masks (the objects that may move), grown by [`MASK_GROW`] pixels
//!   (a mask's edge rarely sits exactly on the object's depth edge);
//! - the near side of every depth step: pixels within [`EDGE_REACH`] pixels (chessboard
//!   distance) of a pixel that has a 4-neighbour whose disparity is below `(1 - EDGE_STEP)` times
//!   its own (what a camera motion can uncover next to them; a smooth slope has no such step).
//!
//! # Depth behind the region
//!
//! For an edge pixel, the farthest disparity within [`EDGE_REACH`] (the background beside it).
//! For a mask pixel, the background around the mask: the disparity of the pixels outside the
//! grown masks, pulled into the masks by the push-pull pyramid ([`crate::raster::pushpull`]: means
//! of known pixels down to 1x1, bilinear up-sampling into the unknown cells), never from the masks themselves; and no nearer
//! than the edge rule's value where both apply (the smaller disparity wins). A region pixel has a
//! backdrop only where that disparity is below its own by more than [`EDGE_STEP`] (something
//! lies behind it); elsewhere it is its own background.
//!
//! # Colour behind the region (exemplar synthesis)
//!
//! Region pixels with a backdrop are completed in onion-peel order (by chessboard distance from
//! the known pixels, then row-major), each taking the colour of one **source** pixel: a pixel
//! outside the masks, with no backdrop of its own, whose disparity is at most `(1 +
//! EDGE_STEP)` times the target's backdrop disparity (background at the same or greater depth;
//! never foreground, never an object). The source is the best of a fixed candidate list by the
//! mean squared colour difference over the [`WINDOW`] x [`WINDOW`] neighbourhood (the target's
//! known or already completed pixels against the source's photo colours): the sources of the
//! eight neighbours shifted by the step to the target (coherence: whole patches of texture are
//! copied, in the spirit of Ashikhmin 2001 and PatchMatch's propagation, Barnes et al. 2009),
//! then `GLOBAL_DRAWS` random sources from the whole eligible set, then a random search around
//! the best so far at halving radii from [`SEARCH_RADIUS`] (a pixel for which no candidate could
//! be compared takes the eligible source nearest in depth). The candidates are drawn from a
//! counter-based hash of the pixel (no shared state), so the result is the same on every run and
//! machine. The
//! synthesis is [`crate::raster::exemplar`], which the texture fill of image2's holes shares.
//! Cost: `O(region x candidates x WINDOW^2)`, about 0.1-0.4 s for a 640 x 480 scene with a third
//! of it in the region (`mpiflow bench quality --realism` states the scene build's time).

use crate::raster::exemplar::{peel_order, synthesise as synthesise_exemplar, Draw, Layout, Sources};
use crate::raster::morph::dilate;
use crate::raster::pushpull::push_pull;
use crate::raster::Grid;

/// Mask pixels are grown by this many pixels (chessboard) before completion.
pub const MASK_GROW: usize = 3;
/// How far beside a depth edge the background is completed, in pixels.
pub const EDGE_REACH: usize = 24;
/// A relative disparity step that counts as a depth edge (and the depth tolerance of sources).
pub const EDGE_STEP: f64 = 0.1;
/// Side of the matching window.
pub const WINDOW: usize = 7;
/// Largest radius of the random search around the best candidate.
pub const SEARCH_RADIUS: usize = 64;
/// Random sources drawn from the whole eligible set per pixel.
const GLOBAL_DRAWS: usize = 4;

/// The completed background of a scene.
#[derive(Clone, Debug, Default)]
pub struct Backdrop {
    pub width: usize,
    pub height: usize,
    /// H x W: whether a completed background lies behind the pixel.
    pub behind: Vec<bool>,
    /// H x W x 3: the completed colour where `behind`, else the photo's.
    pub rgb: Vec<f32>,
    /// H x W: the completed disparity where `behind`, else the pixel's own.
    pub disparity: Vec<f64>,
}

impl Backdrop {
    /// Pixels with a completed background.
    pub fn count(&self) -> usize {
        self.behind.iter().filter(|&&b| b).count()
    }
}

/// Chessboard minimum filter of radius `r` (separable; O(w h r)).
fn min_filter(v: &[f64], w: usize, h: usize, r: usize) -> Vec<f64> {
    let g = Grid::new(w, h);
    let mut tmp = vec![0.0; g.len()];
    for (x, y) in g.pixels() {
        let row = g.span(y, g.window(x, y, r).xs);
        tmp[g.index(x, y)] = v[row].iter().copied().fold(f64::INFINITY, f64::min);
    }
    let mut out = vec![0.0; g.len()];
    for (x, y) in g.pixels() {
        let column = g.window(x, y, r).ys;
        out[g.index(x, y)] = column.map(|yy| tmp[g.index(x, yy)]).fold(f64::INFINITY, f64::min);
    }
    out
}

/// Completes the background of a scene: `rgb` H x W x 3 in [0, 1], `disp` H x W disparities
/// (finite, > 0), `masks` H x W (true = an object that may move). See the module documentation.
pub fn complete(rgb: &[f32], disp: &[f64], masks: &[bool], w: usize, h: usize) -> Backdrop {
    let n = w * h;
    let grown = if masks.iter().any(|&m| m) { dilate(w, h, masks, MASK_GROW) } else { vec![false; n] };
    // the farthest disparity within reach: the background beside each pixel
    // the near sides of depth steps (a 4-neighbour farther by more than EDGE_STEP), grown by
    // EDGE_REACH: a slope, however steep overall, has no such step between neighbours
    let step: Vec<bool> = (0..n)
        .map(|p| {
            let (x, y) = (p % w, p / w);
            let lower = |q: usize| disp[q] < disp[p] * (1.0 - EDGE_STEP);
            (x > 0 && lower(p - 1))
                || (x + 1 < w && lower(p + 1))
                || (y > 0 && lower(p - w))
                || (y + 1 < h && lower(p + w))
        })
        .collect();
    let band = dilate(w, h, &step, EDGE_REACH);
    let far_near = min_filter(disp, w, h, EDGE_REACH);
    let mut back: Vec<f64> = (0..n).map(|p| if band[p] { far_near[p] } else { disp[p] }).collect();
    if grown.iter().any(|&g| g) {
        let outside: Vec<bool> = grown.iter().map(|&g| !g).collect();
        let around = push_pull(disp, &outside, w, h);
        for p in 0..n {
            if grown[p] {
                back[p] = back[p].min(around[p]);
            }
        }
    }
    let behind: Vec<bool> = (0..n).map(|p| back[p] < disp[p] * (1.0 - EDGE_STEP)).collect();
    let mut out_rgb = rgb.to_vec();
    let mut out_disp = disp.to_vec();
    for p in 0..n {
        if behind[p] {
            out_disp[p] = back[p];
        }
    }
    if !behind.iter().any(|&b| b) {
        return Backdrop { width: w, height: h, behind, rgb: out_rgb, disparity: out_disp };
    }
    synthesise(&Region { rgb, disp, grown: &grown, behind: &behind, back: &back, w, h }, &mut out_rgb);
    Backdrop { width: w, height: h, behind, rgb: out_rgb, disparity: out_disp }
}

/// What the colour synthesis reads: the photo, its disparities, the grown masks, the pixels to
/// complete and their background disparity.
struct Region<'a> {
    rgb: &'a [f32],
    disp: &'a [f64],
    grown: &'a [bool],
    behind: &'a [bool],
    back: &'a [f64],
    w: usize,
    h: usize,
}

/// The exemplar synthesis of the module documentation into `out_rgb` (the photo's colours on
/// entry; the pixels of `r.behind` are replaced), by [`crate::raster::exemplar::synthesise`].
fn synthesise(r: &Region<'_>, out_rgb: &mut [f32]) {
    let Region { rgb, disp, grown, behind, back, w, h } = *r;
    let n = w * h;
    // sources: visible background, sorted by disparity (the eligible set of a target is a prefix)
    let mut sources: Vec<usize> = (0..n).filter(|&p| !grown[p] && !behind[p]).collect();
    sources.sort_by(|&a, &b| disp[a].total_cmp(&disp[b]).then(a.cmp(&b)));
    let sorted_disp: Vec<f64> = sources.iter().map(|&p| disp[p]).collect();
    let is_source: Vec<bool> = {
        let mut s = vec![false; n];
        sources.iter().for_each(|&p| s[p] = true);
        s
    };
    let eligible = |t: usize| sorted_disp.partition_point(|&d| d <= back[t] * (1.0 + EDGE_STEP));
    // onion-peel order: chessboard distance from the pixels that need no completion
    let order = peel_order(behind, w, h);
    let mut filled: Vec<bool> = behind.iter().map(|&b| !b).collect();
    let lay = Layout {
        source: Grid::new(w, h),
        target: Grid::new(w, h),
        target_left: 0,
        target_top: 0,
        half: WINDOW / 2,
        search_radius: SEARCH_RADIUS,
        salt: 0x6261_636b_6472_6f70,
        known_weight: 1,
        keep_unmatched: true,
    };
    let mut src = Sources {
        rgb,
        masked: grown,
        eligible: |t: usize, s: usize| is_source[s] && disp[s] <= back[t] * (1.0 + EDGE_STEP),
        // random sources from the whole eligible set
        seeds: |t: usize, draw: &mut Draw, out: &mut Vec<usize>| {
            let m = eligible(t);
            if m > 0 {
                out.extend((0..GLOBAL_DRAWS).map(|_| sources[draw.below(m)]));
            }
        },
        // no candidate could be compared (nothing known nearby): the nearest in depth
        fallback: |t: usize| eligible(t).checked_sub(1).map(|k| sources[k]),
    };
    synthesise_exemplar(&lay, &mut src, out_rgb, &mut filled, &order);
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A striped far wall (disparity 0.2) with a flat red square in front (disparity 1).
    fn scene(w: usize, h: usize) -> (Vec<f32>, Vec<f64>, Vec<bool>) {
        let mut rgb = vec![0.0f32; 3 * w * h];
        let mut disp = vec![0.2f64; w * h];
        let mut mask = vec![false; w * h];
        let g = Grid::new(w, h);
        for y in 0..h {
            for x in 0..w {
                let p = g.index(x, y);
                let stripe = if (x / 3) % 2 == 0 { 0.9 } else { 0.1 };
                rgb[3 * p..3 * p + 3].copy_from_slice(&[0.2, stripe, 0.5]);
                if (20..44).contains(&x) && (16..40).contains(&y) {
                    rgb[3 * p..3 * p + 3].copy_from_slice(&[1.0, 0.0, 0.0]);
                    disp[p] = 1.0;
                    mask[p] = true;
                }
            }
        }
        (rgb, disp, mask)
    }

    #[test]
    fn behind_an_object_lies_the_walls_texture_never_the_object() {
        let (w, h) = (64, 56);
        let (rgb, disp, mask) = scene(w, h);
        let b = complete(&rgb, &disp, &mask, w, h);
        for p in 0..w * h {
            if mask[p] {
                assert!(b.behind[p], "pixel {p} of the object has nothing behind it");
                assert!((b.disparity[p] - 0.2).abs() < 1e-9, "{}", b.disparity[p]);
                // never the object's red, always one of the wall's two colours
                let c = &b.rgb[3 * p..3 * p + 3];
                assert!(c[0] < 0.5 && (c[1] > 0.8 || c[1] < 0.2), "{c:?} at {p}");
            }
            if !b.behind[p] {
                assert_eq!(&b.rgb[3 * p..3 * p + 3], &rgb[3 * p..3 * p + 3]);
            }
        }
        // the stripes continue: most completed pixels have the colour of the stripe of their column
        let inside: Vec<usize> = (0..w * h).filter(|&p| mask[p]).collect();
        let right = inside.iter().filter(|&&p| (b.rgb[3 * p + 1] > 0.5) == ((p % w / 3) % 2 == 0)).count();
        assert!(right * 10 >= inside.len() * 8, "{right} of {}", inside.len());
    }

    #[test]
    fn deterministic_and_flat_scenes_have_no_backdrop() {
        let (w, h) = (64, 56);
        let (rgb, disp, mask) = scene(w, h);
        let a = complete(&rgb, &disp, &mask, w, h);
        let b = complete(&rgb, &disp, &mask, w, h);
        assert_eq!(a.rgb, b.rgb);
        let flat = complete(&rgb, &vec![0.5; w * h], &vec![false; w * h], w, h);
        assert_eq!(flat.count(), 0);
    }
}
