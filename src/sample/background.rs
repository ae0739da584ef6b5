//! Background from the MPI before 2-D inpainting: where a moved object leaves
//! its place, image2 shows what the scene's own planes hold behind it, and only what no plane
//! covers is left to Telea.
//!
//! # Rule ([`Background::Planes`], with the depth-aware merge; opt-in)
//!
//! The moved objects' union mask `U` (their footprint, [`super::object::object_footprint`], with
//! the depth-aware merge) takes the object out of the MPI: at a source pixel `p` with
//! `U(p) > 0` the planes that carry the pixel's own surface, the planes at or in front of its
//! disparity `d(p)` and the first plane behind it (the built-in layering puts a pixel on the
//! two planes around its disparity, [`crate::mpi::layering`]), keep `1 - U(p)` of their density
//! ([`DensityCut`]); the planes behind stay. The camera render of that MPI over the holes of the
//! merge ([`crate::render::cut::render_cut`], bilinear) shows the background: the built-in
//! layering's hidden colours (its back planes hold the colour behind each pixel, filled from
//! the local background) or an MPI network's back planes. The hole pixels where that render's
//! coverage reaches the merge's threshold, opened by a vertical 1 x 3 segment (only column runs
//! of at least three such pixels: a sliver of one or two hole rows between rows that show the
//! scene would otherwise become a line of background colour), take its colour and depth and are
//! no longer holes; the rest stays a hole for Telea.
//!
//! Labels do not change: no valid source pixel is visible at a hole pixel (the honest rule already
//! marks every pixel landing next to a hole occluded, and those stay occluded), so filling holes
//! cannot break a label law. The links (backward and clip flows) keep treating filled pixels as
//! holes: their surface is not in the source frame's visible scene.
//!
//! With the built-in layering's completed background ([`crate::mpi::backdrop`]) the planes hold,
//! behind every object, the photo's own background texture at the depth of the background
//! around it, so what a moved object uncovers is rendered like the rest of the scene (right
//! parallax, the photo's detail and noise) and only what no plane covers is left to Telea
//! (`mpiflow bench quality --realism`, docs/quality.md).
//!
//! [`Background::Inpaint`] leaves every hole to Telea (the paper's rule; the reference merge rule
//! always does). It is the default: on RGB-D photos whose object masks span many depths (a mask
//! that includes part of the floor), the planes' render over the holes alternates row by row
//! between the floor and what lies behind it, which Telea's blend hides (`tests/samples/labels.rs`,
//! thin-line runs; `mpiflow bench quality`, column "lines img2 / img1").

use serde::{Deserialize, Serialize};

use super::merge::unit_to_u8;
use super::object::{scene_mask_window, support_rect};
use crate::geometry::Pose;
use crate::raster::grid::pixel_values;
use crate::raster::Grid;
use crate::render::cut::render_cut;
use crate::render::{DensityCut, Occupancy, Rect, RenderError, RenderParams, Skip};
use crate::scene::Scene;

/// What fills the holes of image2 before 2-D inpainting.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Background {
    /// The MPI's planes behind the moved objects, then Telea for what they do not cover.
    Planes,
    /// Telea for every hole (the paper's rule; the default, see the module documentation).
    #[default]
    Inpaint,
}

impl std::fmt::Display for Background {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Background::Planes => "planes",
            Background::Inpaint => "inpaint",
        })
    }
}

impl std::str::FromStr for Background {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "planes" => Ok(Background::Planes),
            "inpaint" => Ok(Background::Inpaint),
            _ => Err(format!("unknown background `{s}` (expected planes or inpaint)")),
        }
    }
}

/// The farthest plane cut at each source pixel under `union` (see the module documentation):
/// the first plane behind the pixel's disparity (the last plane when none is behind). Pixels
/// outside `union` get 0 (they are not cut: the mask is 0 there).
pub fn cut_planes(scene: &Scene, union: &[f32]) -> Vec<u8> {
    let planes = &scene.mpi.disparity;
    let last_plane = planes.len().saturating_sub(1);
    union
        .iter()
        .zip(&scene.disparity.data)
        .map(|(&u, &d)| {
            if u <= 0.0 {
                return 0;
            }
            // planes are ordered nearest (largest disparity) first
            let in_front = planes.iter().take_while(|&&p| p >= f64::from(d)).count();
            u8::try_from(in_front.min(last_plane)).unwrap_or(u8::MAX)
        })
        .collect()
}

/// One frame to fill: its camera pose and the merge's image2, hole mask and shown depth.
pub struct Frame<'a> {
    pub pose: Pose,
    /// The rectangle of the MPI's frame the buffers below cover (the whole frame, or a crop).
    pub at: Rect,
    /// H x W x 3.
    pub image: &'a mut [u8],
    /// H x W, 1 = hole; cleared where the planes fill it.
    pub hole: &'a mut [u8],
    /// H x W, the depth image2 shows; set where the planes fill it.
    pub depth: &'a mut [f32],
}

/// The planes behind the moved objects that fill holes: the scene (its MPI and intrinsics)
/// with its tile occupancy and work skipping, the moved objects' union mask and the farthest
/// plane cut at each source pixel ([`cut_planes`]), and the coverage a filled pixel needs.
pub struct PlanesBehind<'a> {
    pub scene: &'a Scene,
    pub occupancy: Option<&'a Occupancy>,
    pub skip: Skip,
    /// H x W, the moved objects' union mask.
    pub union: &'a [f32],
    /// H x W, [`cut_planes`] of `union`.
    pub last: &'a [u8],
    /// The render's coverage at a filled pixel: at least this (the merge's mask threshold).
    pub threshold: f32,
}

/// Fills the holes of `frame` that the MPI's planes behind the moved objects cover, returning
/// how many it filled.
pub fn fill_from_planes(planes: &PlanesBehind<'_>, frame: Frame<'_>) -> Result<u64, RenderError> {
    let PlanesBehind { scene, occupancy, skip, union, last, threshold } = *planes;
    let (mpi, k) = (&*scene.mpi, &scene.intrinsics);
    let at = frame.at;
    let g = Grid::new(at.width(), at.height());
    // only holes where the objects' places land can show what lies behind them
    let Some(support) = support_rect(union, mpi.width, mpi.height) else { return Ok(0) };
    let reach = scene_mask_window(mpi, k, &frame.pose, &support).intersect(&at);
    let Some(local_win) = hole_rect(frame.hole, g, &reach.local_to(&at)) else { return Ok(0) };
    // the render's window in the MPI's frame
    let win =
        Rect { x0: local_win.x0 + at.x0, y0: local_win.y0 + at.y0, x1: local_win.x1 + at.x0, y1: local_win.y1 + at.y0 };
    let mut params = RenderParams::new(*k, frame.pose);
    params.skip = skip;
    let r = render_cut::<f32>(mpi, &params, occupancy, &win, &DensityCut { mask: union, last })?;
    let local = Grid::new(win.width(), win.y1 - win.y0);
    // the holes the planes cover, then only their column runs of at least three pixels (an
    // opening): a sliver one or two rows tall between rows that show the scene is left to
    // Telea, which blends it with those rows, where the planes' background would draw a line
    let candidate: Vec<bool> = (0..local.len())
        .map(|o| {
            let (lx, ly) = local.xy(o);
            frame.hole[g.index(local_win.x0 + lx, local_win.y0 + ly)] != 0 && r.out.coverage[o] >= threshold
        })
        .collect();
    let fill = opening_v3(&candidate, local);
    let mut filled = 0u64;
    for y in local_win.y0..local_win.y1 {
        for x in local_win.x0..local_win.x1 {
            let (p, o) = (g.index(x, y), local.index(x - local_win.x0, y - local_win.y0));
            if !fill[o] {
                continue;
            }
            for (d, &v) in frame.image[pixel_values(p, 3)].iter_mut().zip(&r.out.image[pixel_values(o, 3)]) {
                *d = unit_to_u8(v);
            }
            let d = r.out.depth[o];
            frame.depth[p] = if d.is_finite() && d > 0.0 { d } else { 0.0 };
            frame.hole[p] = 0;
            filled += 1;
        }
    }
    Ok(filled)
}

/// The opening of `m` (of grid `g`) by a vertical 1 x 3 segment: the pixels of `m` in a column
/// run of at least three (outside the grid counts as not in `m`).
fn opening_v3(m: &[bool], g: Grid) -> Vec<bool> {
    let mut out = vec![false; g.len()];
    for x in 0..g.w {
        let mut y = 0;
        while y < g.h {
            if !m[g.index(x, y)] {
                y += 1;
                continue;
            }
            let start = y;
            while y < g.h && m[g.index(x, y)] {
                y += 1;
            }
            if y - start >= 3 {
                (start..y).for_each(|r| out[g.index(x, r)] = true);
            }
        }
    }
    out
}

/// The bounding box of the hole pixels (of grid `g`) inside `within`, if any.
fn hole_rect(hole: &[u8], g: Grid, within: &Rect) -> Option<Rect> {
    let (mut x0, mut y0, mut x1, mut y1) = (usize::MAX, usize::MAX, 0, 0);
    for y in within.y0..within.y1 {
        let row = &hole[g.span(y, within.x0..within.x1)];
        let Some(first) = row.iter().position(|&v| v != 0) else { continue };
        let last = row.iter().rposition(|&v| v != 0).unwrap_or(first);
        x0 = x0.min(within.x0 + first);
        x1 = x1.max(within.x0 + last + 1);
        y0 = y0.min(y);
        y1 = y + 1;
    }
    (x0 != usize::MAX).then_some(Rect { x0, y0, x1, y1 })
}
