#!/usr/bin/env bash
# The target view's instructions per plane sample, counted (not timed) and held to a budget.
#
# Cachegrind counts the instructions of `mpiflow bench render` at 320x240, 32 planes, one
# thread, the target pass only (the planes' own depths, or `--true-depth`: every texel at its
# pixel's depth, the true-depth layering's search), with 5 runs and with 1 run: the difference over 4 is one render
# (the synthetic MPI, its prefilter and the warm-up render cancel out), and that render's plane
# samples come from the bench's own count. Counts are deterministic for a binary and a path, so
# the check has no noise; a vector path valgrind cannot run (AVX-512) is not counted.
#
# Usage: tools/instructions.sh [BIN]      (default: target/release/mpiflow)
# Fails when a path's count exceeds its recorded figure in tools/instructions.budget by more
# than 20%. After a change that lowers a count, record the new figure there.
set -euo pipefail
cd "$(dirname "$0")/.."
BIN="${1:-${CARGO_TARGET_DIR:-$PWD/target}/release/mpiflow}"
BUDGET=tools/instructions.budget
if ! command -v valgrind >/dev/null; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
        apt-get install -y -qq valgrind >/dev/null || { apt-get update -qq && apt-get install -y -qq valgrind >/dev/null; }
    fi
    command -v valgrind >/dev/null || { echo "instructions.sh: valgrind is needed (apt-get install valgrind)" >&2; exit 1; }
fi
[ -x "$BIN" ] || { echo "instructions.sh: no binary at $BIN (cargo build --release first)" >&2; exit 1; }
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT

# one count: prints "<instructions> <plane samples>"
count() {
    local path=$1 layers=$2 runs=$3 flag=()
    [ "$layers" = true-depth ] && flag=(--true-depth)
    MPIFLOW_SIMD=$path valgrind --tool=cachegrind --cache-sim=no --cachegrind-out-file="$tmp/cg.out" \
        "$BIN" bench render --width 320 --height 240 --planes 32 --threads 1 --pass target --runs "$runs" "${flag[@]}" \
        >"$tmp/out" 2>"$tmp/err" || { cat "$tmp/out" "$tmp/err" >&2; return 1; }
    local refs samples
    refs=$(grep -E 'I[[:space:]]+refs:' "$tmp/err" | sed 's/.*refs://' | tr -dc '0-9')
    samples=$(grep -oE '[0-9]+ target-view plane samples' "$tmp/out" | cut -d' ' -f1)
    [ -n "$refs" ] && [ -n "$samples" ] || { cat "$tmp/out" "$tmp/err" >&2; return 1; }
    echo "$refs $samples"
}

status=0
while read -r path layers recorded; do
    case "$path" in ''|'#'*) continue ;; esac
    # a failed count stops the script here (set -e), with the bench's output on stderr
    one=$(count "$path" "$layers" 1)
    five=$(count "$path" "$layers" 5)
    line=$(python3 - "$path $layers" "$recorded" $one $five <<'PY'
import sys
path, recorded, one, samples, five, _ = sys.argv[1], float(sys.argv[2]), *map(int, sys.argv[3:])
per, limit = (five - one) / 4 / samples, recorded * 1.2
verdict = "ok" if per <= limit else "FAIL"
print(f"{verdict} instructions per plane sample, {path} path: {per:.1f} ({(five - one) // 4} per render, "
      f"{samples} plane samples); recorded {recorded}, limit {limit:.1f}: {verdict}")
PY
)
    echo "${line#* }"
    [ "${line%% *}" = ok ] || status=1
done <"$BUDGET"
exit $status
