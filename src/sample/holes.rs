//! Filling the holes of image2 (pixels no render covers): with Telea's method on crops around
//! the holes (the whole-frame result, bit for bit), or with texture copied from image1's
//! background (exemplar synthesis) per tile of the frame.
//!
//! # Texture
//!
//! [`InpaintMethod::Exemplar`] fills a hole with patches of the photo instead of a smooth blend,
//! so what motion reveals (what enters the frame, what a moved object or a camera motion
//! uncovers) has the photo's detail and noise. Per 64 x 64 tile of the frame (independently, in
//! parallel: across a tile's border only the frame's known pixels count), the hole pixels are
//! completed in onion-peel order by [`crate::raster::exemplar`]: each copies one pixel of image1,
//! the best by the mean squared difference over the 5 x 5 window (the frame's known background,
//! weighing four times, and the already filled pixels against image1; the frame's objects, in
//! front of the hole, are left out) among the neighbours' sources shifted (whole patches are
//! copied), the pixel's own place in image1, three random places anywhere, and a random search
//! around the best at halving radii from [`TEXTURE_SEARCH`].
//!
//! A source must be image1 background (no object, moved or not, within 3 pixels) and, unless the
//! hole is what enters the frame (connected to the frame's border, where a render's edge shows
//! its far planes and no depth beside it can be trusted), at the depth of the background beside
//! the hole or farther: its disparity at most `1.1` times that of the 90th percentile of the
//! depths of the frame's known background pixels within [`TEXTURE_REACH`] of the centre of the
//! pixel's 4 x 4 block (every second row and column, not beside a hole, not an object, moved to
//! image1's camera by the camera's translation along z: the far side of the hole; no limit where
//! none is known), so foreground is not copied into what lies behind it.
//!
//! What enters the frame beside a moved object that reaches image1's border is more of that
//! object: each hole pixel connected to the border takes the frame's label of the nearest known
//! pixel, and where that is a moved object whose image1 mask touches the border, the pixel copies
//! that object's pixels in image1 (at least 3 pixels inside its mask), matched against what the
//! frame shows of the object; [`fill_holes`] returns those labels for the frame's mask.
//!
//! Hole pixels no source could be found for are left to Telea (known-only). Deterministic: the
//! random draws come from a hash of the pixel's index, and a tile's result does not depend on
//! the others.

use super::config::InpaintMethod;
use super::inpaint::{inpaint, GradientTerm, TeleaOptions, TeleaVariant};
use crate::raster::exemplar::{peel_order, synthesise, Draw, Layout, Sources};
use crate::raster::grid::{interleaved, pixel_values};
use crate::raster::morph::dilate;
use crate::raster::Grid;
use crate::render::Rect;

/// How far around a hole the texture fill looks for the background's depth (pixels, chessboard).
pub const TEXTURE_REACH: usize = 16;
/// Largest radius of the texture fill's random search, in pixels.
pub const TEXTURE_SEARCH: usize = 32;
/// Half the side of the texture fill's matching window.
const TEXTURE_HALF: usize = 2;
/// Weight of the frame's own pixels in the patch distance (filled ones weigh 1): the photo's
/// pixels beside the hole anchor the copies, so a chain of copies does not drift away from them.
const TEXTURE_KNOWN_WEIGHT: u32 = 4;
/// Random places anywhere in image1 among each pixel's candidates.
const TEXTURE_GLOBAL_DRAWS: usize = 3;
/// Side of the frame's tiles, filled independently (in parallel): a tile's pixels compare with
/// the frame's known pixels only across its border.
const TEXTURE_TILE: usize = 64;
/// Side of the frame's blocks over which the depth limit of the sources is one value.
const TEXTURE_BLOCK: usize = 4;
/// Sources keep this distance (pixels, chessboard) from image1's objects.
const TEXTURE_MASK_GROW: usize = 3;
/// A source's disparity may exceed the background's beside the hole by this factor.
const TEXTURE_DEPTH_TOLERANCE: f64 = 1.1;

/// What the texture fill copies from: the photo with its depth and object labels, and the depth
/// of the frame being filled.
#[derive(Clone, Copy, Debug)]
pub struct TextureSource<'a> {
    /// H x W x 3, the photo (image1).
    pub image1: &'a [u8],
    /// H x W, image1's depth (> 0).
    pub depth1: &'a [f32],
    /// H x W, image1's objects, moved or not (true = an object: never a source of background).
    pub objects: &'a [bool],
    /// H x W, the depth of what the frame being filled shows (0 in its holes).
    pub depth: &'a [f32],
    /// H x W, the frame's object labels (0 = background): objects are never the far side.
    pub mask: &'a [u8],
    /// H x W, image1's labels of the moved objects (0 = background; the sample's `mask1`): a
    /// moved object that reaches image1's border continues beyond it.
    pub labels1: &'a [u8],
    /// How much deeper a point of the scene lies in the frame's camera than in image1's: the
    /// camera's translation along z (rotations, a few degrees, are neglected), so the far side's
    /// depth is compared with image1's in image1's camera.
    pub z_shift: f32,
}

/// Fills the holes of `image` with `method`: the texture fill from `texture` for
/// [`InpaintMethod::Exemplar`] (Telea, known-only, for what it leaves), else Telea; Telea from
/// the frame's background only (`texture.mask`'s objects are no context: [`inpaint_background`],
/// windowed). Returns the object labels the fill drew ([`TextureFill::continued`]; empty for the
/// Telea variants), for the frame's mask.
pub fn fill_holes(
    image: &mut [u8],
    w: usize,
    h: usize,
    hole: &[u8],
    method: InpaintMethod,
    radius: f32,
    texture: &TextureSource<'_>,
) -> Vec<u8> {
    if method != InpaintMethod::Exemplar {
        inpaint_background(image, w, h, hole, texture.mask, method, radius, true);
        return Vec::new();
    }
    let fill = texture_fill(image, w, h, hole, texture);
    if fill.left.iter().any(|&o| o != 0) {
        inpaint_background(image, w, h, &fill.left, texture.mask, InpaintMethod::TeleaKnownOnly, radius, true);
    }
    fill.continued
}

/// What [`texture_fill`] did besides filling.
pub struct TextureFill {
    /// H x W, 1 = a hole pixel no source was found for (left to Telea).
    pub left: Vec<u8>,
    /// H x W, the label of the moved object a hole pixel continues (0 = background); empty when
    /// no moved object reaches image1's border.
    pub continued: Vec<u8>,
}

/// Writes the labels of the objects a fill continued ([`fill_holes`]' result) into the frame's
/// mask.
pub fn label_continued(mask: &mut [u8], continued: &[u8]) {
    for (m, &k) in mask.iter_mut().zip(continued) {
        if k != 0 {
            *m = k;
        }
    }
}

/// The nearest depth a source of the hole pixels around `(x, y)` may have: the 90th percentile
/// of the depths of the frame's known background pixels (no hole nor 4-adjacent to one, no
/// object label, depth finite and > 0) on every second row and column within [`TEXTURE_REACH`]
/// (the far side of the hole, robust to a few stray far values at a render's edge), less the
/// frame's `z_shift` (in image1's camera), brought nearer by [`TEXTURE_DEPTH_TOLERANCE`] in
/// disparity; 0 (no limit) where none is known.
fn nearest_source_depth(tex: &TextureSource<'_>, hole: &[u8], g: Grid, x: usize, y: usize, buf: &mut Vec<f32>) -> f32 {
    let reach = g.window(x, y, TEXTURE_REACH);
    buf.clear();
    for yy in reach.ys.step_by(2) {
        for xx in reach.xs.clone().step_by(2) {
            let p = g.index(xx, yy);
            let d = tex.depth[p];
            // a pixel beside a hole is often a render's frayed edge (a stray far depth): left out
            let beside = g.neighbours4(p).any(|q| hole[q] != 0);
            if hole[p] == 0 && tex.mask[p] == 0 && !beside && d > 0.0 && d.is_finite() {
                buf.push(d);
            }
        }
    }
    if buf.is_empty() {
        return 0.0;
    }
    let k = ((9 * buf.len()) / 10).min(buf.len() - 1);
    let (_, far, _) = buf.select_nth_unstable_by(k, f32::total_cmp);
    (f64::from(*far - tex.z_shift) / TEXTURE_DEPTH_TOLERANCE) as f32
}

/// The hole pixels 4-connected to a hole pixel on the frame's border: what enters the frame.
fn entering(hole: &[u8], g: Grid) -> Vec<bool> {
    let mut seen = vec![false; g.len()];
    let mut stack: Vec<usize> = g.border().filter(|&p| hole[p] != 0).collect();
    stack.iter().for_each(|&p| seen[p] = true);
    while let Some(p) = stack.pop() {
        for q in g.neighbours4(p) {
            if hole[q] != 0 && !seen[q] {
                seen[q] = true;
                stack.push(q);
            }
        }
    }
    seen
}

/// The moved objects that continue beyond image1's frame: `reaches[k]` when label `k` of
/// `labels1` has a pixel on the frame's border.
fn reaching_border(labels1: &[u8], g: Grid) -> [bool; 256] {
    let mut reaches = [false; 256];
    for p in g.border() {
        reaches[usize::from(labels1[p])] = true;
    }
    reaches[0] = false;
    reaches
}

/// The object each entering hole pixel continues (0 = background): the frame's label of the
/// nearest known pixel (4-connected breadth-first search over the entering hole pixels from the
/// known pixels beside them, in index order), kept where that object reaches image1's border.
fn continued_objects(hole: &[u8], entering: &[bool], mask: &[u8], reaches: &[bool; 256], g: Grid) -> Vec<u8> {
    let n = g.len();
    let mut owner = vec![0u8; n];
    let mut seen = vec![false; n];
    // the known pixels beside what enters, in index order
    let mut seeds: Vec<usize> =
        (0..n).filter(|&p| entering[p]).flat_map(|p| g.neighbours4(p).filter(|&q| hole[q] == 0)).collect();
    seeds.sort_unstable();
    seeds.dedup();
    let mut queue = std::collections::VecDeque::with_capacity(seeds.len());
    for p in seeds {
        seen[p] = true;
        owner[p] = mask[p];
        queue.push_back(p);
    }
    while let Some(p) = queue.pop_front() {
        for q in g.neighbours4(p) {
            if entering[q] && !seen[q] {
                seen[q] = true;
                owner[q] = owner[p];
                queue.push_back(q);
            }
        }
    }
    for p in 0..n {
        if hole[p] == 0 || !reaches[usize::from(owner[p])] {
            owner[p] = 0;
        }
    }
    owner
}

/// One continued object: its sources are image1's pixels of its label at least
/// [`TEXTURE_MASK_GROW`] inside its edge.
struct Continued {
    label: u8,
    /// H x W, true outside the object (left out of the patch distance).
    outside: Vec<bool>,
    /// H x W, true within [`TEXTURE_MASK_GROW`] of a pixel outside the object (never a source).
    near_outside: Vec<bool>,
}

/// Draws of a place anywhere in image1 for one random candidate of a continued object: the first
/// of this many uniform draws that falls on the object.
const CONTINUED_DRAW_TRIES: usize = 8;

/// The texture fill of the module documentation.
pub fn texture_fill(image: &mut [u8], w: usize, h: usize, hole: &[u8], tex: &TextureSource<'_>) -> TextureFill {
    use rayon::prelude::*;
    let g = Grid::new(w, h);
    let n = g.len();
    assert!(image.len() == 3 * n && hole.len() == n && tex.image1.len() == 3 * n, "texture fill: sizes");
    assert!(tex.depth1.len() == n && tex.objects.len() == n && tex.depth.len() == n, "texture fill: sizes");
    assert!(tex.mask.len() == n && tex.labels1.len() == n, "texture fill: sizes");
    let plan = FillPlan::new(g, hole, tex);
    let frame: &[u8] = image;
    let results: Vec<(Rect, Rect, Vec<u8>, Vec<u32>)> = hole_tiles(hole, g)
        .par_iter()
        .map(|&(tile, win)| {
            let (img, src_of) = plan.fill_tile(frame, tile, win);
            (tile, win, img, src_of)
        })
        .collect();
    let mut left = vec![0u8; n];
    for (tile, win, img, src_of) in results {
        let local = Grid::new(win.width(), win.height());
        for y in tile.y0..tile.y1 {
            for x in tile.x0..tile.x1 {
                let (p, l) = (g.index(x, y), local.index(x - win.x0, y - win.y0));
                if hole[p] != 0 {
                    if src_of[l] == u32::MAX {
                        left[p] = 1;
                    } else {
                        image[pixel_values(p, 3)].copy_from_slice(&img[pixel_values(l, 3)]);
                    }
                }
            }
        }
    }
    TextureFill { left, continued: plan.owner }
}

/// The frame's [`TEXTURE_TILE`] tiles that hold a hole pixel, each with its window: the tile grown
/// by the matching window's reach.
fn hole_tiles(hole: &[u8], g: Grid) -> Vec<(Rect, Rect)> {
    let Grid { w, h } = g;
    let (tx, ty) = (w.div_ceil(TEXTURE_TILE), h.div_ceil(TEXTURE_TILE));
    (0..tx * ty)
        .map(|k| {
            let (x0, y0) = ((k % tx) * TEXTURE_TILE, (k / tx) * TEXTURE_TILE);
            Rect { x0, y0, x1: (x0 + TEXTURE_TILE).min(w), y1: (y0 + TEXTURE_TILE).min(h) }
        })
        .filter(|t| (t.y0..t.y1).any(|y| hole[g.span(y, t.x0..t.x1)].iter().any(|&o| o != 0)))
        .map(|t| (t, t.grow(TEXTURE_HALF, w, h)))
        .collect()
}

/// What every tile of one texture fill reads: the frame's holes, what enters the frame, the
/// continued objects and where sources may not lie.
struct FillPlan<'a> {
    grid: Grid,
    hole: &'a [u8],
    tex: &'a TextureSource<'a>,
    /// H x W, the hole pixels connected to the frame's border.
    entering: Vec<bool>,
    /// H x W, the moved object each hole pixel continues (0 = background); empty when no moved
    /// object reaches image1's border.
    owner: Vec<u8>,
    continued: Vec<Continued>,
    /// H x W, within [`TEXTURE_MASK_GROW`] of one of image1's objects (never a background source).
    near_object: Vec<bool>,
}

/// One synthesis of a tile: which pixels it completes, from which of image1's pixels, matched
/// against which of the frame's.
struct Part<'a, E, D> {
    /// The tile window's pixels to complete.
    todo: &'a [bool],
    /// The label of the frame's pixels matched (0: the background).
    label: u8,
    /// image1's pixels left out of the patch distance.
    masked: &'a [bool],
    /// Whether image1's pixel `s` may be copied into window pixel `t`.
    eligible: E,
    /// One random candidate anywhere in image1 (none: the draws missed).
    draw: D,
    salt: u64,
}

impl<'a> FillPlan<'a> {
    fn new(grid: Grid, hole: &'a [u8], tex: &'a TextureSource<'a>) -> Self {
        let Grid { w, h } = grid;
        let masked = tex.objects;
        // sources keep their distance from every object: the objects grown once
        let near_object =
            if masked.contains(&true) { dilate(w, h, masked, TEXTURE_MASK_GROW) } else { vec![false; w * h] };
        let entering = entering(hole, grid);
        // what a moved object reaching image1's border brings into the frame is more of that object
        let reaches = reaching_border(tex.labels1, grid);
        let owner = if reaches.contains(&true) {
            continued_objects(hole, &entering, tex.mask, &reaches, grid)
        } else {
            Vec::new()
        };
        let continued: Vec<Continued> = (1..=255u8)
            .filter(|&k| reaches[usize::from(k)] && owner.contains(&k))
            .map(|label| {
                let outside: Vec<bool> = tex.labels1.iter().map(|&l| l != label).collect();
                let near_outside = dilate(w, h, &outside, TEXTURE_MASK_GROW);
                Continued { label, outside, near_outside }
            })
            .collect();
        Self { grid, hole, tex, entering, owner, continued, near_object }
    }

    /// Fills the hole pixels of `tile` in a copy of `frame`'s window `win`: the background, then
    /// each continued object. Returns the window's colours and, per window pixel, the source it
    /// copied (`u32::MAX` where none).
    fn fill_tile(&self, frame: &[u8], tile: Rect, win: Rect) -> (Vec<u8>, Vec<u32>) {
        let (g, hole, tex) = (self.grid, self.hole, self.tex);
        let n = g.len();
        let local = Grid::new(win.width(), win.height());
        let owned = |p: usize| !self.owner.is_empty() && self.owner[p] != 0;
        let mut img = Vec::with_capacity(local.len() * 3);
        let mut todo = Vec::with_capacity(local.len());
        for y in win.y0..win.y1 {
            img.extend_from_slice(&frame[interleaved(g.span(y, win.x0..win.x1), 3)]);
            todo.extend((win.x0..win.x1).map(|x| {
                let p = g.index(x, y);
                tile.contains(x, y) && hole[p] != 0 && !owned(p)
            }));
        }
        let nearest = self.depth_limits(&todo, win);
        let lay = Layout {
            source: g,
            target: local,
            target_left: win.x0,
            target_top: win.y0,
            half: TEXTURE_HALF,
            search_radius: TEXTURE_SEARCH,
            salt: 0x7465_7874_7572_6521,
            known_weight: TEXTURE_KNOWN_WEIGHT,
            keep_unmatched: false,
        };
        let background = Part {
            todo: &todo,
            label: 0,
            masked: tex.objects,
            // background at the far side's depth or farther, not next to an object (a mask's
            // edge rarely sits exactly on the object's)
            eligible: |t: usize, s: usize| {
                let d = tex.depth1[s];
                d > 0.0 && d >= nearest[t] && !self.near_object[s]
            },
            draw: |draw: &mut Draw| Some(draw.below(n)),
            salt: lay.salt,
        };
        let mut src_of = self.synthesise_part(&lay, win, background, &mut img);
        // the continued objects: their own pixels in image1 matched against what the frame shows
        // of them
        for c in &self.continued {
            let todo: Vec<bool> = (0..local.len())
                .map(|l| {
                    let (lx, ly) = local.xy(l);
                    let (x, y) = (win.x0 + lx, win.y0 + ly);
                    tile.contains(x, y) && self.owner[g.index(x, y)] == c.label
                })
                .collect();
            if !todo.contains(&true) {
                continue;
            }
            let part = Part {
                todo: &todo,
                label: c.label,
                masked: &c.outside,
                eligible: |_t: usize, s: usize| !c.near_outside[s],
                draw: |draw: &mut Draw| (0..CONTINUED_DRAW_TRIES).map(|_| draw.below(n)).find(|&s| !c.outside[s]),
                salt: lay.salt ^ u64::from(c.label),
            };
            let own = self.synthesise_part(&lay, win, part, &mut img);
            for (l, s) in own.into_iter().enumerate() {
                if todo[l] {
                    src_of[l] = s;
                }
            }
        }
        (img, src_of)
    }

    /// The far side's depth limit of each pixel to complete in window `win` (0 elsewhere), one
    /// per [`TEXTURE_BLOCK`] block of the frame (it varies slowly), at the block's centre; none
    /// for what enters the frame.
    fn depth_limits(&self, todo: &[bool], win: Rect) -> Vec<f32> {
        let g = self.grid;
        let local = Grid::new(win.width(), win.height());
        let (bx0, by0) = (win.x0 / TEXTURE_BLOCK, win.y0 / TEXTURE_BLOCK);
        let blocks_grid = Grid::new((win.x1 - 1) / TEXTURE_BLOCK - bx0 + 1, (win.y1 - 1) / TEXTURE_BLOCK - by0 + 1);
        let mut blocks = vec![f32::NAN; blocks_grid.len()];
        let mut buf = Vec::new();
        let mut nearest = vec![0.0f32; todo.len()];
        for (l, &to_do) in todo.iter().enumerate() {
            let (lx, ly) = local.xy(l);
            let (x, y) = (win.x0 + lx, win.y0 + ly);
            if !to_do || self.entering[g.index(x, y)] {
                continue;
            }
            let (bx, by) = (x / TEXTURE_BLOCK, y / TEXTURE_BLOCK);
            let b = &mut blocks[blocks_grid.index(bx - bx0, by - by0)];
            if b.is_nan() {
                let cx = (bx * TEXTURE_BLOCK + TEXTURE_BLOCK / 2).min(g.w - 1);
                let cy = (by * TEXTURE_BLOCK + TEXTURE_BLOCK / 2).min(g.h - 1);
                *b = nearest_source_depth(self.tex, self.hole, g, cx, cy, &mut buf);
            }
            nearest[l] = *b;
        }
        nearest
    }

    /// Completes `part.todo` in `img` (window `win` of the frame) in onion-peel order, each pixel
    /// from image1 ([`synthesise`]): the candidates are the neighbours' sources shifted, the
    /// pixel's own place in image1 and [`TEXTURE_GLOBAL_DRAWS`] random ones; what is matched is
    /// the frame's pixels of `part.label` (not the holes of the neighbouring tiles, not what
    /// stands in front of the hole).
    fn synthesise_part<E, D>(&self, lay: &Layout, win: Rect, part: Part<'_, E, D>, img: &mut [u8]) -> Vec<u32>
    where
        E: Fn(usize, usize) -> bool,
        D: Fn(&mut Draw) -> Option<usize>,
    {
        let g = self.grid;
        let (hole, mask) = (self.hole, self.tex.mask);
        let order = peel_order(part.todo, win.width(), win.height());
        let mut filled: Vec<bool> = (win.y0..win.y1)
            .flat_map(|y| g.span(y, win.x0..win.x1).map(|p| hole[p] == 0 && mask[p] == part.label))
            .collect();
        let draw_one = &part.draw;
        let mut src = Sources {
            rgb: self.tex.image1,
            masked: part.masked,
            eligible: part.eligible,
            seeds: |t: usize, draw: &mut Draw, out: &mut Vec<usize>| {
                // the pixel's own place in image1
                out.push(lay.place(t));
                for _ in 0..TEXTURE_GLOBAL_DRAWS {
                    out.extend(draw_one(draw));
                }
            },
            fallback: |_: usize| None,
        };
        synthesise(&Layout { salt: part.salt, ..*lay }, &mut src, img, &mut filled, &order)
    }
}

/// Fills the pixels where `hole` is non-zero in the u8 RGB image (`w` x `h` x 3) with `method`
/// (a Telea variant; [`InpaintMethod::Exemplar`] needs the photo, which [`fill_holes`] takes:
/// here it is Telea, known-only).
///
/// With `windowed` (what the recipe uses) the Telea variants of the paper (`telea`,
/// `telea-known-only`, `telea-zero-order`) run on crops instead of the whole frame: the holes'
/// connected components, grouped where their bounding boxes grown by a margin overlap, each on
/// its box grown by the margin, the groups in parallel. The margin (`ceil(1.5 ceil(r) + 2) + 2`
/// pixels for radius `r`) holds everything the method reads for a hole pixel: the known pixels
/// within the radius, their one-pixel gradient stencils, and the outward arrival times, which
/// the method computes only up to `1.5 ceil(r) + 2` from the hole. The result is therefore the
/// whole-frame result, bit for bit (tested), at a cost that follows the holes instead of the
/// frame (the method allocates and scans several full-frame arrays per call). The OpenCV variant
/// treats the image border specially and always runs on the whole frame.
pub fn inpaint_holes(
    image: &mut [u8],
    w: usize,
    h: usize,
    hole: &[u8],
    method: InpaintMethod,
    radius: f32,
    windowed: bool,
) {
    telea_holes(image, Grid::new(w, h), hole, None, method, radius, windowed);
}

/// [`inpaint_holes`] from the frame's background only: the pixels where `labels` (H x W, the
/// frame's object labels) shows an object are never read by the fill (the Telea variants of the
/// paper, [`TeleaOptions::excluded`]), so a moved object's colours do not spread into what it
/// uncovers; a hole enclosed by objects and the frame's border is filled from them. The OpenCV
/// variant reads every known pixel, as `cv2.inpaint` does.
#[allow(clippy::too_many_arguments)]
pub fn inpaint_background(
    image: &mut [u8],
    w: usize,
    h: usize,
    hole: &[u8],
    labels: &[u8],
    method: InpaintMethod,
    radius: f32,
    windowed: bool,
) {
    let objects = (labels.len() == w * h && labels.iter().any(|&l| l != 0)).then_some(labels);
    telea_holes(image, Grid::new(w, h), hole, objects, method, radius, windowed);
}

/// [`inpaint_holes`] and [`inpaint_background`] (`objects`: the labels whose pixels are no
/// context).
fn telea_holes(
    image: &mut [u8],
    g: Grid,
    hole: &[u8],
    objects: Option<&[u8]>,
    method: InpaintMethod,
    radius: f32,
    windowed: bool,
) {
    use rayon::prelude::*;
    let Grid { w, h } = g;
    let gradient = match method {
        InpaintMethod::Telea => GradientTerm::Propagated,
        InpaintMethod::TeleaKnownOnly => GradientTerm::KnownOnly,
        InpaintMethod::TeleaZeroOrder => GradientTerm::Off,
        // without a texture source ([`fill_holes`] has one): the Telea variant it falls back to
        InpaintMethod::Exemplar => GradientTerm::KnownOnly,
        InpaintMethod::TeleaOpencv => {
            let options = TeleaOptions { radius, variant: TeleaVariant::OpenCv, ..TeleaOptions::default() };
            inpaint(image, w, h, 3, hole, &options);
            return;
        }
    };
    let options = TeleaOptions { radius, gradient, ..TeleaOptions::default() };
    let telea = |img: &mut [u8], cw: usize, ch: usize, sub: &[u8], labels: Option<Vec<bool>>| {
        inpaint(img, cw, ch, 3, sub, &TeleaOptions { excluded: labels.as_deref(), ..options })
    };
    let excluded = |labels: &[u8]| labels.iter().map(|&l| l != 0).collect::<Vec<bool>>();
    if !windowed {
        telea(image, w, h, hole, objects.map(excluded));
        return;
    }
    let r = if radius >= 1.0 { radius.min(super::inpaint::MAX_RADIUS) } else { 1.0 };
    let margin = (1.5 * r.ceil() + 2.0).ceil() as usize + 2;
    let groups = hole_groups(hole, g, margin);
    let results: Vec<(Rect, Vec<u8>)> = groups
        .par_iter()
        .map(|win| {
            let (cw, ch) = (win.width(), win.height());
            let mut img = Vec::with_capacity(cw * ch * 3);
            let mut sub = Vec::with_capacity(cw * ch);
            let mut labels = Vec::with_capacity(if objects.is_some() { cw * ch } else { 0 });
            for y in win.y0..win.y1 {
                img.extend_from_slice(&image[interleaved(g.span(y, win.x0..win.x1), 3)]);
                sub.extend_from_slice(&hole[g.span(y, win.x0..win.x1)]);
                if let Some(o) = objects {
                    labels.extend_from_slice(&o[g.span(y, win.x0..win.x1)]);
                }
            }
            telea(&mut img, cw, ch, &sub, objects.map(|_| excluded(&labels)));
            (*win, img)
        })
        .collect();
    for (win, img) in results {
        let local = Grid::new(win.width(), win.height());
        for y in win.y0..win.y1 {
            for x in win.x0..win.x1 {
                let p = g.index(x, y);
                if hole[p] != 0 {
                    let o = local.index(x - win.x0, y - win.y0);
                    image[pixel_values(p, 3)].copy_from_slice(&img[pixel_values(o, 3)]);
                }
            }
        }
    }
}

/// Most separate crops [`inpaint_holes`] makes; beyond, one crop holds all holes.
const MAX_HOLE_GROUPS: usize = 256;

/// The crops of [`inpaint_holes`]: bounding boxes of the holes' 4-connected components, grown by
/// `margin` and clipped to the frame, merged until no two overlap.
fn hole_groups(hole: &[u8], g: Grid, margin: usize) -> Vec<Rect> {
    let Grid { w, h } = g;
    let mut seen = vec![false; g.len()];
    let mut rects: Vec<Rect> = Vec::new();
    let mut stack: Vec<usize> = Vec::new();
    let mut too_many = false;
    let mut all = Rect { x0: w, y0: h, x1: 0, y1: 0 };
    for start in 0..g.len() {
        if hole[start] == 0 || seen[start] {
            continue;
        }
        let (x, y) = g.xy(start);
        let mut r = Rect { x0: x, y0: y, x1: x + 1, y1: y + 1 };
        seen[start] = true;
        stack.push(start);
        while let Some(i) = stack.pop() {
            let (x, y) = g.xy(i);
            r = r.union(&Rect { x0: x, y0: y, x1: x + 1, y1: y + 1 });
            for j in g.neighbours4(i) {
                if hole[j] != 0 && !seen[j] {
                    seen[j] = true;
                    stack.push(j);
                }
            }
        }
        all = all.union(&r);
        if rects.len() < MAX_HOLE_GROUPS {
            rects.push(r.grow(margin, w, h));
        } else {
            too_many = true;
        }
    }
    if too_many {
        return vec![all.grow(margin, w, h)];
    }
    let overlap = |a: &Rect, b: &Rect| a.x0 < b.x1 && b.x0 < a.x1 && a.y0 < b.y1 && b.y0 < a.y1;
    loop {
        let mut merged = false;
        let mut i = 0;
        while i < rects.len() {
            let mut j = i + 1;
            while j < rects.len() {
                if overlap(&rects[i], &rects[j]) {
                    let b = rects.swap_remove(j);
                    rects[i] = rects[i].union(&b);
                    merged = true;
                } else {
                    j += 1;
                }
            }
            i += 1;
        }
        if !merged {
            break;
        }
    }
    rects
}
