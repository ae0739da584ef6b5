#!/usr/bin/env bash
# The target view's instructions per plane sample, counted (not timed) and held to a budget.
#
# Cachegrind counts the instructions of `mpiflow bench render` at 320x240, 32 planes, one
# thread, the target pass only, with 5 runs and with 1 run: the difference over 4 is one render
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
    local path=$1 runs=$2
    MPIFLOW_SIMD=$path valgrind --tool=cachegrind --cache-sim=no --cachegrind-out-file="$tmp/cg.out" \
        "$BIN" bench render --width 320 --height 240 --planes 32 --threads 1 --pass target --runs "$runs" \
        >"$tmp/out" 2>"$tmp/err" || { cat "$tmp/out" "$tmp/err" >&2; return 1; }
    local refs samples
    refs=$(grep -E 'I[[:space:]]+refs:' "$tmp/err" | sed 's/.*refs://' | tr -dc '0-9')
    samples=$(grep -oE '[0-9]+ target-view plane samples' "$tmp/out" | cut -d' ' -f1)
    [ -n "$refs" ] && [ -n "$samples" ] || { cat "$tmp/out" "$tmp/err" >&2; return 1; }
    echo "$refs $samples"
}

status=0
while read -r path recorded; do
    case "$path" in ''|'#'*) continue ;; esac
    read -r one samples < <(count "$path" 1)
    read -r five _ < <(count "$path" 5)
    per=$(python3 -c "print(f'{($five - $one) / 4 / $samples:.1f}')")
    limit=$(python3 -c "print(f'{$recorded * 1.2:.1f}')")
    verdict=$(python3 -c "print('ok' if $per <= $recorded * 1.2 else 'FAIL')")
    echo "instructions per plane sample, $path path: $per ($(( (five - one) / 4 )) per render, $samples plane samples); recorded $recorded, limit $limit: $verdict"
    [ "$verdict" = ok ] || status=1
done <"$BUDGET"
exit $status
