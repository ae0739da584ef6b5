//! The built-in MPI builder: the RGB-D layering of [`crate::mpi::layering`] behind the
//! [`MpiBuilder`] trait, for when no MPI network is configured.
//!
//! The scene-scale disparity is turned into depth `1 / max(disparity, `[`DISPARITY_FLOOR`](super::scale::DISPARITY_FLOOR)`)` (so at
//! most 1000) and layered with [`build_mpi_for_camera`] for the scene's intrinsics: `planes`
//! planes uniform in disparity over the scene's own disparity range (or over
//! `disparity_range`, e.g. the reference's `(1.0, 0.001)`), each pixel on its nearest plane
//! ([`Layering::Hard`]: each pixel moves as one, so image2 keeps more detail) or split between its
//! two neighbouring planes ([`Layering::Soft`], the default, whose composite reproduces the
//! disparity exactly); with `backdrop`, the background behind objects and depth edges is
//! completed ([`crate::mpi::backdrop`]) and the object masks are aligned with their depth edges
//! ([`super::matte`]). Its name, which goes into provenance and the dataset fingerprint, is
//! `builtin soft 32` (plus ` range NEAR-FAR` when a range is set, ` backdrop` with it).

use super::scale::depth_from_disparity;
use super::{Disparity, MpiBuilder, SceneError};
use crate::geometry::Intrinsics;
use crate::io::image::RgbImage;
use crate::mpi::layering::{
    build_mpi_for_camera, build_mpi_for_scene, Layering, LayeringOptions, Placement, MAX_PLANES,
};
use crate::mpi::Mpi;
use crate::raster::InstanceMasks;

/// The built-in layering as an [`MpiBuilder`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BuiltinMpi {
    /// Number of planes, 1 to [`MAX_PLANES`].
    pub planes: usize,
    pub layering: Layering,
    /// Where the planes go within the scene's range ([`Placement`]).
    pub placement: Placement,
    /// (nearest, farthest) plane disparities; `None` = the scene's own range.
    pub disparity_range: Option<(f64, f64)>,
    /// Complete the background behind objects and depth edges ([`crate::mpi::backdrop`]).
    pub backdrop: bool,
}

impl Default for BuiltinMpi {
    /// 32 planes, soft layering uniform over the scene's own range, no completed background.
    fn default() -> Self {
        BuiltinMpi::new(32, Layering::default())
    }
}

impl BuiltinMpi {
    fn options(&self) -> LayeringOptions {
        LayeringOptions {
            planes: self.planes,
            layering: self.layering,
            placement: self.placement,
            disparity_range: self.disparity_range,
            backdrop: self.backdrop,
        }
    }

    pub fn new(planes: usize, layering: Layering) -> Self {
        BuiltinMpi { planes, layering, placement: Placement::Uniform, disparity_range: None, backdrop: false }
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
        let kind = self.layering;
        let completed = if self.backdrop { " backdrop" } else { "" };
        // uniform placement keeps the name (and so the fingerprints) it had before placements
        let placed = if self.placement == Placement::Uniform { "" } else { " content" };
        match self.disparity_range {
            None => format!("builtin {kind} {}{placed}{completed}", self.planes),
            Some((near, far)) => format!("builtin {kind} {} range {near}-{far}{completed}", self.planes),
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
        Ok(build_mpi_for_camera(&image.data, &depth, image.width, image.height, &self.options(), k)?)
    }

    fn aligns_masks(&self) -> bool {
        self.backdrop
    }

    fn build_with_masks(
        &self,
        image: &RgbImage,
        disparity: &Disparity,
        masks: &InstanceMasks,
        k: &Intrinsics,
    ) -> Result<Mpi, SceneError> {
        let n = image.width * image.height;
        if (masks.width, masks.height) != (image.width, image.height) || masks.masks.iter().any(|m| m.mask.len() != n) {
            return self.build(image, disparity, k);
        }
        if (disparity.width, disparity.height) != (image.width, image.height) || disparity.data.len() != n {
            return self.build(image, disparity, k);
        }
        let union: Vec<bool> = (0..n).map(|p| masks.masks.iter().any(|m| m.mask[p] >= 0.5)).collect();
        let depth = depth_from_disparity(disparity);
        Ok(build_mpi_for_scene(&image.data, &depth, image.width, image.height, &self.options(), k, &union)?)
    }
}
