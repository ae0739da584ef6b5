//! Binary morphology on row-major `H x W` masks: the one dilation every stage uses (holes'
//! rings in inpainting, grown object masks and depth-edge bands in the completed background,
//! mask bands in the matte alignment).

use super::grid::Grid;

/// Pixels within Chebyshev distance `r` of a set pixel (a `(2r+1)^2` rectangle dilation).
pub fn dilate(w: usize, h: usize, set: &[bool], r: usize) -> Vec<bool> {
    let g = Grid::new(w, h);
    let mut horiz = vec![false; w * h];
    let mut prefix = vec![0u32; w.max(h) + 1];
    for y in 0..h {
        for x in 0..w {
            prefix[x + 1] = prefix[x] + u32::from(set[g.index(x, y)]);
        }
        for x in 0..w {
            horiz[g.index(x, y)] = prefix[(x + r + 1).min(w)] > prefix[x.saturating_sub(r)];
        }
    }
    let mut out = vec![false; w * h];
    for x in 0..w {
        for y in 0..h {
            prefix[y + 1] = prefix[y] + u32::from(horiz[g.index(x, y)]);
        }
        for y in 0..h {
            out[g.index(x, y)] = prefix[(y + r + 1).min(h)] > prefix[y.saturating_sub(r)];
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dilation_is_the_chebyshev_ball() {
        let g = Grid::new(7, 5);
        let mut set = vec![false; g.len()];
        set[g.index(3, 2)] = true;
        let d = dilate(g.w, g.h, &set, 1);
        for (x, y) in g.pixels() {
            assert_eq!(d[g.index(x, y)], x.abs_diff(3) <= 1 && y.abs_diff(2) <= 1, "({x}, {y})");
        }
        assert_eq!(dilate(g.w, g.h, &set, 0), set);
    }
}
