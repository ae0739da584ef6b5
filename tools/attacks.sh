#!/usr/bin/env bash
# The hostile clients of `mpiflow bench soak`, one attack at a time against a real server
# (640x480, 2 workers, --max-buffered-mb 256), each beside one fast client and a newcomer probe:
# a flood of GetSample calls, GetSample replies never read, idle HTTP/2 connections, stalled
# streams with batch 64, then all of them at once. Prints each run's summary (docs/robustness.md).
#   bash tools/attacks.sh [SECONDS]      # default 60 s per attack
set -euo pipefail
cd "$(dirname "$0")/.."
secs="${1:-60}"
bin="${CARGO_TARGET_DIR:-$PWD/target}/release/mpiflow"
[ -x "$bin" ] || cargo build --release
base=(bench soak --seconds "$secs" --solo-s 10 --size 640x480 --workers 2 --fast 1 --stalled 0 --slow 0
  --cancelling 0 --uploading 0 --report-every-s 5)
run() {
  local name="$1"; shift
  echo "== $name: $*"
  "$bin" "${base[@]}" "$@" -- --max-buffered-mb 256 | grep -E "^(solo|fast|server RSS|other|errors|soak:)|longest" || true
}
echo "load before: $(cut -d' ' -f1-3 /proc/loadavg)"
run "unary flood" --unary 150
run "unread replies" --unread 75
run "idle connections" --idle 520
run "batch stalls" --batch-stall 10
run "all at once" --unary 150 --unread 75 --idle 520 --batch-stall 10
echo "load after: $(cut -d' ' -f1-3 /proc/loadavg)"
