//! Volume rendering of an MPI under a camera motion: the target-view image, depth, coverage and
//! extra channels, the source-view forward flow, and the `valid` and `occlusion` masks.
//!
//! Two modes share the output type:
//! - [`Mode::Reference`] reproduces the public MPI-Flow implementation formula for formula
//!   (border-clamped sampling, `+1e-6` in the transmittance, flow clipped to ±200, depth
//!   normalised by `sum w + 1e-5`); see `tests/render/reference_vectors.rs`.
//! - [`Mode::Exact`] ray-casts every target pixel against the planes analytically (no clamping:
//!   a ray that leaves the source frustum sees nothing, which shows up as coverage < 1), drops
//!   the `+1e-6`, composites planes in the order the target ray meets them, normalises flow and
//!   depth by the rendered weight, and supports work skipping (empty planes over a tile, early
//!   ray termination).
//!
//! Geometry is set up in f64; the per-pixel loops run in the generic [`Real`] type (f32 in
//! production, f64 for references). Rows are distributed over the current rayon pool; each pixel
//! is computed independently, so the parallel output is bit-identical to a serial one.
//!
//! # One renderer, any window
//!
//! [`render_window`] is the renderer; [`render`] is its full-frame case. In exact mode it renders
//! any window ([`Rect`]) of the frame into window-sized buffers, with the extra channels taken
//! per plane from the MPI ([`Channels::PerPlane`]) or from one H x W mask broadcast on every
//! plane ([`Channels::Broadcast`], which equals an MPI copy holding that mask on every plane,
//! without the copy), and optionally computes the source view only where a mask is positive
//! (`flow_where`). Every value equals the full-frame render's at the same pixel, bit for bit
//! (`tests/render/render_window.rs`). Occlusion needs the whole target frame, so it is computed only
//! when the window is the full frame. The reference mode renders full frames with per-plane
//! channels only. Every output, full frame or window, passes the non-finite guard (a NaN or Inf
//! is replaced by 0 and counted in [`RenderStats::repaired`]).
//!
//! # Links: the target view followed into other views
//!
//! With [`RenderParams::links`] the exact target pass also follows every target pixel into up to
//! two other cameras ([`View`]): each plane sample's point is projected into the view and the
//! displacements are composited with the target weights ([`Link`]). Into [`View::Source`] this
//! is the backward flow (target -> source on the target grid, the inverse displacement of
//! each plane); into a pose it is the flow between two novel views (the frames of a clip). The
//! loop is specialised by the number of links outside the pixel loop, so a render without links
//! does none of that work and gives the same bytes as before links existed. With a link into
//! the source view, the source pass also gives the source camera's own rendered depth
//! ([`RenderOutput::source_depth`], for the backward occlusion test).
//!
//! The plane spacing rule (`DELTA_LAST`, `DEPTH_MAX`, the gaps) belongs to
//! [`crate::mpi::planes`].
//!
//! # The rooms
//!
//! This file is the front door: [`render`], [`render_window`] and the occlusion mask, and the
//! names of the public API. The shared types live in the leaf `types.rs`; the modules below
//! it name only modules under them (`tests/server/layers.rs` holds the order):
//! `types`, `simd` (four-lane arithmetic) < `real` (the scalar type) < `tap` (bilinear taps),
//! `window` ([`Rect`]) < `band` (row bands, `valid`), `guard` (input checks, the non-finite
//! guard), `resample` (colour kernels), `store` (packed planes) < `mip` (minification levels),
//! `occupancy` (tile occupancy) < `reference`, `exact` (the two modes' loops; `exact/row16.rs`
//! the target view's sixteen-lane loop on AVX-512) < `cut` (the density cut).

mod band;
pub mod cut;
mod exact;
mod guard;
pub mod mip;
mod occupancy;
mod real;
mod reference;
pub mod resample;
mod simd;
pub mod store;
mod tap;
mod types;
mod window;

use crate::mpi::Mpi;
pub use occupancy::Occupancy;
pub use real::Real;
pub use types::{
    Channels, DensityCut, Fields, Link, Mode, Prefilter, RenderError, RenderOutput, RenderParams, RenderStats,
    Resample, Skip, View,
};
pub use window::{Rect, WindowRender};

/// Renders the whole frame of `mpi` with scalar type `T` (f32 in production), the MPI's own
/// extra channels: [`render_window`] over the full frame.
pub fn render<T: Real>(
    mpi: &Mpi,
    params: &RenderParams,
    occupancy: Option<&Occupancy>,
) -> Result<RenderOutput, RenderError> {
    let full = Rect::full(mpi.width, mpi.height);
    render_window::<T>(mpi, params, occupancy, &full, Channels::PerPlane, None).map(|r| r.out)
}

/// Renders the pixels of `window` (target view and source view alike) with scalar type `T`.
///
/// - `channels`: the extra channels, per plane from the MPI or one broadcast mask (H x W).
/// - `flow_where` (H x W): compute the source view only at pixels where it is > 0; the others
///   keep flow 0, source depth 0 and `valid` 0.
/// - `occupancy`: the MPI's tile occupancy for tile skipping (built here when skipping is on and
///   none with `params.skip.tile_sigma_eps` is given).
///
/// The output buffers are window-sized ([`WindowRender`]); each value equals the full-frame
/// render's at the same pixel, bit for bit. The occlusion field needs the whole target frame:
/// it is computed only when `window` is the full frame (with `params.fields.occlusion`), and
/// stays empty otherwise. An empty window gives empty buffers. Errors: an invalid MPI,
/// intrinsics or pose; a window outside the frame; a mask of the wrong size; a partial window,
/// a broadcast channel or `flow_where` in [`Mode::Reference`] (which renders full frames only).
pub fn render_window<T: Real>(
    mpi: &Mpi,
    params: &RenderParams,
    occupancy: Option<&Occupancy>,
    window: &Rect,
    channels: Channels<'_>,
    flow_where: Option<&[f32]>,
) -> Result<WindowRender, RenderError> {
    guard::check_inputs(mpi, params)?;
    let (w, h) = (mpi.width, mpi.height);
    let bad = |m: String| Err(RenderError::Request(m));
    for (what, mask) in [("broadcast channel", broadcast(channels)), ("flow_where mask", flow_where)] {
        if let Some(m) = mask.filter(|m| m.len() != w * h) {
            return bad(format!("{what} has {} values, the MPI is {w} x {h}", m.len()));
        }
    }
    if params.mode == Mode::Reference
        && (!window.is_full(w, h) || broadcast(channels).is_some() || flow_where.is_some())
    {
        return bad("the reference mode renders full frames with the MPI's own channels only".into());
    }
    let links = params.links;
    if links.iter().flatten().any(|v| matches!(v, View::Pose(p) if !p.is_finite())) {
        return Err(RenderError::Pose);
    }
    if params.mode == Mode::Reference && links.iter().any(Option::is_some) {
        return bad("links (backward flow, clip flows) need the exact mode".into());
    }
    let mut fields = params.fields;
    if fields.occlusion {
        fields.target = true;
        fields.flow = true;
    }
    let (ww, wh) = (window.width(), window.height());
    let c = if broadcast(channels).is_some() { 1 } else { mpi.extra_channels };
    let mut out = RenderOutput { width: ww, height: wh, extra_channels: c, ..Default::default() };
    if window.is_empty() {
        return Ok(WindowRender { win: *window, out });
    }
    if window.x1 > w || window.y1 > h {
        return bad(format!("window {window:?} is not inside the {w} x {h} frame"));
    }
    // the reference mode reads dense planes (a packed MPI's blocks spread out: the same bits)
    let unpacked = (params.mode == Mode::Reference).then(|| mpi.unpacked());
    let mpi = unpacked.as_deref().unwrap_or(mpi);
    let mut built = None;
    let occ = occupancy::tile_occupancy(mpi, params, occupancy, &mut built);
    if fields.target {
        out.image = crate::buf::zeros(ww * wh * 3);
        out.depth = crate::buf::zeros(ww * wh);
        out.coverage = crate::buf::zeros(ww * wh);
        out.extras = crate::buf::zeros(ww * wh * c);
        for (link, view) in out.links.iter_mut().zip(&links) {
            if view.is_some() {
                link.flow = crate::buf::zeros(ww * wh * 2);
                link.depth = crate::buf::zeros(ww * wh);
            }
        }
        let stats = match params.mode {
            Mode::Reference => reference::target_view::<T>(mpi, params, &mut out),
            Mode::Exact => exact::target_view::<T>(mpi, params, occ, window, channels, &mut out),
        };
        out.stats += stats;
    }
    if fields.flow {
        out.flow = crate::buf::zeros(ww * wh * 2);
        out.source_depth_in_target = crate::buf::zeros(ww * wh);
        out.valid = crate::buf::zeros(ww * wh);
        if links.contains(&Some(View::Source)) {
            out.source_depth = crate::buf::zeros(ww * wh);
        }
        match params.mode {
            Mode::Reference => reference::source_view::<T>(mpi, params, &mut out),
            Mode::Exact => exact::source_view::<T>(mpi, params, occ, window, flow_where, &mut out),
        }
    }
    if fields.occlusion && window.is_full(w, h) {
        out.occlusion = occlusion_mask(&out);
    }
    out.stats.repaired += guard::repair_nonfinite(&mut out);
    Ok(WindowRender { win: *window, out })
}

fn broadcast(channels: Channels<'_>) -> Option<&[f32]> {
    match channels {
        Channels::PerPlane => None,
        Channels::Broadcast(m) | Channels::BroadcastWithin(m, _) => Some(m),
    }
}

/// Relative depth margin of the occlusion test.
pub const OCCLUSION_TOLERANCE: f32 = 0.02;

/// A source point is occluded when the target view renders something clearly nearer at the
/// place the point moves to: its expected target depth exceeds the rendered target depth at all
/// four bilinear neighbours of p + flow by more than [`OCCLUSION_TOLERANCE`]. Points that leave
/// the image, or land on holes (coverage < 0.5), are not called occluded (`valid` covers them).
fn occlusion_mask(out: &RenderOutput) -> Vec<u8> {
    let (w, h) = (out.width, out.height);
    use rayon::prelude::*;
    let mut occ = crate::buf::zeros::<u8>(w * h);
    occ.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (x, o) in row.iter_mut().enumerate() {
            let i = y * w + x;
            if out.valid[i] == 0 {
                continue;
            }
            let tx = (x as f32 + out.flow[2 * i]).clamp(0.0, (w - 1) as f32);
            let ty = (y as f32 + out.flow[2 * i + 1]).clamp(0.0, (h - 1) as f32);
            let (x0, y0) = (tx.floor() as usize, ty.floor() as usize);
            let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
            let z = out.source_depth_in_target[i];
            let mut hidden = true;
            for &(nx, ny) in &[(x0, y0), (x1, y0), (x0, y1), (x1, y1)] {
                let j = ny * w + nx;
                if out.coverage[j] < 0.5 || z <= out.depth[j] * (1.0 + OCCLUSION_TOLERANCE) {
                    hidden = false;
                    break;
                }
            }
            *o = hidden as u8;
        }
    });
    occ
}
