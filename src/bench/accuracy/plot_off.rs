//! The accuracy plot without the `plots` cargo feature: the report is written without it and
//! these say how to get it (`cargo run --release --features plots -- bench accuracy ...`).

use super::{AccuracyError, AccuracyReport};
use std::path::Path;

fn off() -> AccuracyError {
    AccuracyError::Plot(
        "this build has no plotting (rebuild with `--features plots`, e.g. `cargo run --release --features plots -- bench accuracy ...`)"
            .into(),
    )
}

/// Without the `plots` feature: always [`AccuracyError::Plot`].
pub fn plot_rgb(_report: &AccuracyReport, _width: u32, _height: u32) -> Result<Vec<u8>, AccuracyError> {
    Err(off())
}

/// Without the `plots` feature: always [`AccuracyError::Plot`].
pub fn write_plot(_report: &AccuracyReport, _path: &Path, _width: u32, _height: u32) -> Result<(), AccuracyError> {
    Err(off())
}
