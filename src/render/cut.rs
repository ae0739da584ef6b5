//! Rendering an MPI with part of it taken out: a [`DensityCut`] removes the front planes of the
//! source pixels under a mask, so that the target view shows what the MPI holds *behind* them
//! (the background of a moved object's place: the built-in layering's hidden colours, an MPI
//! network's back planes). The render is the exact renderer's target pass, bilinear, with the
//! density of plane `i` at a tap scaled by `1 - c`, where `c` is the bilinear mean over the tap's
//! four pixels of `mask`, each pixel counted only on the planes it cuts (`i <= last`).

use super::exact;
use super::guard::{check_inputs, repair_nonfinite};
use super::occupancy::{tile_occupancy, Occupancy};
use super::real::Real;
use super::types::{DensityCut, Mode, RenderError, RenderOutput, RenderParams};
use super::window::{Rect, WindowRender};
use crate::mpi::Mpi;

/// The target view (image premultiplied by coverage, depth, coverage) of `window` of `mpi`
/// with `cut` applied, in exact mode with bilinear sampling whatever `params.resample` says;
/// no flow, links or extra channels (`extras` holds the rendered cut mask). Errors as
/// `render_window`, and for a cut of the wrong size, a reference-mode `params` or links.
pub fn render_cut<T: Real>(
    mpi: &Mpi,
    params: &RenderParams,
    occupancy: Option<&Occupancy>,
    window: &Rect,
    cut: &DensityCut<'_>,
) -> Result<WindowRender, RenderError> {
    check_inputs(mpi, params)?;
    let (w, h) = (mpi.width, mpi.height);
    let bad = |m: String| Err(RenderError::Request(m));
    if cut.mask.len() != w * h || cut.last.len() != w * h {
        return bad(format!(
            "the density cut has {} / {} values, the MPI is {w} x {h}",
            cut.mask.len(),
            cut.last.len()
        ));
    }
    if params.mode != Mode::Exact || params.links.iter().any(Option::is_some) {
        return bad("a density cut renders in exact mode without links".into());
    }
    let (ww, wh) = (window.width(), window.height());
    let mut out = RenderOutput { width: ww, height: wh, extra_channels: 1, ..Default::default() };
    if window.is_empty() {
        return Ok(WindowRender { win: *window, out });
    }
    if window.x1 > w || window.y1 > h {
        return bad(format!("window {window:?} is not inside the {w} x {h} frame"));
    }
    let mut built = None;
    let occ = tile_occupancy(mpi, params, occupancy, &mut built);
    out.image = crate::buf::zeros(ww * wh * 3);
    out.depth = crate::buf::zeros(ww * wh);
    out.coverage = crate::buf::zeros(ww * wh);
    out.extras = crate::buf::zeros(ww * wh);
    let stats = exact::target_view_cut::<T>(mpi, params, occ, window, cut, &mut out);
    out.stats += stats;
    out.stats.repaired += repair_nonfinite(&mut out);
    Ok(WindowRender { win: *window, out })
}
