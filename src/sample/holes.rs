//! Filling the holes of image2 (pixels no render covers) with Telea's method, on crops around
//! the holes whose result is the whole-frame result bit for bit.

use super::config::InpaintMethod;
use super::inpaint::{inpaint_telea_opencv_u8, inpaint_telea_u8_with, GradientTerm, TeleaOptions};
use crate::render::Rect;

/// Fills the pixels where `hole` is non-zero in the u8 RGB image (`w` x `h` x 3) with `method`.
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
    use rayon::prelude::*;
    let gradient = match method {
        InpaintMethod::Telea => GradientTerm::Propagated,
        InpaintMethod::TeleaKnownOnly => GradientTerm::KnownOnly,
        InpaintMethod::TeleaZeroOrder => GradientTerm::Off,
        InpaintMethod::TeleaOpencv => {
            inpaint_telea_opencv_u8(image, w, h, 3, hole, radius);
            return;
        }
    };
    let options = TeleaOptions { radius, gradient };
    if !windowed {
        inpaint_telea_u8_with(image, w, h, 3, hole, &options);
        return;
    }
    let r = if radius >= 1.0 { radius.min(super::inpaint::MAX_RADIUS) } else { 1.0 };
    let margin = (1.5 * r.ceil() + 2.0).ceil() as usize + 2;
    let groups = hole_groups(hole, w, h, margin);
    let results: Vec<(Rect, Vec<u8>)> = groups
        .par_iter()
        .map(|win| {
            let (cw, ch) = (win.width(), win.height());
            let mut img = Vec::with_capacity(cw * ch * 3);
            let mut sub = Vec::with_capacity(cw * ch);
            for y in win.y0..win.y1 {
                img.extend_from_slice(&image[3 * (y * w + win.x0)..3 * (y * w + win.x1)]);
                sub.extend_from_slice(&hole[y * w + win.x0..y * w + win.x1]);
            }
            inpaint_telea_u8_with(&mut img, cw, ch, 3, &sub, &options);
            (*win, img)
        })
        .collect();
    for (win, img) in results {
        let cw = win.width();
        for y in win.y0..win.y1 {
            for x in win.x0..win.x1 {
                if hole[y * w + x] != 0 {
                    let o = 3 * ((y - win.y0) * cw + (x - win.x0));
                    image[3 * (y * w + x)..3 * (y * w + x) + 3].copy_from_slice(&img[o..o + 3]);
                }
            }
        }
    }
}

/// Most separate crops [`inpaint_holes`] makes; beyond, one crop holds all holes.
const MAX_HOLE_GROUPS: usize = 256;

/// The crops of [`inpaint_holes`]: bounding boxes of the holes' 4-connected components, grown by
/// `margin` and clipped to the frame, merged until no two overlap.
fn hole_groups(hole: &[u8], w: usize, h: usize, margin: usize) -> Vec<Rect> {
    let mut seen = vec![false; w * h];
    let mut rects: Vec<Rect> = Vec::new();
    let mut stack: Vec<usize> = Vec::new();
    let mut too_many = false;
    let mut all = Rect { x0: w, y0: h, x1: 0, y1: 0 };
    for start in 0..w * h {
        if hole[start] == 0 || seen[start] {
            continue;
        }
        let mut r = Rect { x0: start % w, y0: start / w, x1: start % w + 1, y1: start / w + 1 };
        seen[start] = true;
        stack.push(start);
        while let Some(i) = stack.pop() {
            let (x, y) = (i % w, i / w);
            r = r.union(&Rect { x0: x, y0: y, x1: x + 1, y1: y + 1 });
            let mut visit = |j: usize| {
                if hole[j] != 0 && !seen[j] {
                    seen[j] = true;
                    stack.push(j);
                }
            };
            if x > 0 {
                visit(i - 1);
            }
            if x + 1 < w {
                visit(i + 1);
            }
            if y > 0 {
                visit(i - w);
            }
            if y + 1 < h {
                visit(i + w);
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
