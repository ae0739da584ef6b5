//! Tests that make a process-wide choice (the vector path, the ONNX Runtime library), kept in a
//! binary of their own so that no other test runs beside the choice.
//! One test binary per group (each file beside this one is a module), so that the suite links a
//! handful of binaries.

mod onnx_runtime_missing;
mod simd_paths;
