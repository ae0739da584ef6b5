#!/usr/bin/env bash
# The project's whole test suite (the README's test command). Installs what the tests need:
# a Python environment in .venv with ONNX Runtime (the library mpiflow loads), onnx, numpy,
# pillow and webdataset (the independent readers the tests compare against).
set -euo pipefail
cd "$(dirname "$0")/.."
eval "$(bash tools/setup_python.sh)"
cargo test --release --all-targets
