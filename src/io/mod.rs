//! File formats: NumPy arrays, Middlebury `.flo`, the flow colour wheel, PNG/JPEG images.

pub mod colorwheel;
pub mod extent;
pub mod flo;
pub mod image;
pub mod npy;
