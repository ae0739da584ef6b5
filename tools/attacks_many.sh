#!/usr/bin/env bash
# The soak's hostile clients spread over many loopback addresses (127.0.0.2 and up), one attack at
# a time against a real server (640x480, 2 workers, --max-buffered-mb 256), each beside one fast
# client and a newcomer probe: unread clip calls, stalled clip streams, unread pairs, clip readers,
# streams on one connection that grants no HTTP/2 window, health watches. Prints each run's summary
# (docs/robustness.md, "Many addresses").
#   bash tools/attacks_many.sh
set -euo pipefail
cd "$(dirname "$0")/.."
bin="${CARGO_TARGET_DIR:-$PWD/target}/release/mpiflow"
[ -x "$bin" ] || cargo build --release
base=(bench soak --seconds 45 --solo-s 10 --size 640x480 --workers 2 --fast 1 --stalled 0 --slow 0 --cancelling 0 --uploading 0 --report-every-s 3)
run() { local name="$1"; shift; echo "== $name: $*"; "$bin" "${base[@]}" "$@" -- --max-buffered-mb 256 | grep -E "^(solo|fast|server RSS|other|errors|soak:|buffered)|longest" || true; }
echo "load before: $(cut -d' ' -f1-3 /proc/loadavg)"
run "100 unread clip calls from 50 addresses" --unread 50 --unread-calls 2 --hostile-frames 8 --attacker-addresses 50
run "60 stalled clip streams from 60 addresses" --batch-stall 60 --hostile-frames 8 --attacker-addresses 60
run "40 addresses x 2 unread GetSample calls (pairs)" --unread 40 --unread-calls 2 --attacker-addresses 40
run "80 GetSample clip readers from 40 addresses" --unary 80 --hostile-frames 8 --attacker-addresses 40
run "70 streams on one connection withholding window" --window-streams 70 --hostile-frames 8
run "512 health watches from 4 addresses" --watch 512 --attacker-addresses 4
echo "load after: $(cut -d' ' -f1-3 /proc/loadavg)"
