//! PNG/JPEG decoding and encoding with size limits (being written).

/// An RGB image, H x W x 3 values in [0, 1], row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct RgbImage {
    pub width: usize,
    pub height: usize,
    pub data: Vec<f32>,
}
