//! The row bands of the per-pixel loops (each band's slices of the buffers, in parallel on the
//! current rayon pool) and the `valid` mask of a flow pass.

use super::types::RenderStats;
use super::window::Rect;

/// Rows rendered per parallel task.
pub(crate) const BAND_ROWS: usize = 16;

/// Splits the image rows into bands of [`BAND_ROWS`] and hands each band's slices of the
/// per-pixel buffers to `f`, in parallel. `bufs[k]` holds `stride[k]` values per pixel.
pub(crate) fn for_each_band<const B: usize, F>(
    width: usize,
    height: usize,
    bufs: [&mut [f32]; B],
    strides: [usize; B],
    f: F,
) -> RenderStats
where
    F: Fn(usize, usize, &mut [&mut [f32]; B]) -> RenderStats + Sync + Send,
{
    use rayon::prelude::*;
    let mut bands: Vec<(usize, usize, [&mut [f32]; B])> = Vec::new();
    let mut rest = bufs;
    let mut y0 = 0;
    while y0 < height {
        let rows = BAND_ROWS.min(height - y0);
        let mut heads: [&mut [f32]; B] = std::array::from_fn(|_| Default::default());
        for k in 0..B {
            let buf = std::mem::take(&mut rest[k]);
            let (a, b) = buf.split_at_mut(rows * width * strides[k]);
            heads[k] = a;
            rest[k] = b;
        }
        bands.push((y0, rows, heads));
        y0 += rows;
    }
    bands.par_iter_mut().with_max_len(1).map(|(y0, rows, slices)| f(*y0, *rows, slices)).reduce(
        RenderStats::default,
        |mut a, b| {
            a += b;
            a
        },
    )
}

/// `valid` = the point is (by rendered weight, mostly) in front of the target camera and its
/// flow target lies inside the image [0, W-1] x [0, H-1] (`w` x `h` is the frame; `flow` and
/// `front_fraction` cover the window `win`).
pub(crate) fn mark_valid(win: &Rect, w: usize, h: usize, flow: &[f32], front_fraction: &[f32]) -> Vec<u8> {
    use rayon::prelude::*;
    let ww = win.width();
    let mut valid = crate::buf::zeros::<u8>(ww * win.height());
    valid.par_chunks_mut(ww.max(1)).enumerate().for_each(|(ry, row)| {
        let y = win.y0 + ry;
        for (rx, v) in row.iter_mut().enumerate() {
            let (x, i) = (win.x0 + rx, ry * ww + rx);
            let tx = x as f32 + flow[2 * i];
            let ty = y as f32 + flow[2 * i + 1];
            let inside = tx >= 0.0 && tx <= (w - 1) as f32 && ty >= 0.0 && ty <= (h - 1) as f32;
            *v = (inside && front_fraction[i] >= 0.5) as u8;
        }
    });
    valid
}
