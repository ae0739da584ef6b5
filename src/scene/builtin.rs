//! The built-in MPI builder: the RGB-D layering of [`crate::mpi::layering`] behind the
//! [`MpiBuilder`] trait, for when no MPI network is configured.
//!
//! The scene-scale disparity is turned into depth `1 / max(disparity, `[`DISPARITY_FLOOR`](super::scale::DISPARITY_FLOOR)`)` (so at
//! most 1000) and layered with [`build_mpi_for_camera`] for the scene's intrinsics: `planes`
//! planes uniform in disparity over the scene's own disparity range (or over
//! `disparity_range`, e.g. the reference's `(1.0, 0.001)`), each pixel on its nearest plane
//! ([`Layering::Hard`]) or split between its two neighbouring planes ([`Layering::Soft`], the
//! default, whose composite reproduces the disparity exactly). Its name, which goes into
//! provenance and the dataset fingerprint, is `builtin soft 32` (plus ` range NEAR-FAR` when a
//! range is set).

use super::scale::depth_from_disparity;
use super::{Disparity, MpiBuilder, SceneError};
use crate::geometry::Intrinsics;
use crate::io::image::RgbImage;
use crate::mpi::layering::{build_mpi_for_camera, Layering, LayeringOptions, MAX_PLANES};
use crate::mpi::Mpi;

/// The built-in layering as an [`MpiBuilder`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BuiltinMpi {
    /// Number of planes, 1 to [`MAX_PLANES`].
    pub planes: usize,
    pub layering: Layering,
    /// (nearest, farthest) plane disparities; `None` = the scene's own range.
    pub disparity_range: Option<(f64, f64)>,
}

impl Default for BuiltinMpi {
    /// 32 planes, soft layering, the scene's own range.
    fn default() -> Self {
        BuiltinMpi { planes: 32, layering: Layering::Soft, disparity_range: None }
    }
}

impl BuiltinMpi {
    pub fn new(planes: usize, layering: Layering) -> Self {
        BuiltinMpi { planes, layering, disparity_range: None }
    }

    /// Checks the configuration (planes in range, range ordered), for start-up validation.
    pub fn validate(&self) -> Result<(), SceneError> {
        if !(1..=MAX_PLANES).contains(&self.planes) {
            return Err(SceneError::Invalid(format!(
                "builtin MPI: {} planes requested; the built-in layering makes 1 to {MAX_PLANES}",
                self.planes
            )));
        }
        if let Some((near, far)) = self.disparity_range {
            if !(near.is_finite() && far.is_finite() && far >= 0.0 && near > far) {
                return Err(SceneError::Invalid(format!(
                    "builtin MPI: disparity range ({near}, {far}) must be finite with near > far >= 0"
                )));
            }
        }
        Ok(())
    }
}

impl MpiBuilder for BuiltinMpi {
    fn name(&self) -> String {
        let kind = match self.layering {
            Layering::Hard => "hard",
            Layering::Soft => "soft",
        };
        match self.disparity_range {
            None => format!("builtin {kind} {}", self.planes),
            Some((near, far)) => format!("builtin {kind} {} range {near}-{far}", self.planes),
        }
    }

    fn build(&self, image: &RgbImage, disparity: &Disparity, k: &Intrinsics) -> Result<Mpi, SceneError> {
        let n = image.width * image.height;
        if (disparity.width, disparity.height) != (image.width, image.height) || disparity.data.len() != n {
            return Err(SceneError::Invalid(format!(
                "builtin MPI: disparity of {} x {} for an image of {} x {}",
                disparity.width, disparity.height, image.width, image.height
            )));
        }
        let depth = depth_from_disparity(disparity);
        let opts =
            LayeringOptions { planes: self.planes, layering: self.layering, disparity_range: self.disparity_range };
        Ok(build_mpi_for_camera(&image.data, &depth, image.width, image.height, &opts, k)?)
    }
}
