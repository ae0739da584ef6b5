//! Benchmarks (placeholder, being written).
