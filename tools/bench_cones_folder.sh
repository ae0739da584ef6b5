#!/usr/bin/env bash
# The folder throughput of photos with complex depth: a folder of 48 crops of Cones with its
# measured depth (tools/make_rgbd_folder.py --sources cones --no-masks: crops at random positions
# and scales, resized to 640x480 up to 1920x1080, every 8th 4032x3024; no masks) served with the
# default settings, RAFT's 496x368 random crops pulled, 264 samples (three windows of 11 photos x
# 8 motions) on a fresh server per run, three runs. Prints each run's samples/s, the scene cache's
# misses and evictions per 8 samples (the server's metrics), the median and the load average.
#
#   bash tools/bench_cones_folder.sh [BIN] [DIR]     (defaults: target/release/mpiflow, /tmp/cones48)
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=${1:-target/release/mpiflow}
DIR=${2:-/tmp/cones48}
COUNT=264
PY=${PYTHON:-python3}
[ -d "$DIR/images" ] || "$PY" tools/make_rgbd_folder.py "$DIR" --sources cones --no-masks >/dev/null
LOG=$(mktemp -d)
trap 'rm -rf "$LOG"' EXIT
metric() { curl -s "http://$2/metrics" | awk -v m="$1" '$1 == m { print $2 }'; }
rates=()
for run in 1 2 3; do
  # a free port for the metrics: the kernel's choice, released just before the server binds it
  MPORT=$("$PY" -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
  "$BIN" serve --source "$DIR" --addr 127.0.0.1:0 --metrics-addr "127.0.0.1:$MPORT" >"$LOG/out" 2>"$LOG/err" &
  PID=$!
  # the first line on stdout says the server listens
  until grep -q "serving on" "$LOG/out"; do
    kill -0 "$PID" 2>/dev/null || { cat "$LOG/err" >&2; exit 1; }
    sleep 0.2
  done
  ADDR=$(awk '/serving on/ { print $4 }' "$LOG/out")
  PULL=$("$BIN" pull --addr "$ADDR" --count "$COUNT" --crop 496x368 --random-crop 2>&1 | tail -1)
  RATE=$(echo "$PULL" | sed -n 's/.* \([0-9.]*\) samples\/s.*/\1/p')
  MISSES=$(metric mpiflow_scene_cache_misses_total "127.0.0.1:$MPORT")
  EVICTIONS=$(metric mpiflow_scene_cache_evictions_total "127.0.0.1:$MPORT")
  kill "$PID"
  wait "$PID" || true
  rates+=("$RATE")
  echo "run $run: $RATE samples/s; scene cache misses $MISSES, evictions $EVICTIONS over $COUNT samples" \
    "($(awk -v m="$MISSES" -v c="$COUNT" 'BEGIN { printf "%.2f", 8 * m / c }') misses per 8 samples)"
  [ "$run" = 1 ] && grep -m1 "dataset opened" "$LOG/err" | sed 's/.*source=/dataset: /'
done
MEDIAN=$(printf '%s\n' "${rates[@]}" | sort -n | sed -n 2p)
echo "median $MEDIAN samples/s over $COUNT samples; load average $(cut -d' ' -f1-3 /proc/loadavg), $(nproc) cores"
