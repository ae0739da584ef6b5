//! PNG/JPEG decoding and encoding with size limits (placeholder, being written).
