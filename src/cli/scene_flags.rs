//! The scene model flags shared by `generate`, `bake` and `bench quality`: each flag left out
//! keeps [`ModelConfig`]'s default, so the defaults are declared once, there.

use std::path::PathBuf;

use clap::Args;
use mpiflow::mpi::layering::{Layering, Placement};
use mpiflow::scene::models::ModelConfig;

#[derive(Args, Clone, Debug, Default)]
pub struct SceneFlags {
    /// Depth model for photos without depth: a NAME (`mpiflow models list`; fetched and cached on
    /// first use) or an ONNX FILE (optional manifest FILE.toml beside it; docs/models.md).
    #[arg(long, value_name = "NAME|FILE")]
    pub depth_model: Option<PathBuf>,
    /// MPI network (ONNX, AdaMPI-style default contract) instead of the built-in layering.
    #[arg(long, value_name = "FILE.onnx")]
    pub mpi_model: Option<PathBuf>,
    /// Instance segmentation model for photos without masks: a NAME or an ONNX FILE.
    #[arg(long, value_name = "NAME|FILE")]
    pub segment_model: Option<PathBuf>,
    /// MPI planes of the built-in layering, 1 to 256 (default 32; ignored for items with a given
    /// MPI or with --mpi-model).
    #[arg(long, value_name = "N")]
    pub planes: Option<usize>,
    /// Layering of the built-in MPI: soft (the default: each pixel split between the two planes
    /// around its depth), hard (each pixel on its nearest plane) or true-depth (soft, every
    /// texel at the pixel's own depth; docs/quality.md).
    #[arg(long, value_name = "KIND")]
    pub layering: Option<Layering>,
    /// Where the built-in layering puts its planes in disparity: uniform (the default) or content
    /// (dense where the photo's depths are; docs/quality.md, "The realistic scene").
    #[arg(long, value_name = "KIND")]
    pub placement: Option<Placement>,
    /// Complete the background behind objects and depth edges once per scene and align the object
    /// masks with their depth edges (built-in layering; off by default; `--backdrop` or
    /// `--backdrop=true` turns it on; docs/quality.md).
    #[arg(long, value_name = "BOOL", num_args = 0..=1, default_missing_value = "true")]
    pub backdrop: Option<bool>,
}

impl SceneFlags {
    /// The scene models: these flags over [`ModelConfig::default`].
    pub fn models(&self) -> ModelConfig {
        let d = ModelConfig::default();
        ModelConfig {
            planes: self.planes.unwrap_or(d.planes),
            layering: self.layering.unwrap_or(d.layering),
            placement: self.placement.unwrap_or(d.placement),
            backdrop: self.backdrop.unwrap_or(d.backdrop),
            depth_model: self.depth_model.clone(),
            mpi_model: self.mpi_model.clone(),
            segment_model: self.segment_model.clone(),
        }
    }
}
