//! Volume rendering of an MPI under a camera motion: the target-view image, depth, coverage and
//! extra channels, the source-view forward flow, and the `valid` and `occlusion` masks.
//!
//! Two modes share the output type:
//! - [`Mode::Reference`] reproduces the public MPI-Flow implementation formula for formula
//!   (border-clamped sampling, `+1e-6` in the transmittance, flow clipped to ±200, depth
//!   normalised by `sum w + 1e-5`); see `tests/reference_vectors.rs`.
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
//! (`tests/render_window.rs`). Occlusion needs the whole target frame, so it is computed only
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
//! The plane spacing rule ([`DELTA_LAST`], [`DEPTH_MAX`], the gaps) belongs to
//! [`crate::mpi::planes`] and is re-exported here.

pub mod cut;
mod exact;
pub mod mip;
pub mod occupancy;
pub mod real;
mod reference;
pub mod resample;
mod simd;
pub mod store;
pub mod window;

use crate::geometry::{Intrinsics, Pose};
pub use crate::mpi::planes::{DELTA_LAST, DEPTH_MAX};
use crate::mpi::Mpi;
pub use occupancy::Occupancy;
pub use real::Real;
pub use resample::Resample;
pub use window::{Rect, WindowRender};
/// Rows rendered per parallel task.
pub const BAND_ROWS: usize = 16;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Mode {
    /// Formula-for-formula the public reference implementation.
    Reference,
    /// Analytic ray casting with coverage, validity and optional work skipping (default).
    #[default]
    Exact,
}

impl std::str::FromStr for Mode {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "reference" => Ok(Mode::Reference),
            "exact" => Ok(Mode::Exact),
            _ => Err(format!("unknown mode `{s}` (expected reference or exact)")),
        }
    }
}

/// Which passes to run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Fields {
    /// Target view: image, depth, coverage, extra channels.
    pub target: bool,
    /// Source view: forward flow and `valid`.
    pub flow: bool,
    /// Occlusion mask (needs both passes; forces them on).
    pub occlusion: bool,
}

impl Default for Fields {
    fn default() -> Self {
        Self { target: true, flow: true, occlusion: true }
    }
}

/// Optional work skipping (exact mode only; the reference mode never skips).
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct Skip {
    /// Stop compositing a ray once its transmittance falls below this (0 = never).
    pub transmittance_eps: f32,
    /// Skip planes that are empty (all sigma <= `tile_sigma_eps`) over a target tile's footprint.
    pub tiles: bool,
    /// Densities at or below this count as empty for tile skipping (0 = exact skipping only).
    pub tile_sigma_eps: f32,
}

impl Skip {
    pub const NONE: Skip = Skip { transmittance_eps: 0.0, tiles: false, tile_sigma_eps: 0.0 };
    /// Exact skipping only: empty tiles and rays whose transmittance is below 1e-4.
    pub const DEFAULT: Skip = Skip { transmittance_eps: 1e-4, tiles: true, tile_sigma_eps: 0.0 };
}

#[derive(Clone, Copy, Debug)]
pub struct RenderParams {
    pub k_src: Intrinsics,
    pub k_tgt: Intrinsics,
    pub pose: Pose,
    pub mode: Mode,
    pub fields: Fields,
    pub skip: Skip,
    /// Views the target view's pixels are followed into ([`Link`]s, exact mode, with the target
    /// pass): [`View::Source`] gives the backward flow. None = no link work at all.
    pub links: [Option<View>; 2],
    /// The colour kernel of the exact-mode target view ([`resample`]); the reference mode is
    /// always bilinear.
    pub resample: Resample,
    /// Alias-free minification of the exact-mode target view's colour: planes that the view
    /// shrinks are sampled from prefiltered levels ([`mip`]). Off = the colour kernel alone.
    pub minify: bool,
}

impl RenderParams {
    /// Exact mode, all fields, default skipping, bilinear colour.
    pub fn new(k: Intrinsics, pose: Pose) -> Self {
        Self {
            k_src: k,
            k_tgt: k,
            pose,
            mode: Mode::Exact,
            fields: Fields::default(),
            skip: Skip::DEFAULT,
            links: [None, None],
            resample: Resample::Bilinear,
            minify: false,
        }
    }
}

/// A camera that the points seen in the target view are followed into (see [`Link`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum View {
    /// The source camera (intrinsics `k_src`): the link is the backward flow, target -> source.
    Source,
    /// A camera at this pose from the source camera (`X_view = R X_src + t`) with the target
    /// intrinsics `k_tgt`: e.g. the next or the previous frame of a clip.
    Pose(Pose),
}

/// A target-view correspondence into another [`View`], on the target grid (window-sized like
/// every target field). For each target pixel p and each plane i its ray meets (in the order
/// and with the weights w_i of the target view), the plane's point X_i (at source pixel q_i) is
/// projected into the view, pi_v(X_i); the link flow is sum_i w_i (pi_v(X_i) - p) / sum_i w_i
/// over the planes whose point is in front of the view's camera. Into [`View::Source`],
/// pi_v(X_i) = q_i exactly: the backward flow (each plane's inverse displacement composited
/// with the target weights).
#[derive(Clone, Debug, Default)]
pub struct Link {
    /// H x W x 2 (u, v) in pixels; 0 where nothing in front of the view is rendered.
    pub flow: Vec<f32>,
    /// The expected depth of the target pixel's point in the view's camera, H x W.
    pub depth: Vec<f32>,
    /// 1 where the target pixel is rendered (coverage >= 1/2), its point is (by weight, mostly)
    /// in front of the view's camera and lands inside the frame [0, W-1] x [0, H-1].
    pub valid: Vec<u8>,
}

#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    #[error("invalid MPI: {0}")]
    Mpi(#[from] crate::mpi::MpiError),
    #[error("invalid {which} intrinsics {k:?}: focal lengths must be finite and non-zero")]
    Intrinsics { which: &'static str, k: Intrinsics },
    #[error("invalid pose: rotation and translation must be finite")]
    Pose,
    #[error("invalid render request: {0}")]
    Request(String),
}

/// Where a render's extra channels come from.
#[derive(Clone, Copy, Debug, Default)]
pub enum Channels<'a> {
    /// The MPI's own extra channels (`mpi.extra_channels` of them, one set per plane).
    #[default]
    PerPlane,
    /// One channel: this H x W mask, the same on every plane (the MPI's own extras are ignored).
    Broadcast(&'a [f32]),
}

/// Counters describing the work done.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RenderStats {
    /// Plane samples evaluated in the target view.
    pub samples: u64,
    /// Plane samples avoided by tile skipping.
    pub skipped_tile: u64,
    /// Plane samples avoided by early ray termination.
    pub skipped_early: u64,
    /// Non-finite output values replaced by 0 (should stay 0; counted, never hidden).
    pub repaired: u64,
}

impl std::ops::AddAssign for RenderStats {
    fn add_assign(&mut self, o: Self) {
        self.samples += o.samples;
        self.skipped_tile += o.skipped_tile;
        self.skipped_early += o.skipped_early;
        self.repaired += o.repaired;
    }
}

/// What a render produces. The target-view fields live on the target grid, the flow fields on
/// the source grid; both are `width` x `height`: the MPI's size for [`render`], the window's for
/// [`render_window`]. Empty when not requested.
#[derive(Clone, Debug, Default)]
pub struct RenderOutput {
    pub width: usize,
    pub height: usize,
    /// Target image, H x W x 3, rgb = sum_i w_i rgb_i.
    pub image: Vec<f32>,
    /// Target depth (z in the target camera), H x W.
    pub depth: Vec<f32>,
    /// Target coverage sum_i w_i, H x W (1 = fully rendered, 0 = hole).
    pub coverage: Vec<f32>,
    /// Extra channels in the target view, H x W x C.
    pub extras: Vec<f32>,
    pub extra_channels: usize,
    /// Forward flow on source pixels, H x W x 2 (u, v).
    pub flow: Vec<f32>,
    /// Expected depth of each source pixel's point in the target camera, H x W.
    pub source_depth_in_target: Vec<f32>,
    /// 1 where the flow target lies inside the image and the point is in front of the camera.
    pub valid: Vec<u8>,
    /// 1 where the source point is hidden in the target view (full-frame renders only).
    pub occlusion: Vec<u8>,
    /// The target view's links into `RenderParams::links` (same slots; empty where None).
    pub links: [Link; 2],
    /// The source view's expected depth of each source pixel in the source camera, H x W (the
    /// depth image1 shows, for the backward occlusion test); only with the flow pass and a link
    /// into [`View::Source`].
    pub source_depth: Vec<f32>,
    pub stats: RenderStats,
}

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

/// The checks every render makes of its inputs: a valid MPI, valid intrinsics, a finite pose.
pub(crate) fn check_inputs(mpi: &Mpi, params: &RenderParams) -> Result<(), RenderError> {
    mpi.validate()?;
    if !params.k_src.is_valid() {
        return Err(RenderError::Intrinsics { which: "source", k: params.k_src });
    }
    if !params.k_tgt.is_valid() {
        return Err(RenderError::Intrinsics { which: "target", k: params.k_tgt });
    }
    if !params.pose.is_finite() {
        return Err(RenderError::Pose);
    }
    Ok(())
}

/// The tile occupancy an exact render with tile skipping uses: `given` when it was built with
/// the render's threshold, else one built into `built`; none in reference mode or without tiles.
pub(crate) fn tile_occupancy<'a>(
    mpi: &Mpi,
    params: &RenderParams,
    given: Option<&'a Occupancy>,
    built: &'a mut Option<Occupancy>,
) -> Option<&'a Occupancy> {
    if params.mode != Mode::Exact || !params.skip.tiles {
        return None;
    }
    match given {
        Some(o) if o.sigma_eps == params.skip.tile_sigma_eps => Some(o),
        _ => Some(built.insert(Occupancy::build(mpi, params.skip.tile_sigma_eps))),
    }
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
    check_inputs(mpi, params)?;
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
    let occ = tile_occupancy(mpi, params, occupancy, &mut built);
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
    out.stats.repaired += repair_nonfinite(&mut out);
    Ok(WindowRender { win: *window, out })
}

fn broadcast(channels: Channels<'_>) -> Option<&[f32]> {
    match channels {
        Channels::PerPlane => None,
        Channels::Broadcast(m) => Some(m),
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

/// The last line of defence of the numerics rule (docs/design.md §4): no NaN or Inf leaves the
/// renderer (full frame or window). Returns how many
/// values had to be replaced (0 in every tested case; the count is reported, not hidden).
fn repair_nonfinite(out: &mut RenderOutput) -> u64 {
    use rayon::prelude::*;
    let mut n = 0u64;
    for buf in [
        &mut out.image,
        &mut out.depth,
        &mut out.coverage,
        &mut out.extras,
        &mut out.flow,
        &mut out.source_depth_in_target,
        &mut out.source_depth,
    ]
    .into_iter()
    .chain(out.links.iter_mut().flat_map(|l| [&mut l.flow, &mut l.depth]))
    {
        n += buf
            .par_chunks_mut(1 << 16)
            .map(|chunk| {
                let mut k = 0u64;
                for v in chunk.iter_mut().filter(|v| !v.is_finite()) {
                    *v = 0.0;
                    k += 1;
                }
                k
            })
            .sum::<u64>();
    }
    n
}

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
    bands.par_iter_mut().map(|(y0, rows, slices)| f(*y0, *rows, slices)).reduce(RenderStats::default, |mut a, b| {
        a += b;
        a
    })
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

/// `(q as usize).min(n - 1)` for q >= 0 (truncation is floor there; NaN and negatives give 0,
/// as Rust's saturating `as` does), through `i32`: the same value for every q with n < 2^31, in
/// one x86-64 conversion where `f32 as usize` takes several (`resample::sample_rgb`: -2.3% of
/// the `bspline3` target pass's instructions; `Tap::new`'s scalar remainder gained nothing).
#[inline(always)]
pub(crate) fn floor_index(q: f32, n: usize) -> usize {
    ((q as i32).max(0) as usize).min(n - 1)
}

/// A bilinear tap at a point already clamped to [0, W-1] x [0, H-1].
#[derive(Clone, Copy, Debug)]
pub(crate) struct Tap<T> {
    /// the tap's pixel (the top-left of its four)
    pub(crate) x0: usize,
    pub(crate) y0: usize,
    /// the plane's width and height (the four pixels' indices are computed where a dense plane
    /// is read, [`Self::corners`]: a block store needs only the pixel)
    w: usize,
    h: usize,
    wx: T,
    wy: T,
}

impl<T: Real> Tap<T> {
    #[inline(always)]
    pub(crate) fn new(qx: T, qy: T, w: usize, h: usize) -> Self {
        // q >= 0 here, so truncation is floor (and avoids a libm call without SSE4.1)
        let x0 = (qx.f32() as usize).min(w - 1);
        let y0 = (qy.f32() as usize).min(h - 1);
        let (fx, fy) = (T::of(x0 as f64), T::of(y0 as f64));
        Self::from_parts(x0, y0, w, h, qx - fx, qy - fy)
    }

    /// The tap of [`Self::new`] from its parts: the pixel (x0, y0) (q truncated, at most the last
    /// pixel) and the fractions wx = qx - x0, wy = qy - y0 (the four-lane loop computes these in
    /// lanes with `new`'s operations).
    #[inline(always)]
    pub(crate) fn from_parts(x0: usize, y0: usize, w: usize, h: usize, wx: T, wy: T) -> Self {
        Self { x0, y0, w, h, wx, wy }
    }

    /// The indices in a dense plane of the tap's four pixels: (x0, y0), (x1, y0), (x0, y1),
    /// (x1, y1), with x1 = x0 + 1 and y1 = y0 + 1 clamped to the last column and row.
    #[inline(always)]
    fn corners(&self) -> [usize; 4] {
        let (w, x0, y0) = (self.w, self.x0, self.y0);
        let x1 = (x0 + 1).min(w - 1);
        let y1 = (y0 + 1).min(self.h - 1);
        [y0 * w + x0, y0 * w + x1, y1 * w + x0, y1 * w + x1]
    }

    /// [`Self::sample4`] of a block of 4-valued pixels ([`crate::mpi::bricks::Bricks`]) whose
    /// value at the tap's pixel starts at `s`, rows `row` values apart, the right and lower
    /// neighbours in the block's apron (the same arithmetic).
    #[inline(always)]
    pub(crate) fn sample4_at(&self, data: &[f32], s: usize, row: usize) -> [T; 4] {
        let d = &data[s..s + row + 8];
        T::lerp4(&d[..4], &d[4..8], &d[row..row + 4], &d[row + 4..], self.wx, self.wy)
    }

    /// Samples an interleaved 4-channel plane (per channel the arithmetic of [`Self::sample1`];
    /// `f32` takes the four channels at once, [`Real::lerp4`]).
    #[inline(always)]
    pub(crate) fn sample4(&self, plane: &[f32]) -> [T; 4] {
        let [i00, i10, i01, i11] = self.corners();
        let px = |i: usize| &plane[4 * i..4 * i + 4];
        T::lerp4(px(i00), px(i10), px(i01), px(i11), self.wx, self.wy)
    }

    /// Samples a single-channel plane (`sample_c` with `c = 1`, the same arithmetic).
    #[inline(always)]
    pub(crate) fn sample1(&self, plane: &[f32]) -> T {
        let [i00, i10, i01, i11] = self.corners();
        let at = |i: usize| T::of32(plane[i]);
        let top = at(i00) + self.wx * (at(i10) - at(i00));
        let bot = at(i01) + self.wx * (at(i11) - at(i01));
        top + self.wy * (bot - top)
    }

    /// Samples a single-channel plane counting only the pixels where `keep` holds (the others
    /// as 0), with the arithmetic of [`Self::sample1`].
    #[inline(always)]
    pub(crate) fn sample_where(&self, plane: &[f32], keep: impl Fn(usize) -> bool) -> T {
        let [i00, i10, i01, i11] = self.corners();
        let at = |i: usize| if keep(i) { T::of32(plane[i]) } else { T::zero() };
        let top = at(i00) + self.wx * (at(i10) - at(i00));
        let bot = at(i01) + self.wx * (at(i11) - at(i01));
        top + self.wy * (bot - top)
    }

    /// Samples `c` interleaved channels into `out`.
    #[inline(always)]
    pub(crate) fn sample_c(&self, plane: &[f32], c: usize, out: &mut [T]) {
        let (wx, wy) = (self.wx, self.wy);
        let [i00, i10, i01, i11] = self.corners();
        for k in 0..c {
            let at = |i: usize| T::of32(plane[c * i + k]);
            let top = at(i00) + wx * (at(i10) - at(i00));
            let bot = at(i01) + wx * (at(i11) - at(i01));
            out[k] = top + wy * (bot - top);
        }
    }
}
