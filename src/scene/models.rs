//! Which scene models a pipeline uses (ONNX files, or the built-in layering with the given
//! plane count) and loading them into a [`SceneStage`]: the one place models are opened, for the
//! server, `mpiflow generate` and the benches alike.

use std::path::PathBuf;
use std::sync::Arc;

use serde::{Deserialize, Serialize};

use super::builtin::BuiltinMpi;
use super::hub::Hub;
use super::onnx::{OnnxMpi, OnnxMpiConfig};
use super::registry::{self, Role};
use super::stage::SceneStage;
use super::MpiBuilder;
use crate::mpi::layering::{Layering, LayeringOptions, Placement, MAX_PLANES};

/// The scene models shared by every dataset (ONNX files; none = the built-in layering, with depth
/// and masks coming with the sources).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ModelConfig {
    /// Planes of the built-in layering (when there is no MPI model). Default 32 (docs/quality.md,
    /// "The realistic scene": 128 placed by content keep more detail, opt-in until the label
    /// tests hold with them).
    pub planes: usize,
    /// How the built-in layering assigns pixels to planes: `soft` (split between two planes, the
    /// default) or `hard` (each pixel on its nearest plane: sharper image2, seams on slopes;
    /// docs/quality.md).
    pub layering: Layering,
    /// Where the built-in layering puts its planes in disparity: `uniform` (the default) or
    /// `content` (dense where the scene's pixels are; docs/quality.md, "The realistic scene").
    pub placement: Placement,
    /// Complete the background behind objects and depth edges once per scene and align the
    /// object masks with their depth edges (the built-in layering; default false: what motion
    /// reveals then shows the photo's texture at the background's depth, docs/quality.md).
    pub backdrop: bool,
    /// Depth model for sources without depth: a registry name (`mpiflow models list`, fetched
    /// into the hub cache on first use) or an ONNX file (with an optional `FILE.toml` manifest).
    pub depth_model: Option<PathBuf>,
    /// MPI network (ONNX, AdaMPI-style) instead of the built-in layering.
    pub mpi_model: Option<PathBuf>,
    /// Instance segmentation model for sources without masks: a registry name or an ONNX file.
    pub segment_model: Option<PathBuf>,
}

impl Default for ModelConfig {
    fn default() -> Self {
        Self {
            planes: 32,
            layering: Layering::default(),
            placement: Placement::Uniform,
            backdrop: false,
            depth_model: None,
            mpi_model: None,
            segment_model: None,
        }
    }
}

impl ModelConfig {
    /// The built-in layering's options of these models (the scene's own disparity range).
    pub fn layering_options(&self) -> LayeringOptions {
        LayeringOptions {
            planes: self.planes,
            layering: self.layering,
            placement: self.placement,
            disparity_range: None,
            backdrop: self.backdrop,
        }
    }

    /// Loads the models (ONNX sessions are created and warmed here, each file read and hashed
    /// once) into a scene stage. Errors name the key (`planes`, `depth model`, ...).
    pub fn build_stage(&self) -> Result<SceneStage, String> {
        let mpi: Arc<dyn MpiBuilder> = match &self.mpi_model {
            Some(p) => Arc::new(OnnxMpi::new(OnnxMpiConfig::new(p)).map_err(|e| format!("mpi model: {e}"))?),
            None => {
                if !(1..=MAX_PLANES).contains(&self.planes) {
                    return Err(format!("planes = {}: expected 1 to {MAX_PLANES}", self.planes));
                }
                let b = BuiltinMpi {
                    backdrop: self.backdrop,
                    placement: self.placement,
                    ..BuiltinMpi::new(self.planes, self.layering)
                };
                b.validate().map_err(|e| e.to_string())?;
                Arc::new(b)
            }
        };
        let mut stage = SceneStage::new(mpi);
        let hub = Hub::from_env();
        if let Some(p) = &self.depth_model {
            let r = registry::resolve(p, Role::Depth, &hub, true).map_err(|e| e.to_string())?;
            let m = registry::load_depth(&r).map_err(|e| format!("depth model: {e}"))?;
            stage = stage.with_depth(m);
        }
        if let Some(p) = &self.segment_model {
            let r = registry::resolve(p, Role::Segment, &hub, true).map_err(|e| e.to_string())?;
            let m = registry::load_segmenter(&r).map_err(|e| format!("segment model: {e}"))?;
            stage = stage.with_segmenter(m);
        }
        Ok(stage)
    }
}
