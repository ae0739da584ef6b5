//! Built-in RGB-D layering (placeholder, being written).
