#!/usr/bin/env bash
# The project's whole test suite (the README's test command). Installs what the tests need.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo test --release --all-targets
