#!/usr/bin/env bash
# The project's whole test suite (the README's test command). Installs what the tests need:
# a Python environment in .venv with ONNX Runtime (the library mpiflow loads), onnx, numpy,
# pillow and webdataset (the independent readers the tests compare against), and the Python
# client (clients/python) with grpcio, lz4 and pytest for its tests against the real server.
set -euo pipefail
cd "$(dirname "$0")/.."
eval "$(bash tools/setup_python.sh)"
cargo test --release --all-targets --all-features
# The run above takes the widest vector path this CPU has (mpiflow::isa; tests/process/simd_paths.rs
# compares every path's bytes in one process); the determinism tests again on the SSE2 baseline.
MPIFLOW_SIMD=sse2 cargo test --release --all-features --test render -- reference_vectors:: render_window:: \
    pipeline:: laws::
MPIFLOW_SIMD=sse2 cargo test --release --all-features --test process -- simd_paths::
# The Python client against the real `mpiflow serve` (built by cargo test above).
MPIFLOW_BIN="${CARGO_TARGET_DIR:-$PWD/target}/release/mpiflow" "$MPIFLOW_PYTHON" -m pytest -q clients/python/tests
# The target view's instructions per plane sample against their recorded figures (counted by
# cachegrind, not timed: tools/instructions.sh).
bash tools/instructions.sh "${CARGO_TARGET_DIR:-$PWD/target}/release/mpiflow"
# The Kubernetes manifests against the Kubernetes JSON schemas, offline (deploy/validate.sh).
bash deploy/validate.sh
