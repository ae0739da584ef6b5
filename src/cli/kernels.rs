//! The `--resample` values: the kernels [`Resample::ALL`] declares, parsed and listed in each
//! command's help from that one declaration.

use clap::builder::{PossibleValuesParser, TypedValueParser};
use mpiflow::render::Resample;

/// The parser of a `--resample` value: a name of [`Resample::ALL`], each shown in the help.
pub fn resample_parser() -> impl TypedValueParser<Value = Resample> {
    PossibleValuesParser::new(Resample::ALL.map(Resample::name)).try_map(|name| name.parse::<Resample>())
}
