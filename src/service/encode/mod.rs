//! Samples on the wire: cropping (centre, or a position from the sample's own random stream),
//! a sample's tensors (their bytes: [`super::tensor`]) and the way back (decoding a received
//! sample, for `mpiflow pull` and tests, reading the received bytes in place).
//!
//! Rooms: `fields` (what a request wants: the fields, their wire names and sizes; the crop and its
//! cut are [`crate::sample::crop`]'s), `wire` (a sample's tensors and message), `decode` (the way back).

mod decode;
mod fields;
#[cfg(test)]
mod tests;
mod wire;

pub use crate::sample::crop::{crop_sample, crop_window, CropSpec, CropTooLarge, CROP_PURPOSE};
pub use decode::{decode_f32, decode_tensor, from_proto, raw_view, DecodeError};
pub use fields::{
    bytes_per_pixel, clip_field_name, field_name, wants_backward, wants_occlusion, OutputSpec, ALL_FIELDS,
    DEFAULT_FIELDS,
};
pub use wire::to_proto;
