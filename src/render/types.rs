//! The render's shared types: its parameters ([`RenderParams`]: [`Mode`], [`Fields`], [`Skip`],
//! the colour kernel [`Resample`], the [`View`]s a render links into), where its extra channels
//! come from ([`Channels`]), what it produces ([`RenderOutput`], [`Link`], [`RenderStats`]), its
//! error ([`RenderError`]) and a density cut ([`DensityCut`]). A leaf of `render/`: it names no
//! other module of it.

use serde::{Deserialize, Serialize};

use crate::geometry::{Intrinsics, Pose};

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
    /// The colour kernel of the exact-mode target view ([`Resample`]); the reference mode is
    /// always bilinear.
    pub resample: Resample,
    /// Alias-free minification of the exact-mode target view's colour: planes that the view
    /// shrinks are sampled from prefiltered levels (`render::mip`). Off = the colour kernel alone.
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
    /// [`Channels::Broadcast`] where it is needed only inside the frame's rectangle
    /// `[x0, x1) x [y0, y1)` given as `[x0, y0, x1, y1]` (where the mask's footprint lies; a
    /// `Rect`'s bounds): inside it every value is `Broadcast`'s; outside it the target view
    /// computes the channel only in the tiles that meet the rectangle, and leaves 0 in the
    /// others (a scene render that also gives the moved objects' mask costs little more than the
    /// render alone).
    BroadcastWithin(&'a [f32], [usize; 4]),
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
/// the source grid; both are `width` x `height`: the MPI's size for a full-frame render, the window's
/// for a window. Empty when not requested.
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

/// The reconstruction kernel of the target render's colour (`render::resample` describes each).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Resample {
    /// 2 x 2 bilinear (the reference's kernel).
    Bilinear,
    /// 4 x 4 Keys cubic convolution (a = -1/2).
    Bicubic,
    /// 4 x 4 cubic B-spline interpolation (prefiltered coefficients); the default.
    #[default]
    Bspline3,
    /// 6 x 6 quintic B-spline interpolation (prefiltered coefficients).
    Bspline5,
    /// 6 x 6 Lanczos-3 (normalised windowed sinc).
    Lanczos3,
    /// 4 x 4 OMOMS-3 interpolation (prefiltered coefficients): the cubic of Blu, Thevenaz and
    /// Unser of maximal order and minimal support, the cubic B-spline's cost and taps.
    Omoms3,
}

pub use crate::mpi::Prefilter;

impl Resample {
    pub const ALL: [Resample; 6] = [
        Resample::Bilinear,
        Resample::Bicubic,
        Resample::Bspline3,
        Resample::Bspline5,
        Resample::Lanczos3,
        Resample::Omoms3,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Resample::Bilinear => "bilinear",
            Resample::Bicubic => "bicubic",
            Resample::Bspline3 => "bspline3",
            Resample::Bspline5 => "bspline5",
            Resample::Lanczos3 => "lanczos3",
            Resample::Omoms3 => "omoms3",
        }
    }

    /// The prefilter of a kernel that samples prefiltered coefficients instead of the colours
    /// themselves.
    pub fn prefilter(self) -> Option<Prefilter> {
        match self {
            Resample::Bspline3 => Some(Prefilter::Bspline3),
            Resample::Bspline5 => Some(Prefilter::Bspline5),
            Resample::Omoms3 => Some(Prefilter::Omoms3),
            _ => None,
        }
    }
}

impl std::fmt::Display for Resample {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Resample {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Resample::ALL.into_iter().find(|r| r.name() == s).ok_or_else(|| {
            let names: Vec<&str> = Resample::ALL.iter().map(|r| r.name()).collect();
            format!("unknown resample kernel `{s}` (expected one of {})", names.join(", "))
        })
    }
}

/// Which planes are taken out where: at source pixel `p` with `mask[p] > 0`, planes
/// `0..=last[p]` (the nearest first) keep `1 - mask[p]` of their density; the planes behind
/// `last[p]` and every plane elsewhere are untouched.
#[derive(Clone, Copy, Debug)]
pub struct DensityCut<'a> {
    /// H x W, in [0, 1].
    pub mask: &'a [f32],
    /// H x W: the farthest plane cut at each pixel.
    pub last: &'a [u8],
}
