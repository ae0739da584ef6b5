//! Binary morphology on row-major `H x W` masks: the one dilation every stage uses (holes'
//! rings in inpainting, grown object masks and depth-edge bands in the completed background,
//! mask bands in the matte alignment).

/// Pixels within Chebyshev distance `r` of a set pixel (a `(2r+1)^2` rectangle dilation).
pub fn dilate(w: usize, h: usize, set: &[bool], r: usize) -> Vec<bool> {
    let mut horiz = vec![false; w * h];
    let mut prefix = vec![0u32; w.max(h) + 1];
    for y in 0..h {
        for x in 0..w {
            prefix[x + 1] = prefix[x] + u32::from(set[y * w + x]);
        }
        for x in 0..w {
            horiz[y * w + x] = prefix[(x + r + 1).min(w)] > prefix[x.saturating_sub(r)];
        }
    }
    let mut out = vec![false; w * h];
    for x in 0..w {
        for y in 0..h {
            prefix[y + 1] = prefix[y] + u32::from(horiz[y * w + x]);
        }
        for y in 0..h {
            out[y * w + x] = prefix[(y + r + 1).min(h)] > prefix[y.saturating_sub(r)];
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dilation_is_the_chebyshev_ball() {
        let (w, h) = (7, 5);
        let mut set = vec![false; w * h];
        set[2 * w + 3] = true;
        let d = dilate(w, h, &set, 1);
        for y in 0..h {
            for x in 0..w {
                assert_eq!(d[y * w + x], x.abs_diff(3) <= 1 && y.abs_diff(2) <= 1, "({x}, {y})");
            }
        }
        assert_eq!(dilate(w, h, &set, 0), set);
    }
}
