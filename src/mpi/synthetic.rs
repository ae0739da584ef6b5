//! Synthetic MPIs for benchmarks and tests (placeholder, being written).
