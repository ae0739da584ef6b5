//! File formats: NumPy arrays, Middlebury `.flo`, the flow colour wheel, PNG/JPEG images; small
//! text files read with a size bound.

pub mod bounded;
pub mod colorwheel;
pub mod extent;
pub mod flo;
pub mod image;
pub mod npy;
pub mod scaled;
