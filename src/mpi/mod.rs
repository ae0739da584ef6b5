//! The multiplane image: N fronto-parallel planes of (r, g, b, sigma) plus optional extra
//! channels (object masks), plane disparities near to far, and the checks and sanitising that
//! every MPI passes before it reaches the renderer. The plane spacing rule (depths, gaps,
//! [`planes::DELTA_LAST`], [`planes::DEPTH_MAX`]) lives in [`planes`]; `mpi` depends on nothing
//! above it (not on `render`).

pub mod backdrop;
pub mod bricks;
pub mod layering;
pub mod npz;
pub mod planes;
pub mod synthetic;

use crate::geometry::{Intrinsics, Pose};

/// Largest density kept after sanitising; large enough to be opaque over any plane gap, small
/// enough that sigma * delta stays finite in f32 for deltas up to 1e8.
pub const SIGMA_MAX: f32 = 1e30;

#[derive(Debug, thiserror::Error)]
pub enum MpiError {
    #[error("cannot read {path}: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("{path}: not a valid .npz archive: {reason}")]
    BadArchive { path: String, reason: String },
    #[error("{path}: missing array `{key}`")]
    MissingKey { path: String, key: &'static str },
    #[error("{path}: array `{key}` has shape {shape:?}, expected {expected}")]
    BadShape { path: String, key: String, shape: Vec<u64>, expected: String },
    #[error("{0}")]
    Invalid(String),
}

/// How many values the sanitiser had to repair.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SanitizeReport {
    /// NaN or infinite colours and extra channels, set to 0.
    pub nonfinite_color: usize,
    /// NaN or negative densities set to 0, +inf or larger than SIGMA_MAX clamped.
    pub bad_sigma: usize,
}

impl SanitizeReport {
    pub fn total(&self) -> usize {
        self.nonfinite_color + self.bad_sigma
    }
}

/// A multiplane image. Plane 0 is the nearest; plane data is plane-major, row-major,
/// interleaved (r, g, b, sigma) per pixel; extras are plane-major, row-major, `channels` per pixel.
#[derive(Clone, Debug)]
pub struct Mpi {
    pub width: usize,
    pub height: usize,
    /// Plane disparities (1 / depth), strictly decreasing, >= 0 (0 = infinitely far).
    pub disparity: Vec<f64>,
    /// N * H * W * 4 values: r, g, b in [0, 1] (not enforced), sigma >= 0; empty once the MPI
    /// is packed into [`Self::rgba_blocks`].
    pub rgba: Vec<f32>,
    /// The planes in 16 x 16 blocks, only those a render can read (a prepared scene's MPI,
    /// `render::store::pack`); `rgba` is empty then. Renders read them through
    /// `render::store::Rgba`; [`Self::unpacked`] gives a dense copy.
    pub rgba_blocks: Option<std::sync::Arc<bricks::Bricks>>,
    /// Number of extra channels per plane pixel (0 when none).
    pub extra_channels: usize,
    /// N * H * W * extra_channels values.
    pub extras: Vec<f32>,
    /// Intrinsics stored with the MPI (from an npz `K`), if any.
    pub intrinsics: Option<Intrinsics>,
    /// Pose stored with the MPI (from an npz `G`), if any.
    pub pose: Option<Pose>,
    /// B-spline coefficients of the rgb channels, for the B-spline resampling of the target
    /// render (`render::resample`); None until a scene is prepared for it. They describe `rgba`
    /// as it was when they were computed: whoever changes the colours afterwards must drop them
    /// (the renderer computes its own when they are missing or of another degree).
    pub bspline_rgb: Option<BsplineRgb>,
    /// Prefiltered levels of every plane's colour for alias-free minification
    /// (`render::mip`); None until a scene is prepared for it. Like [`Self::bspline_rgb`], they
    /// describe `rgba` as it was when they were computed.
    pub mip: Option<std::sync::Arc<MipLevels>>,
    /// The true-depth surface ([`Surface`]): every texel's own disparity, for layers whose
    /// texels keep their depth ([`layering::Layering::TrueDepth`]); None: every texel lies on
    /// its plane.
    pub surface: Option<std::sync::Arc<Surface>>,
}

/// The disparity of the photo's surface at every pixel (H x W, row-major, finite and >= 0) that
/// the texels of a true-depth MPI follow: the texel of plane `i` at pixel `p` lies at disparity
/// `disp_i + clamp(s(p) - disp_i, lo_i, hi_i)`, `[lo_i, hi_i]` its slab ([`Surface::slab`]: from
/// the plane behind to the plane in front), so a pixel split between two planes keeps one
/// depth on both and its two copies move as one.
#[derive(Clone, Debug)]
pub struct Surface {
    pub disparity: Vec<f32>,
}

impl Surface {
    /// The slab `[lo, hi]` of plane `i`'s offsets (`lo <= 0 <= hi`): down to the plane behind,
    /// up to the plane in front (0 beyond the farthest and the nearest plane).
    pub fn slab(disparity: &[f64], i: usize) -> (f64, f64) {
        let lo = disparity.get(i + 1).map_or(0.0, |&b| b - disparity[i]);
        let hi = if i == 0 { 0.0 } else { disparity[i - 1] - disparity[i] };
        (lo, hi)
    }
}

/// One prefiltered level of a plane ([`MipLevels`]): colour (interleaved RGB) and density,
/// `width` x `height`.
#[derive(Clone, Debug)]
pub struct MipLevel {
    pub rgb: Vec<f32>,
    pub sigma: Vec<f32>,
    pub width: usize,
    pub height: usize,
}

/// Levels 1, 2, ... of every plane (`planes[i][l - 1]` is level `l` of plane `i`; a plane may
/// hold fewer levels than another, or none).
#[derive(Clone, Debug, Default)]
pub struct MipLevels {
    pub planes: Vec<Vec<MipLevel>>,
}

impl MipLevels {
    /// Values held (floats).
    pub fn len(&self) -> usize {
        self.planes.iter().flatten().map(|l| l.rgb.len() + l.sigma.len()).sum()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// The prefilter whose coefficients a kernel samples instead of the colours
/// (`render::Resample::prefilter`; `render::resample::prefilter`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Prefilter {
    /// Cubic B-spline interpolation.
    Bspline3,
    /// Quintic B-spline interpolation.
    Bspline5,
    /// OMOMS-3 interpolation.
    Omoms3,
}

impl Prefilter {
    /// The number that names it in the scene cache's key (`SampleConfig::scene_variant`): the
    /// B-spline's degree, 7 for OMOMS-3.
    pub fn id(self) -> u32 {
        match self {
            Prefilter::Bspline3 => 3,
            Prefilter::Bspline5 => 5,
            Prefilter::Omoms3 => 7,
        }
    }

    /// The kernel's taps per axis.
    pub fn taps(self) -> usize {
        match self {
            Prefilter::Bspline5 => 6,
            Prefilter::Bspline3 | Prefilter::Omoms3 => 4,
        }
    }
}

/// Prefiltered colour of an MPI ([`Mpi::bspline_rgb`]).
#[derive(Clone, Debug)]
pub struct BsplineRgb {
    /// The kernel's prefilter.
    pub prefilter: Prefilter,
    /// The rgb coefficients (3 values per pixel) of the blocks the colour kernel can reach:
    /// those with density on the plane (`render::resample::prefilter`), or all of them.
    pub coefficients: std::sync::Arc<bricks::Bricks>,
}

impl Mpi {
    /// An MPI of transparent black planes at the given disparities.
    pub fn new(width: usize, height: usize, disparity: Vec<f64>, extra_channels: usize) -> Self {
        let n = disparity.len();
        Self {
            width,
            height,
            disparity,
            rgba: crate::buf::reused_zeros(n * width * height * 4),
            rgba_blocks: None,
            extra_channels,
            extras: vec![0.0; n * width * height * extra_channels],
            intrinsics: None,
            pose: None,
            bspline_rgb: None,
            mip: None,
            surface: None,
        }
    }

    /// [`Mpi::new`] without extra channels for a caller that writes every value of `rgba`
    /// (the layering): the planes' buffer is a reused one as it is ([`crate::buf::reused_to_write`]).
    pub fn to_write(width: usize, height: usize, disparity: Vec<f64>) -> Self {
        let rgba = crate::buf::reused_to_write(disparity.len() * width * height * 4);
        Self { width, height, rgba, ..Self::new(0, 0, disparity, 0) }
    }

    pub fn planes(&self) -> usize {
        self.disparity.len()
    }

    #[inline]
    pub fn plane_len(&self) -> usize {
        self.width * self.height
    }

    /// Plane `i`'s dense data.
    ///
    /// # Panics
    /// If the MPI is packed ([`Self::rgba_blocks`]; see [`Self::unpacked`]).
    #[inline]
    pub fn plane_rgba(&self, i: usize) -> &[f32] {
        assert!(self.rgba_blocks.is_none(), "plane_rgba of a packed MPI (read it through render::store)");
        let n = self.plane_len() * 4;
        &self.rgba[i * n..(i + 1) * n]
    }

    /// A copy of everything but the plane data (`rgba` and `extras` empty; the shared blocks,
    /// coefficients and levels are shared, not copied).
    pub fn clone_without_planes(&self) -> Mpi {
        Mpi {
            width: self.width,
            height: self.height,
            disparity: self.disparity.clone(),
            rgba: Vec::new(),
            rgba_blocks: self.rgba_blocks.clone(),
            extra_channels: self.extra_channels,
            extras: Vec::new(),
            intrinsics: self.intrinsics,
            pose: self.pose,
            bspline_rgb: self.bspline_rgb.clone(),
            mip: self.mip.clone(),
            surface: self.surface.clone(),
        }
    }

    /// Whether the planes are held in blocks ([`Self::rgba_blocks`]).
    pub fn is_packed(&self) -> bool {
        self.rgba_blocks.is_some()
    }

    /// The MPI with dense planes: itself, or a copy with the blocks spread out (pixels of blocks
    /// not kept read 0: they have no density, so every render gives the same bits).
    pub fn unpacked(&self) -> std::borrow::Cow<'_, Mpi> {
        let Some(b) = &self.rgba_blocks else { return std::borrow::Cow::Borrowed(self) };
        let mut m = self.clone();
        m.rgba_blocks = None;
        m.rgba = (0..self.planes()).flat_map(|i| b.plane_dense(i)).collect();
        std::borrow::Cow::Owned(m)
    }

    /// Plane `i`'s data for a change; drops the prefiltered coefficients ([`Self::bspline_rgb`]).
    ///
    /// # Panics
    /// If the MPI is packed.
    pub fn plane_rgba_mut(&mut self, i: usize) -> &mut [f32] {
        assert!(self.rgba_blocks.is_none(), "plane_rgba_mut of a packed MPI");
        self.bspline_rgb = None;
        self.mip = None;
        let n = self.plane_len() * 4;
        &mut self.rgba[i * n..(i + 1) * n]
    }

    #[inline]
    pub fn plane_extras(&self, i: usize) -> &[f32] {
        let n = self.plane_len() * self.extra_channels;
        &self.extras[i * n..(i + 1) * n]
    }

    /// Bytes held by the plane data.
    pub fn byte_size(&self) -> usize {
        (self.rgba.len() + self.extras.len() + self.mip.as_ref().map_or(0, |m| m.len())) * 4
            + self.rgba_blocks.as_ref().map_or(0, |b| b.byte_size())
            + self.bspline_rgb.as_ref().map_or(0, |c| c.coefficients.byte_size())
            + self.surface.as_ref().map_or(0, |s| s.disparity.len() * 4)
    }

    /// Structural checks: sizes agree, at least one plane, disparities finite, >= 0 and
    /// strictly decreasing (near to far).
    pub fn validate(&self) -> Result<(), MpiError> {
        if self.width == 0 || self.height == 0 {
            return Err(MpiError::Invalid(format!("MPI has an empty size {}x{}", self.width, self.height)));
        }
        let n = self.planes();
        if n == 0 {
            return Err(MpiError::Invalid("MPI has no planes".into()));
        }
        let rgba_ok = match &self.rgba_blocks {
            None => self.rgba.len() == n * self.plane_len() * 4,
            Some(b) => {
                self.rgba.is_empty()
                    && (b.width(), b.height(), b.stride(), b.planes()) == (self.width, self.height, 4, n)
            }
        };
        if !rgba_ok
            || self.extras.len() != n * self.plane_len() * self.extra_channels
            || self.bspline_rgb.as_ref().is_some_and(|c| {
                let b = &c.coefficients;
                (b.width(), b.height(), b.stride()) != (self.width, self.height, 3)
            })
        {
            return Err(MpiError::Invalid("MPI plane data does not match its size".into()));
        }
        if let Some(s) = &self.surface {
            if s.disparity.len() != self.plane_len() || s.disparity.iter().any(|d| !(d.is_finite() && *d >= 0.0)) {
                return Err(MpiError::Invalid("MPI surface must hold one finite disparity >= 0 per pixel".into()));
            }
        }
        for (i, &d) in self.disparity.iter().enumerate() {
            if !d.is_finite() || d < 0.0 {
                return Err(MpiError::Invalid(format!(
                    "plane {i} has disparity {d:?}; disparities must be finite and >= 0"
                )));
            }
            if i > 0 && d >= self.disparity[i - 1] {
                return Err(MpiError::Invalid(format!(
                    // `{:?}`: 1e300 in 7 characters, not 301 digits (fuzz `npz_mpi` case 308105)
                    "plane disparities must decrease strictly from near to far; plane {i} has {d:?} after {:?}",
                    self.disparity[i - 1]
                )));
            }
        }
        Ok(())
    }

    /// Repairs values the renderer cannot use: non-finite colours become 0, NaN or negative
    /// densities 0, densities above [`SIGMA_MAX`] (including +inf) are clamped.
    pub fn sanitize(&mut self) -> SanitizeReport {
        let mut report = SanitizeReport::default();
        for px in self.rgba.chunks_exact_mut(4) {
            for c in &mut px[..3] {
                if !c.is_finite() {
                    *c = 0.0;
                    report.nonfinite_color += 1;
                }
            }
            let s = px[3];
            if s.is_nan() || s < 0.0 {
                px[3] = 0.0;
                report.bad_sigma += 1;
            } else if s > SIGMA_MAX {
                px[3] = SIGMA_MAX;
                report.bad_sigma += 1;
            }
        }
        for v in &mut self.extras {
            if !v.is_finite() {
                *v = 0.0;
                report.nonfinite_color += 1;
            }
        }
        report
    }

    /// Depth of plane i (infinite for disparity 0).
    pub fn depth(&self, i: usize) -> f64 {
        1.0 / self.disparity[i]
    }

    /// The public generator's fixed plane disparities: linspace(1.0, 0.001, n + 2)[1..n+1].
    pub fn reference_disparities(n: usize) -> Vec<f64> {
        let (a, b) = (1.0f64, 0.001f64);
        let m = (n + 1) as f64;
        (1..=n).map(|i| a + (b - a) * i as f64 / m).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reference_disparities_match_the_vectors() {
        let d = Mpi::reference_disparities(8);
        let expect = [0.889, 0.778, 0.667, 0.556, 0.445, 0.334, 0.223, 0.112];
        for (a, b) in d.iter().zip(expect) {
            assert!((a - b).abs() < 1e-7, "{a} vs {b}");
        }
    }

    #[test]
    fn sanitize_repairs_and_counts() {
        let mut m = Mpi::new(2, 1, vec![0.5, 0.1], 1);
        m.rgba[0] = f32::NAN;
        m.rgba[3] = f32::INFINITY;
        m.rgba[7] = -1.0;
        m.rgba[11] = f32::NAN;
        m.extras[1] = f32::NEG_INFINITY;
        let r = m.sanitize();
        assert_eq!(r, SanitizeReport { nonfinite_color: 2, bad_sigma: 3 });
        assert!(m.rgba.iter().all(|v| v.is_finite()));
        assert_eq!(m.rgba[3], SIGMA_MAX);
        assert_eq!(m.rgba[7], 0.0);
    }

    #[test]
    fn validate_rejects_bad_disparities() {
        assert!(Mpi::new(2, 2, vec![0.5, 0.6], 0).validate().is_err());
        assert!(Mpi::new(2, 2, vec![0.5, f64::NAN], 0).validate().is_err());
        assert!(Mpi::new(2, 2, vec![], 0).validate().is_err());
        assert!(Mpi::new(2, 2, vec![1.0, 0.0], 0).validate().is_ok());
    }
}
