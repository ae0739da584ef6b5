//! Render windows: the pixel rectangle [`Rect`] a render covers, and [`WindowRender`], a render
//! whose per-pixel buffers cover only that rectangle of the frame.
//!
//! Invariants: a `Rect` is half-open, `[x0, x1) x [y0, y1)`; one with `x1 <= x0` or `y1 <= y0`
//! is empty (its width or height is 0). A `WindowRender`'s buffers are `win.width()` x
//! `win.height()` (times the channels of each field), row-major, and pixel `(x, y)` of them is
//! frame pixel `(win.x0 + x, win.y0 + y)`, in the target view as in the source view.

use super::types::RenderOutput;

/// A pixel rectangle `[x0, x1) x [y0, y1)`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Rect {
    pub x0: usize,
    pub y0: usize,
    pub x1: usize,
    pub y1: usize,
}

impl Rect {
    pub fn full(width: usize, height: usize) -> Self {
        Rect { x0: 0, y0: 0, x1: width, y1: height }
    }

    pub fn width(&self) -> usize {
        self.x1.saturating_sub(self.x0)
    }

    pub fn height(&self) -> usize {
        self.y1.saturating_sub(self.y0)
    }

    pub fn area(&self) -> usize {
        self.width() * self.height()
    }

    pub fn is_empty(&self) -> bool {
        self.area() == 0
    }

    pub fn contains(&self, x: usize, y: usize) -> bool {
        x >= self.x0 && x < self.x1 && y >= self.y0 && y < self.y1
    }

    /// Whether this is the whole `width` x `height` frame.
    pub fn is_full(&self, width: usize, height: usize) -> bool {
        *self == Rect::full(width, height)
    }

    /// The smallest rectangle holding both (an empty one is ignored).
    pub fn union(&self, o: &Rect) -> Rect {
        if self.is_empty() {
            return *o;
        }
        if o.is_empty() {
            return *self;
        }
        Rect { x0: self.x0.min(o.x0), y0: self.y0.min(o.y0), x1: self.x1.max(o.x1), y1: self.y1.max(o.y1) }
    }

    /// The pixels in both (empty when they do not meet).
    pub fn intersect(&self, o: &Rect) -> Rect {
        let r = Rect { x0: self.x0.max(o.x0), y0: self.y0.max(o.y0), x1: self.x1.min(o.x1), y1: self.y1.min(o.y1) };
        if r.is_empty() {
            Rect { x0: r.x0, y0: r.y0, x1: r.x0, y1: r.y0 }
        } else {
            r
        }
    }

    /// This rectangle in the coordinates of `origin`'s corner (`self` lies inside `origin`).
    pub fn local_to(&self, origin: &Rect) -> Rect {
        Rect { x0: self.x0 - origin.x0, y0: self.y0 - origin.y0, x1: self.x1 - origin.x0, y1: self.y1 - origin.y0 }
    }

    /// Grown by `m` pixels on every side, clipped to `width` x `height`.
    pub fn grow(&self, m: usize, width: usize, height: usize) -> Rect {
        if self.is_empty() {
            return *self;
        }
        Rect {
            x0: self.x0.saturating_sub(m),
            y0: self.y0.saturating_sub(m),
            x1: (self.x1 + m).min(width),
            y1: (self.y1 + m).min(height),
        }
    }

    /// The pixels of the continuous box `[x0, x1] x [y0, y1]` (rounded outwards), clipped to the
    /// image; `None` for non-finite input.
    pub(crate) fn from_box(b: [f64; 4], width: usize, height: usize) -> Option<Rect> {
        if !b.iter().all(|v| v.is_finite()) {
            return None;
        }
        let (wf, hf) = (width as f64, height as f64);
        let x0 = b[0].floor().clamp(0.0, wf) as usize;
        let y0 = b[1].floor().clamp(0.0, hf) as usize;
        let x1 = (b[2].ceil() + 1.0).clamp(0.0, wf) as usize;
        let y1 = (b[3].ceil() + 1.0).clamp(0.0, hf) as usize;
        if x1 <= x0 || y1 <= y0 {
            return Some(Rect { x0: 0, y0: 0, x1: 0, y1: 0 });
        }
        Some(Rect { x0, y0, x1, y1 })
    }

    /// The centres of the four corner pixels (non-empty rectangles only).
    pub(crate) fn corners(&self) -> [(f64, f64); 4] {
        let (x0, y0) = (self.x0 as f64, self.y0 as f64);
        let (x1, y1) = ((self.x1 - 1) as f64, (self.y1 - 1) as f64);
        [(x0, y0), (x1, y0), (x0, y1), (x1, y1)]
    }
}

/// A render over a window of the frame (see the module documentation): `out.width` x
/// `out.height` = `win.width()` x `win.height()`.
#[derive(Clone, Debug)]
pub struct WindowRender {
    pub win: Rect,
    pub out: RenderOutput,
}

impl WindowRender {
    /// Index into the window's per-pixel buffers of frame pixel (x, y), if inside.
    #[inline]
    pub fn index(&self, x: usize, y: usize) -> Option<usize> {
        self.win.contains(x, y).then(|| (y - self.win.y0) * self.win.width() + (x - self.win.x0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn rect() -> impl Strategy<Value = Rect> {
        (0usize..40, 0usize..40, 0usize..40, 0usize..40).prop_map(|(x0, y0, x1, y1)| Rect { x0, y0, x1, y1 })
    }

    proptest! {
        /// A pixel is in the intersection exactly when it is in both; the intersection is the
        /// same either way round, and a rectangle in the coordinates of one holding it keeps its
        /// size and its pixels, shifted by the corner.
        #[test]
        fn the_intersection_holds_the_pixels_of_both(a in rect(), b in rect(), x in 0usize..40, y in 0usize..40) {
            let i = a.intersect(&b);
            prop_assert_eq!(i.contains(x, y), a.contains(x, y) && b.contains(x, y));
            prop_assert_eq!(i.area(), b.intersect(&a).area());
            if !i.is_empty() {
                let l = i.local_to(&a);
                prop_assert_eq!((l.width(), l.height()), (i.width(), i.height()));
                if i.contains(x, y) {
                    prop_assert!(l.contains(x - a.x0, y - a.y0));
                }
            }
        }
    }
}
