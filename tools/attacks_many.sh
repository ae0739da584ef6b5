#!/usr/bin/env bash
# The soak's hostile clients spread over many loopback addresses (127.0.0.2 and up), one attack at
# a time against a real server (640x480, 2 workers, --max-buffered-mb 256), each beside one fast
# client (the honest trainer) and a newcomer probe at every reading (a new connection, GetInfo and
# a one-sample stream): unread clip calls, stalled clip streams, unread pairs, clip readers,
# window-withholding streams, health watches; prompt readers of cheap-to-send clips, clip
# GetSample calls read and asked again, readers taking a message every 0.3-0.45 s, a mix of
# trickling, stalled and unread clients, zero-window streams from three addresses, unfinished
# Health/Check calls, pinging holders behind a 16 KiB window, one stream of 64 every-field clips.
# Each run prints its summary and its criteria line (the honest stream keeps >= 50% of its solo
# rate with no wait over 2 s, >= 90% of newcomers served, buffered <= the budget, RSS <= idle +
# budget x 1.25, no index lost or repeated); with RUNS > 1, the medians of the rate and the
# longest wait per attack close the output (docs/robustness.md, "Many addresses" and "An honest
# trainer beside each attack").
#   bash tools/attacks_many.sh [SECONDS] [RUNS] [ATTACK-NUMBERS...]   # default 45 s, 1 run, all
set -euo pipefail
cd "$(dirname "$0")/.."
secs="${1:-45}"
runs="${2:-1}"
shift $(($# > 2 ? 2 : $#))
only=" $* "
bin="${CARGO_TARGET_DIR:-$PWD/target}/release/mpiflow"
[ -x "$bin" ] || cargo build --release
base=(bench soak --seconds "$secs" --solo-s 10 --size 640x480 --workers 2 --fast 1 --stalled 0 --slow 0 --cancelling 0
  --uploading 0 --report-every-s 3)
attacks=(
  "100 unread clip calls from 50 addresses|--unread 50 --unread-calls 2 --hostile-frames 8 --attacker-addresses 50"
  "60 stalled clip streams from 60 addresses|--batch-stall 60 --hostile-frames 8 --attacker-addresses 60"
  "40 addresses x 2 unread GetSample calls (pairs)|--unread 40 --unread-calls 2 --attacker-addresses 40"
  "80 GetSample clip readers from 40 addresses|--unary 80 --hostile-frames 8 --attacker-addresses 40"
  "70 streams on one connection withholding window|--window-streams 70 --hostile-frames 8"
  "512 health watches from 4 addresses|--watch 512 --attacker-addresses 4"
  "16 prompt readers of valid+LZ4 clips from one address|--readers 16 --cheap --hostile-frames 8 --attacker-addresses 1"
  "40 addresses x 2 valid+LZ4 clip GetSample, read and asked again|--unary 80 --cheap --hostile-frames 8 --attacker-addresses 40"
  "32 clip GetSample from one address|--unary 32 --hostile-frames 8 --attacker-addresses 1"
  "50 clip readers taking a message every 0.3-0.45 s, 50 addresses|--trickle 50 --hostile-frames 8 --attacker-addresses 50"
  "30 trickling readers + 30 stalled streams + 20 unread calls, 80 addresses|--trickle 30 --batch-stall 30 --unread 20 --unread-calls 1 --hostile-frames 8 --attacker-addresses 80"
  "3 addresses x 22 zero-window clip streams, refusals asked again|--window-streams 66 --window-connections 3 --hostile-frames 8 --attacker-addresses 3"
  "512 unfinished Health/Check calls from 4 addresses|--unfinished 4 --unfinished-calls 128 --attacker-addresses 4"
  "7 pinging holders behind a 16 KiB window, 7 addresses|--ping-holders 7 --hostile-frames 8 --attacker-addresses 7"
  "one stream of 64 every-field clips, batch 64|--batch-stall 1 --hostile-frames 8"
)
med() { sort -n | awk '{a[NR] = $1} END {print (NR % 2) ? a[(NR + 1) / 2] : (a[NR / 2] + a[NR / 2 + 1]) / 2}'; }
out=$(mktemp)
trap 'rm -f "$out"' EXIT
echo "load before: $(cut -d' ' -f1-3 /proc/loadavg)"
for n in "${!attacks[@]}"; do
  num=$((n + 1))
  [ "$only" = "  " ] || [[ "$only" == *" $num "* ]] || continue
  name="${attacks[$n]%%|*}"
  read -r -a flags <<< "${attacks[$n]#*|}"
  : > "$out"
  for run in $(seq "$runs"); do
    echo "== $num. $name (run $run, load $(cut -d' ' -f1 /proc/loadavg)): ${flags[*]}"
    "$bin" "${base[@]}" "${flags[@]}" -- --max-buffered-mb 256 \
      | grep -E "^(solo|fast|server RSS|other|errors|soak:|buffered|criteria)|longest" | tee -a "$out" || true
  done
  if [ "$runs" -gt 1 ]; then
    rate=$(grep -o 'rate [0-9]*% of solo' "$out" | grep -o '[0-9]*' | med)
    wait=$(grep -o 'longest wait [0-9]* ms (<=' "$out" | grep -o '[0-9]*' | med)
    echo "-- $num. median of $runs runs: rate $rate% of solo, longest wait $wait ms"
  fi
done
echo "load after: $(cut -d' ' -f1-3 /proc/loadavg)"
