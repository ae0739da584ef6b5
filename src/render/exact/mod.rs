//! Exact-mode rendering: every target ray is intersected with the planes analytically.
//!
//! For a target pixel p let u = K_t^-1 p (unit z), v = R^T u (the ray direction in source
//! coordinates), s = v_z, C = -R^T t (the target centre in source coordinates) and k = -C_z.
//! The ray C + lambda v meets plane Z = d_i at lambda_i = (d_i + k) / s, which is also the
//! point's depth in the target camera. With g_i = lambda_i / d_i = (1 + k disp_i) / s the source
//! pixel is q_i = (fx_s (C_x disp_i + v_x g_i) + cx_s, fy_s (C_y disp_i + v_y g_i) + cy_s),
//! finite even for disparity 0. Planes with g_i <= 0 lie behind the target camera and are not
//! seen; planes are composited in increasing lambda (source order when s > 0, reversed when the
//! camera has passed the planes and looks back, s < 0); the gap between consecutive planes along
//! the ray is (lambda_{i+1} - lambda_i) |u|, the last one `DELTA_LAST`
//! ([`crate::mpi::planes`]). A ray that leaves the source image (q outside [-0.5, W-0.5] x
//! [-0.5, H-0.5]) sees nothing on that plane, so holes show as coverage < 1 instead of smeared
//! borders.
//!
//! The source view uses H_i p = K_t R K_s^-1 p + K_t t disp_i (homogeneous): planes whose point
//! is behind the target camera (third coordinate <= 0) carry no flow; flow is the weight-
//! normalised mean over the planes in front.
//!
//! This is the only implementation of these loops (the tile width `TILE`, the per-plane
//! constants, `tile_activity`); `SourceLanes` and `TargetLanes` run the same loops for four
//! adjacent pixels at once in `f32` lanes, operation for operation, so with the same bits (the
//! scalar loops are their reference and take the rest). Every exact render goes through it: the
//! full frame, and windows of it (`render_window`). Both passes take a window `win` of the frame
//! and write window-sized buffers (pixel (x, y) of them is frame pixel (win.x0 + x, win.y0 +
//! y)); rays, sampling and the "leaves the source image" test always use the whole frame, so a
//! pixel's value does not depend on the window it is rendered in. Tiles start at `win.x0` and
//! bands at `win.y0`; tile skipping only drops planes whose density is at most the occupancy's
//! `sigma_eps` over the tile's footprint, which with `sigma_eps = 0` (the default) contribute
//! nothing, so tile alignment does not change values either. Extra channels are sampled per
//! plane from the MPI or from one H x W mask shared by every plane ([`super::Channels`]); the
//! source view can be restricted to the pixels where a mask is positive.
//!
//! The band loops run on the vector path chosen at start-up ([`crate::isa`]): each band is a
//! job (`TargetBandJob`, `SourceBandJob`) whose loop is inlined into a function compiled for
//! AVX-512, AVX2 or the SSE2 baseline; the source view then takes 16, 8 or 4 pixels per plane
//! step (`SourceLanes::wide`, `SourceLanes::four`), and on AVX-512 the target view takes a tile
//! row of 16 pixels reading packed planes in registers ([`row16`]; four pixels at a time
//! on the other paths and for the other samplers), the same bits on every path.
//!
//! # The rooms
//!
//! This file is the front door: the entry points [`target_view`], [`target_view_cut`] and
//! [`source_view`]. Each room names only rooms under it (`tests/server/layers.rs` holds the order):
//! `plane` (the tile width, the per-plane constants, the depth cap, a true-depth texel's search
//! `SurfaceRay`) < `row16` (the target view's sixteen-lane loop on AVX-512, `TargetLanes`), `source_lanes` (the source view's lane loops, `SourceLanes`) < `sampler` (the plane samplers' trait, the bilinear and
//! the density-cut samplers, the four lanes' taps), `geometry` (the target view's per-render
//! constants, `TargetGeometry`), `activity` (the planes a tile may need, `tile_activity`),
//! `source` (the source view and its band loop) < `kernel` (the samplers of the higher-order
//! colour kernels), `lanes` (the target view's four-lane loop, `TargetLanes::new` and
//! `TargetLanes::four`) < `target_band` (the target view's band loop) < `target` (the target
//! view's set-up, once per colour kernel and number of links).
//!
//! A scalar loop and its lane twin sit in rooms side by side (`target_band` and `lanes`,
//! `source` and `source_lanes`) and read the same per-plane constants; each twin follows its
//! loop operation for operation, so a change to one is a change to both. One thing here stays
//! large on purpose: `TargetBand::band` (about 180 lines) is the target view's band loop, which
//! the compiler must see whole: its set-up is outside it (`TargetGeometry`, `TargetLanes::new`),
//! but the tile's planes, the edge clamp, the link sums or the pixel's writes as inlined
//! functions of their own cost 1.9% more instructions in the band loop of the bilinear target
//! pass (cachegrind, `mpiflow bench render --threads 1 --pass target --resample bilinear`).

mod activity;
mod geometry;
mod kernel;
mod lanes;
mod plane;
mod row16;
mod sampler;
mod source;
mod source_lanes;
mod target;
mod target_band;

pub(super) use source::source_view;
pub(super) use target::{target_view, target_view_cut};
