#!/usr/bin/env bash
# The long fuzz run: every harness of tests/fuzz.rs for M minutes each (default 5), then a table
# of inputs tried, time and failures per target. Failing inputs are saved under
# $CARGO_TARGET_DIR/tmp/fuzz-failures/ (replay one with MPIFLOW_FUZZ_CASE=i).
#   bash tools/fuzz.sh [--minutes M] [--target NAME]   (NAME: a test name of tests/fuzz.rs, e.g. fuzz_pfm)
# The bounded CI run is part of `cargo test` (a fixed number of inputs per target).
set -euo pipefail
cd "$(dirname "$0")/.."
minutes=5
target=fuzz_
while [ $# -gt 0 ]; do
  case "$1" in
    --minutes) minutes="$2"; shift 2 ;;
    --target) target="$2"; shift 2 ;;
    *) echo "usage: bash tools/fuzz.sh [--minutes M] [--target NAME]" >&2; exit 2 ;;
  esac
done
seconds=$(python3 -c "import sys; print(max(1, round(float(sys.argv[1]) * 60)))" "$minutes")
log="${CARGO_TARGET_DIR:-$PWD/target}/fuzz-$(date -u +%Y%m%dT%H%M%SZ).log"
echo "fuzzing each target for $seconds s (log: $log)"
set +e
MPIFLOW_FUZZ_SECONDS="$seconds" cargo test --release --test fuzz "$target" -- --nocapture --test-threads 1 2>&1 | tee "$log" \
  | grep -E '^fuzz |^test result|case [0-9]+ \('
status=${PIPESTATUS[0]}
set -e
total=$(grep -E '^fuzz ' "$log" | awk '{n += $3} END {print n + 0}')
echo "total: $total inputs; exit status $status"
exit "$status"
