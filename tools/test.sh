#!/usr/bin/env bash
# The project's whole test suite (the README's test command). Installs what the tests need:
# a Python environment in .venv with ONNX Runtime (the library mpiflow loads), onnx, numpy,
# pillow and webdataset (the independent readers the tests compare against), and the Python
# client (clients/python) with grpcio, lz4 and pytest for its tests against the real server.
set -euo pipefail
cd "$(dirname "$0")/.."
eval "$(bash tools/setup_python.sh)"
cargo test --release --all-targets --all-features
# The Python client against the real `mpiflow serve` (built by cargo test above).
MPIFLOW_BIN="${CARGO_TARGET_DIR:-$PWD/target}/release/mpiflow" "$MPIFLOW_PYTHON" -m pytest -q clients/python/tests
# The Kubernetes manifests against the Kubernetes JSON schemas, offline (deploy/validate.sh).
bash deploy/validate.sh
