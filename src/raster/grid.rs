//! The dimensions of a row-major raster ([`Grid`]): a pixel's index and coordinates, its
//! neighbours and clipped windows within bounds, and the spans of rows, so that callers say
//! `grid.index(x, y)` instead of writing the arithmetic.

use std::ops::Range;

/// A `w x h` raster stored row-major: pixel `(x, y)` (x = column, y = row) at index
/// `y * w + x`. Small and `Copy`: pass it by value beside the buffers it describes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Grid {
    pub w: usize,
    pub h: usize,
}

/// A clipped rectangle of pixels: the columns `xs` of the rows `ys`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Window {
    pub xs: Range<usize>,
    pub ys: Range<usize>,
}

impl Window {
    /// Its pixels `(x, y)`, row by row.
    pub fn pixels(self) -> impl Iterator<Item = (usize, usize)> {
        let xs = self.xs;
        self.ys.flat_map(move |y| xs.clone().map(move |x| (x, y)))
    }
}

impl Grid {
    pub const fn new(w: usize, h: usize) -> Self {
        Self { w, h }
    }

    /// The number of pixels.
    pub const fn len(self) -> usize {
        self.w * self.h
    }

    pub const fn is_empty(self) -> bool {
        self.len() == 0
    }

    /// The index of pixel `(x, y)` (inside the grid).
    #[inline(always)]
    pub fn index(self, x: usize, y: usize) -> usize {
        debug_assert!(x < self.w && y < self.h, "({x}, {y}) outside {} x {}", self.w, self.h);
        y * self.w + x
    }

    /// The coordinates `(x, y)` of pixel index `i`.
    #[inline(always)]
    pub fn xy(self, i: usize) -> (usize, usize) {
        (i % self.w, i / self.w)
    }

    /// Whether `(x, y)` lies inside the grid.
    #[inline(always)]
    pub fn contains(self, x: isize, y: isize) -> bool {
        x >= 0 && y >= 0 && (x as usize) < self.w && (y as usize) < self.h
    }

    /// The index of `(x, y)` where it lies inside the grid.
    #[inline(always)]
    pub fn at(self, x: isize, y: isize) -> Option<usize> {
        self.contains(x, y).then(|| self.index(x as usize, y as usize))
    }

    /// The indices of the pixels `xs` of row `y`.
    #[inline(always)]
    pub fn span(self, y: usize, xs: Range<usize>) -> Range<usize> {
        debug_assert!(xs.start <= xs.end && xs.end <= self.w && y < self.h);
        y * self.w + xs.start..y * self.w + xs.end
    }

    /// The indices of row `y`.
    #[inline(always)]
    pub fn row(self, y: usize) -> Range<usize> {
        self.span(y, 0..self.w)
    }

    /// Every pixel `(x, y)`, row by row (index order).
    pub fn pixels(self) -> impl Iterator<Item = (usize, usize)> {
        (0..self.h).flat_map(move |y| (0..self.w).map(move |x| (x, y)))
    }

    /// The 4-neighbours of pixel index `i` inside the grid, in the order left, right, up, down.
    #[inline(always)]
    pub fn neighbours4(self, i: usize) -> impl Iterator<Item = usize> {
        let (x, y) = self.xy(i);
        let w = self.w;
        [(x > 0).then(|| i - 1), (x + 1 < w).then(|| i + 1), (y > 0).then(|| i - w), (y + 1 < self.h).then(|| i + w)]
            .into_iter()
            .flatten()
    }

    /// The 8-neighbours `(x, y)` of `(x, y)` inside the grid, row by row.
    pub fn neighbours8(self, x: usize, y: usize) -> impl Iterator<Item = (usize, usize)> {
        self.window(x, y, 1).pixels().filter(move |&p| p != (x, y))
    }

    /// The square of pixels within Chebyshev distance `r` of `(x, y)`, clipped to the grid.
    pub fn window(self, x: usize, y: usize, r: usize) -> Window {
        Window { xs: x.saturating_sub(r)..(x + r + 1).min(self.w), ys: y.saturating_sub(r)..(y + r + 1).min(self.h) }
    }

    /// The indices of the pixels on the grid's border: the top and bottom row column by column,
    /// then the left and right column row by row (corners appear twice).
    pub fn border(self) -> impl Iterator<Item = usize> {
        let Grid { w, h } = self;
        (0..w).flat_map(move |x| [x, (h - 1) * w + x]).chain((0..h).flat_map(move |y| [y * w, y * w + w - 1]))
    }
}

/// The values of the pixels `pixels` in a buffer of `channels` interleaved channels per pixel.
#[inline(always)]
pub fn interleaved(pixels: Range<usize>, channels: usize) -> Range<usize> {
    channels * pixels.start..channels * pixels.end
}

/// The values of pixel index `p` in a buffer of `channels` interleaved channels per pixel.
#[inline(always)]
pub fn pixel_values(p: usize, channels: usize) -> Range<usize> {
    channels * p..channels * p + channels
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn grid() -> impl Strategy<Value = Grid> {
        (1usize..40, 1usize..40).prop_map(|(w, h)| Grid::new(w, h))
    }

    proptest! {
        #[test]
        fn index_and_xy_are_inverse(g in grid(), i in 0usize..1600) {
            let i = i % g.len();
            let (x, y) = g.xy(i);
            prop_assert!(x < g.w && y < g.h);
            prop_assert_eq!(g.index(x, y), i);
            prop_assert_eq!(g.at(x as isize, y as isize), Some(i));
        }

        #[test]
        fn pixels_are_in_index_order(g in grid()) {
            let idx: Vec<usize> = g.pixels().map(|(x, y)| g.index(x, y)).collect();
            prop_assert_eq!(idx, (0..g.len()).collect::<Vec<_>>());
            let rows: Vec<usize> = (0..g.h).flat_map(|y| g.row(y)).collect();
            prop_assert_eq!(rows, (0..g.len()).collect::<Vec<_>>());
        }

        #[test]
        fn contains_is_the_bounds(g in grid(), x in -3isize..45, y in -3isize..45) {
            let inside = (0..g.w as isize).contains(&x) && (0..g.h as isize).contains(&y);
            prop_assert_eq!(g.contains(x, y), inside);
            prop_assert_eq!(g.at(x, y).is_some(), inside);
        }

        #[test]
        fn neighbours4_are_the_pixels_at_manhattan_distance_one(g in grid(), i in 0usize..1600) {
            let i = i % g.len();
            let (x, y) = g.xy(i);
            let got: Vec<usize> = g.neighbours4(i).collect();
            let want: Vec<usize> = [(-1isize, 0isize), (1, 0), (0, -1), (0, 1)]
                .iter()
                .filter_map(|&(dx, dy)| g.at(x as isize + dx, y as isize + dy))
                .collect();
            prop_assert_eq!(got, want);
        }

        #[test]
        fn neighbours8_and_windows_are_the_clipped_chebyshev_balls(
            g in grid(), i in 0usize..1600, r in 0usize..5,
        ) {
            let i = i % g.len();
            let (x, y) = g.xy(i);
            let ball = |r: usize| -> Vec<(usize, usize)> {
                g.pixels().filter(|&(a, b)| a.abs_diff(x) <= r && b.abs_diff(y) <= r).collect()
            };
            let win: Vec<(usize, usize)> = g.window(x, y, r).pixels().collect();
            prop_assert_eq!(win, ball(r));
            let n8: Vec<(usize, usize)> = g.neighbours8(x, y).collect();
            let want: Vec<(usize, usize)> = ball(1).into_iter().filter(|&p| p != (x, y)).collect();
            prop_assert_eq!(n8, want);
        }

        #[test]
        fn border_is_the_pixels_on_an_edge(g in grid()) {
            let mut got: Vec<usize> = g.border().collect();
            got.sort_unstable();
            got.dedup();
            let want: Vec<usize> = g
                .pixels()
                .filter(|&(x, y)| x == 0 || y == 0 || x + 1 == g.w || y + 1 == g.h)
                .map(|(x, y)| g.index(x, y))
                .collect();
            prop_assert_eq!(got, want);
        }

        #[test]
        fn spans_are_rows_of_indices(g in grid(), y in 0usize..40, a in 0usize..40, b in 0usize..40, c in 1usize..5) {
            let y = y % g.h;
            let (a, b) = (a % (g.w + 1), b % (g.w + 1));
            let xs = a.min(b)..a.max(b);
            let s = g.span(y, xs.clone());
            prop_assert_eq!(s.clone().collect::<Vec<_>>(), xs.clone().map(|x| g.index(x, y)).collect::<Vec<_>>());
            let v = interleaved(s.clone(), c);
            prop_assert_eq!(v.len(), c * xs.len());
            if let Some(first) = s.clone().next() {
                prop_assert_eq!(pixel_values(first, c).start, v.start);
                prop_assert_eq!(pixel_values(first, c).len(), c);
            }
        }
    }
}
